//! Prequential σ calibration: each new scan tests the maps as they stood before it arrived.
//!
//! A stratified sample of the scan's returns is answered by [`query::raw_elevation`] over the
//! snapshot from before the scan. Each return is a fresh, independent measurement of ground the
//! maps already claim to know, so its residual against the answer, with the return's own noise
//! taken out, tells how wide the answer's σ should have been. Residuals are weighted by the ground
//! area their return stands for and kept per (source, grazing class, range bin from the answering
//! sensor) over the last scans; within a cell, each fifth of them by the answer's own σ gets the
//! factor on σ whose 68 % and 95 % intervals cover that share. Nothing here knows the terrain or
//! the sensor: it adapts to whatever the robot drives on, and follows it when the terrain changes
//! (the oldest residuals drop out). Figures: docs/EVALUATION.md "Calibration". Every
//! [`PAIR_EVERY_SCANS`] scans, pairs of returns a footprint apart also measure how the maps'
//! errors correlate ([`super::correlation`]), and the held residuals give the errors' tail shape
//! ([`TailShape`]): what planner layers turn height σ into slope σ and risks with.

use super::correlation::{CorrelationLearner, PairResidual, PAIR_SEPARATION_M};
use super::query::{self, Answerer};
use super::relief::ReliefLearner;
use super::scales::{
    bin_of, class_of, BinScale, ScaleTable, SigmaScales, TailShape, BINS, CLASSES, SIGMA_GROUPS,
};
use super::window::MapSnapshot;
use super::LocalRangeMap;
use crate::gp::sphere;
use crate::scan::ScanInput;
use nalgebra::Vector3;
use rangegp_proto::msg::Source;
use std::collections::{HashMap, VecDeque};

/// Step of the finite differences that give a return's surface normal, radians (0.1°).
const NORMAL_STEP_RAD: f64 = 1.745e-3;
/// Floor of the cosine between a ray and the surface normal in a return's area weight (a
/// return grazing the surface at under 3° counts as if at 3°).
const MIN_COS_INCIDENCE: f64 = 0.05;
/// Returns sampled per range bin from each scan.
pub const PER_BIN_PER_SCAN: usize = 48;
/// Residuals a bin remembers (about 30 scans at the full quota).
pub const BIN_MEMORY: usize = 1500;
/// A bin's scale stays 1 (the map's own, leave-one-out-calibrated σ) until it holds this many.
pub const MIN_RESIDUALS: usize = 40;
/// Bounds of a scale: σ is never shrunk below a tenth nor widened past a hundredfold.
pub const SCALE_BOUNDS: (f64, f64) = (0.1, 100.0);

/// One tested answer: squared residual, the answer's variance and the return's own noise
/// variance along z, m².
#[derive(Debug, Clone, Copy, Default)]
struct Residual {
    r2: f64,
    var: f64,
    noise_var: f64,
    /// Ground area the return stands for, relative ([`area_weight`]).
    weight: f64,
    /// The answer's distance to its map's nearest datum, metres.
    data_m: f64,
    /// The relief variance unseen at that distance (window answers with the relief in heights;
    /// else 0), m²: added to the scaled variance, as the snapshot adds it.
    relief_var: f64,
}

/// Recent residuals of one source, by grazing class and range bin.
type Residuals = [[VecDeque<Residual>; BINS]; CLASSES];

/// The fitter's calibration state: recent residuals per cell and the scales they give.
#[derive(Debug, Clone, Default)]
pub struct Calibrator {
    window: Residuals,
    aggregate: Residuals,
    correlation: CorrelationLearner,
    relief: ReliefLearner,
    scales: SigmaScales,
}

impl Calibrator {
    /// A calibrator with nothing learnt. It learns the relief unseen between data
    /// ([`super::relief`]) from maps that index their data, for planner layers; with
    /// `relief_in_heights` it also adds it to window answers' σ (`gp.unseen_relief`).
    pub fn new(relief_in_heights: bool) -> Self {
        let mut calibrator = Self::default();
        calibrator.scales.relief_in_heights = relief_in_heights;
        calibrator
    }

    /// The current scales.
    pub fn scales(&self) -> SigmaScales {
        self.scales
    }

    /// Residuals held, window then aggregate, by range bin (all grazing classes).
    #[cfg(test)]
    pub fn counts(&self) -> ([usize; BINS], [usize; BINS]) {
        let count = |r: &Residuals| std::array::from_fn(|b| r.iter().map(|c| c[b].len()).sum());
        (count(&self.window), count(&self.aggregate))
    }

    /// Tests `snapshot` (the maps before `scan`) against a stratified sample of `scan`'s returns
    /// and updates the scales; `map` is the scan's own fitted map, which gives each return's
    /// surface normal (the ground area it stands for). Returns how many returns were answered.
    /// Does nothing before the first map.
    pub fn observe(&mut self, snapshot: &MapSnapshot, scan: &ScanInput, map: &LocalRangeMap) -> usize {
        let Some(newest) = snapshot.maps().first() else {
            return 0;
        };
        let relief_before = self.scales.relief;
        self.relief.observe(scan, map);
        self.scales.relief = self.relief.relief();
        let in_heights = self.scales.relief_in_heights;
        let reference = newest.sensor_position();
        let sample = stratified_sample(scan, map, &reference);
        let answers = query::par_map(
            &sample,
            rayon::current_num_threads(),
            |&(p, noise_var, weight)| {
                let a = query::raw_elevation(snapshot, p.x, p.y)?;
                Some((p, noise_var, weight, a))
            },
        );
        let mut touched = [false; 2];
        let mut answered = 0;
        for (p, noise_var, weight, a) in answers.into_iter().flatten() {
            let r2 = (p.z - a.estimate.z).powi(2);
            if !(r2.is_finite() && a.estimate.var.is_finite()) {
                continue;
            }
            let (bins, which) = match a.by {
                Answerer::Aggregate => (&mut self.aggregate, 1),
                Answerer::Window(_) => (&mut self.window, 0),
            };
            let q = &mut bins[class_of(a.estimate.grazing)][bin_of(a.rho_m)];
            if q.len() == BIN_MEMORY {
                q.pop_front();
            }
            q.push_back(Residual {
                r2,
                var: a.estimate.var.max(1e-14),
                noise_var,
                weight,
                data_m: a.estimate.data_m,
                relief_var: 0.0,
            });
            touched[which] = true;
            answered += 1;
        }
        // The relief learnt from this scan applies to every held window residual (the new ones
        // included), and the window's scales are refitted under it.
        let relief = self.scales.relief;
        if in_heights {
            for r in self.window.iter_mut().flatten().flatten() {
                r.relief_var = relief.var_at(r.data_m);
            }
        }
        if touched[0] || (in_heights && relief != relief_before) {
            self.scales.window = table_of(&self.window);
        }
        if touched[1] {
            self.scales.aggregate = table_of(&self.aggregate);
        }
        if touched[0] || touched[1] {
            self.scales.tails = self.tails();
        }
        if scan.sequence.is_multiple_of(PAIR_EVERY_SCANS) {
            let pairs = self.pairs(snapshot, scan, &sample);
            self.correlation.observe(&pairs);
            self.scales.correlation = self.correlation.correlation();
        }
        answered
    }

    /// Pairs of `scan`'s returns a footprint apart ([`PAIR_SEPARATION_M`]), each sampled return
    /// with the nearest other return in that band, both answered by `snapshot` (the maps before
    /// the scan) with σ calibrated by the current scales.
    fn pairs(
        &self,
        snapshot: &MapSnapshot,
        scan: &ScanInput,
        sample: &[(Vector3<f64>, f64, f64)],
    ) -> Vec<PairResidual> {
        let cell = PAIR_SEPARATION_M.1;
        let key = |p: &Vector3<f64>| ((p.x / cell).floor() as i64, (p.y / cell).floor() as i64);
        let origin = scan.pose.translation.vector;
        let mut cells: HashMap<(i64, i64), Vec<Return>> = HashMap::new();
        for ray in &scan.rays {
            let [x, y, z] = sphere::to_sphere(ray.inclination, ray.azimuth, 1.0);
            let dir = scan.pose.rotation * Vector3::new(x, y, z);
            let p = origin + dir * ray.range;
            let sd = scan.range_sd(ray.range) * dir.z;
            cells.entry(key(&p)).or_default().push((p, sd * sd));
        }
        let partner = |p: &Vector3<f64>| -> Option<Return> {
            let (i, j) = key(p);
            let mut best: Option<(f64, Vector3<f64>, f64)> = None;
            for di in -1..=1 {
                for dj in -1..=1 {
                    for &(q, noise) in cells.get(&(i + di, j + dj)).into_iter().flatten() {
                        let d = (q.x - p.x).hypot(q.y - p.y);
                        let inside = (PAIR_SEPARATION_M.0..=PAIR_SEPARATION_M.1).contains(&d);
                        if inside && best.is_none_or(|(b, _, _)| d < b) {
                            best = Some((d, q, noise));
                        }
                    }
                }
            }
            best.map(|(_, q, noise)| (q, noise))
        };
        let answer = |p: &Vector3<f64>| -> Option<(f64, f64)> {
            let a = query::raw_elevation(snapshot, p.x, p.y)?;
            let source = match a.by {
                Answerer::Aggregate => Source::Aggregate,
                Answerer::Window(_) => Source::Window,
            };
            let var = self.scales.calibrate(source, a.rho_m, &a.estimate).var_m2;
            Some((p.z - a.estimate.z, var.sqrt()))
        };
        query::par_map(sample, rayon::current_num_threads(), |&(p, noise_p, _)| {
            let (q, noise_q) = partner(&p)?;
            let (ep, sp) = answer(&p)?;
            let (eq, sq) = answer(&q)?;
            Some(PairResidual {
                residual_m: [ep, eq],
                sd_m: [sp, sq],
                noise_var_m2: [noise_p, noise_q],
                separation_m: (q.x - p.x).hypot(q.y - p.y),
            })
        })
        .into_iter()
        .flatten()
        .collect()
    }

    /// The shape of the calibrated errors: the shares of every held residual (both sources,
    /// weighted by area) within ±1 and ±1.96 calibrated σ, fitted by [`TailShape::fit`];
    /// Gaussian until [`MIN_TAIL_RESIDUALS`] are held.
    fn tails(&self) -> TailShape {
        let mut inside = [0.0; 2];
        let mut total = 0.0;
        let mut count = 0;
        for (residuals, table) in [
            (&self.window, &self.scales.window),
            (&self.aggregate, &self.scales.aggregate),
        ] {
            for (c, bins) in residuals.iter().enumerate() {
                for (b, q) in bins.iter().enumerate() {
                    for r in q {
                        let f = table[c][b].factor(r.var.sqrt());
                        let latent = f * f * r.var + r.relief_var;
                        if r.noise_var > LATENT_SHARE * latent {
                            continue;
                        }
                        let v = latent + r.noise_var;
                        let w = r.weight.max(1e-9);
                        total += w;
                        count += 1;
                        for (share, k) in inside.iter_mut().zip([1.0, 1.96]) {
                            if r.r2 <= k * k * v {
                                *share += w;
                            }
                        }
                    }
                }
            }
        }
        if count < MIN_TAIL_RESIDUALS {
            return TailShape::default();
        }
        TailShape::fit(inside[0] / total, inside[1] / total)
    }
}

/// A return in map coordinates with its noise variance along z, m².
type Return = (Vector3<f64>, f64);

/// Every this many scans (by sequence) pairs of returns test how the maps' errors correlate (the
/// pairs need every return in a spatial hash: a few milliseconds for an OS1-64 scan).
pub const PAIR_EVERY_SCANS: u64 = 2;

/// Only residuals whose return noise variance is at most this share of the answer's calibrated
/// variance show the shape: the rest are mostly the return's own (Gaussian) noise, which would
/// hide the heavy tails of the map's errors that planner risks are about.
pub const LATENT_SHARE: f64 = 0.25;

/// Residuals held before the tail shape is fitted (a Gaussian until then).
pub const MIN_TAIL_RESIDUALS: usize = 400;

/// Up to [`PER_BIN_PER_SCAN`] returns of `scan` per range bin from `reference` (a sensor position),
/// spread over the scan by a stride coprime with its size; each as a map point, its noise
/// variance along z and the ground area it stands for ([`area_weight`]).
fn stratified_sample(
    scan: &ScanInput,
    map: &LocalRangeMap,
    reference: &Vector3<f64>,
) -> Vec<(Vector3<f64>, f64, f64)> {
    let n = scan.rays.len();
    let mut quota = [PER_BIN_PER_SCAN; BINS];
    let mut out = Vec::with_capacity(BINS * PER_BIN_PER_SCAN);
    if n == 0 {
        return out;
    }
    let stride = coprime_stride(n);
    let origin = scan.pose.translation.vector;
    let mut k = (scan.sequence as usize).wrapping_mul(2_654_435_761) % n;
    for _ in 0..n {
        let ray = &scan.rays[k];
        k = (k + stride) % n;
        let [x, y, z] = sphere::to_sphere(ray.inclination, ray.azimuth, 1.0);
        let dir = scan.pose.rotation * Vector3::new(x, y, z);
        let p = origin + dir * ray.range;
        let bin = bin_of((p.x - reference.x).hypot(p.y - reference.y));
        if quota[bin] == 0 {
            continue;
        }
        quota[bin] -= 1;
        let sd = scan.range_sd(ray.range) * dir.z;
        let weight = area_weight(scan, map, ray.inclination, ray.azimuth, ray.range);
        out.push((p, sd * sd, weight));
        if quota.iter().all(|&q| q == 0) {
            break;
        }
    }
    out
}

/// The ground-plane area a return stands for per unit solid angle: r² · |n_z| / |cos i|, where n
/// is the surface normal (from the scan's own map: the cross product of its surface's tangents
/// along inclination and azimuth) and i the angle between ray and normal. Returns sample the
/// ground by solid angle while a planner asks about it by area: faces turned toward the sensor
/// are over-sampled, grazed ground under-sampled, and vertical faces, which hold no ground area,
/// carry no weight.
fn area_weight(scan: &ScanInput, map: &LocalRangeMap, inclination: f64, azimuth: f64, range: f64) -> f64 {
    let surface = |inc: f64, az: f64| {
        let [x, y, z] = sphere::to_sphere(inc, az, 1.0);
        Vector3::new(x, y, z) * map.predict_range(inc, az).0
    };
    let at = surface(inclination, azimuth);
    let along_inc = surface(inclination + NORMAL_STEP_RAD, azimuth) - at;
    let along_az = surface(inclination, azimuth + NORMAL_STEP_RAD) - at;
    let Some(normal) = along_inc.cross(&along_az).try_normalize(1e-12) else {
        return 0.0;
    };
    let [x, y, z] = sphere::to_sphere(inclination, azimuth, 1.0);
    let cos_incidence = Vector3::new(x, y, z).dot(&normal).abs();
    let up = (scan.pose.rotation * normal).z.abs();
    let weight = range * range * up / cos_incidence.max(MIN_COS_INCIDENCE);
    if weight.is_finite() {
        weight
    } else {
        0.0
    }
}

/// A stride near n·0.618 that shares no factor with `n`, so that stepping by it visits every index.
fn coprime_stride(n: usize) -> usize {
    let gcd = |mut a: usize, mut b: usize| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let mut s = ((n as f64 * 0.618_033_988_7) as usize).max(1);
    while gcd(s, n) != 1 {
        s += 1;
    }
    s
}

/// The scales of one source. A cell with fewer than [`MIN_RESIDUALS`] takes the scales of the
/// nearest range bin of its grazing class that has them (the wider, between two as near); a
/// class with none at all takes the nearest class's. So an empty cell neither pulls its
/// neighbours' interpolation toward 1 nor answers with the map's raw σ.
fn table_of(residuals: &Residuals) -> ScaleTable {
    let rows: Vec<Option<[BinScale; BINS]>> = residuals.iter().map(row_of).collect();
    let width = |row: &[BinScale; BINS]| row.iter().map(BinScale::width).sum::<f64>();
    std::array::from_fn(|c| nearest_filled(&rows, c, width).unwrap_or_default())
}

/// One grazing class's scales by range bin, gaps filled from the nearest bin; `None` when no
/// bin has [`MIN_RESIDUALS`].
fn row_of(bins: &[VecDeque<Residual>; BINS]) -> Option<[BinScale; BINS]> {
    let learnt: Vec<Option<BinScale>> = bins
        .iter()
        .map(|b| (b.len() >= MIN_RESIDUALS).then(|| bin_scale_of(b)))
        .collect();
    learnt
        .iter()
        .any(Option::is_some)
        .then(|| std::array::from_fn(|k| nearest_filled(&learnt, k, BinScale::width).unwrap_or_default()))
}

/// `items[k]` if present, else the nearest present one (of two as near, the one `width` calls
/// wider).
fn nearest_filled<T: Copy>(items: &[Option<T>], k: usize, width: impl Fn(&T) -> f64) -> Option<T> {
    (0..items.len()).find_map(|d| {
        let below = k.checked_sub(d).and_then(|i| items[i]);
        let above = items.get(k + d).copied().flatten();
        match (below, above) {
            (Some(a), Some(b)) => Some(if width(&a) >= width(&b) { a } else { b }),
            (a, b) => a.or(b),
        }
    })
}

/// The scales of one bin: its residuals sorted by the answer's σ, cut into [`SIGMA_GROUPS`]
/// groups of equal count when each can hold [`MIN_RESIDUALS`] (else one group for all).
fn bin_scale_of(residuals: &VecDeque<Residual>) -> BinScale {
    let mut sorted: Vec<Residual> = residuals.iter().copied().collect();
    sorted.sort_by(|a, b| a.var.total_cmp(&b.var));
    let mut out = BinScale::default();
    if sorted.is_empty() {
        return out;
    }
    let group = |g: &[Residual]| (0.5 * g[g.len() / 2].var.ln(), scale_of(g));
    if sorted.len() < SIGMA_GROUPS * MIN_RESIDUALS {
        // One group: every slot holds the whole bin's scale.
        let (log_sd, scale) = group(&sorted);
        out.log_sd = [log_sd; SIGMA_GROUPS];
        out.scale = [scale; SIGMA_GROUPS];
        return out;
    }
    let n = sorted.len();
    for k in 0..SIGMA_GROUPS {
        (out.log_sd[k], out.scale[k]) = group(&sorted[k * n / SIGMA_GROUPS..(k + 1) * n / SIGMA_GROUPS]);
    }
    out
}

/// The σ scale of one group: within the band where 93–97 % of residuals fall inside 1.96 σ and
/// 62–74 % inside 1 σ, the one nearest to 95 % coverage; where heavy tails leave no such band, the
/// geometric middle of the two demands. 1 until [`MIN_RESIDUALS`] are held. Never below 1 where
/// most of the group's weight lies in residuals whose return noise exceeds the map's own
/// variance ([`noise_dominated`]): those residuals cannot show a map too unsure, only one too
/// sure.
fn scale_of(residuals: &[Residual]) -> f64 {
    if residuals.len() < MIN_RESIDUALS {
        return 1.0;
    }
    let least = if noise_dominated(residuals) {
        1.0
    } else {
        SCALE_BOUNDS.0
    };
    let at = |k: f64, share: f64| scale_for_coverage(residuals, k, share);
    let target = at(1.96, 0.95);
    let lo = at(1.96, 0.93).max(at(1.0, 0.62));
    let hi = at(1.96, 0.97).min(at(1.0, 0.74));
    let s = if lo <= hi {
        target.clamp(lo, hi)
    } else {
        (lo * hi).sqrt()
    };
    s.clamp(least, SCALE_BOUNDS.1)
}

/// Whether most of the residuals' weight ([`weight_in`]) lies where the return's own noise
/// variance exceeds the map's variance. A return 3 cm noisy tests a map of 5 mm σ hardly at all:
/// any scale of σ down to the smallest covers it, so the bisection would shrink σ to its bound
/// (seen near a VLP-16, whose 3 cm floor the daemon measures). The unseen relief does not count
/// here: it is part of the answer's σ, so a scale it makes small still leaves σ covering.
fn noise_dominated(residuals: &[Residual]) -> bool {
    let weight = weight_in(residuals);
    let all: f64 = residuals.iter().map(&weight).sum();
    let noisy: f64 = residuals
        .iter()
        .filter(|r| r.noise_var > r.var)
        .map(&weight)
        .sum();
    noisy > 0.5 * all
}

/// Each residual's weight among `residuals`: the ground area it stands for, or 1 each where the
/// weights sum to nothing (every return on a vertical face).
fn weight_in(residuals: &[Residual]) -> impl Fn(&Residual) -> f64 {
    let by_area = residuals.iter().map(|r| r.weight).sum::<f64>() > 0.0;
    move |r: &Residual| if by_area { r.weight } else { 1.0 }
}

/// The smallest scale s (bisection in log s over [`SCALE_BOUNDS`]) at which a `share` of the
/// residuals lies within k·sqrt(s²·var + relief_var + noise_var).
fn scale_for_coverage(residuals: &[Residual], k: f64, share: f64) -> f64 {
    let weight = weight_in(residuals);
    let need = share * residuals.iter().map(&weight).sum::<f64>();
    let covered = |s: f64| {
        let s2 = s * s;
        residuals
            .iter()
            .filter(|r| r.r2 <= k * k * (s2 * r.var + r.relief_var + r.noise_var))
            .map(&weight)
            .sum::<f64>()
    };
    let (mut lo, mut hi) = (SCALE_BOUNDS.0.ln(), SCALE_BOUNDS.1.ln());
    for _ in 0..30 {
        let mid = 0.5 * (lo + hi);
        if covered(mid.exp()) >= need {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi.exp()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{family_terrain, params, scan_of};
    use crate::map::Window;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use rangegp_sim::Heightmap;
    use std::sync::Arc;

    /// The seed-000 scanner 0.75 m above flat ground, at `x` along the track.
    fn scan_over_flat(x: f64, sequence: u64) -> ScanInput {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.75), UnitQuaternion::identity());
        let mut scan = scan_of(&terrain, pose);
        scan.sequence = sequence;
        scan
    }

    /// Share of `probes` whose true height lies within 1.96 σ of the snapshot's answer.
    fn coverage95(snapshot: &MapSnapshot, terrain: &Heightmap, probes: &[[f64; 2]]) -> f64 {
        let hits: Vec<bool> = probes
            .iter()
            .filter_map(|&[x, y]| {
                let e = query::elevation(snapshot, x, y);
                let (z, var) = (e.z_m?, e.z_var_m2?);
                Some((z - terrain.height(x, y)?).abs() <= 1.96 * var.sqrt())
            })
            .collect();
        assert!(
            hits.len() > probes.len() / 2,
            "only {} of {} answered",
            hits.len(),
            probes.len()
        );
        hits.iter().filter(|&&h| h).count() as f64 / hits.len() as f64
    }

    #[test]
    fn on_rough_terrain_the_next_scans_teach_a_sigma_that_covers_the_truth() {
        // Rough fBm relief (p95 slope 16°) and maps without their own leave-one-out calibration:
        // their σ is the kernel's, far too sure of this ground.
        let terrain = family_terrain("fbm-h05-16deg", 7, 40.0);
        let preset = rangegp_sim::ScannerPreset::seed000();
        let path = rangegp_sim::Path::wander(3, &terrain, 12, 0.5, 0.2);
        let mut window = Window::new(16);
        let mut calibrator = Calibrator::new(true);
        let mut snapshot = MapSnapshot::default();
        for i in 0..12 {
            let mut scan = scan_of(&terrain, path.pose(&terrain, i, preset.mount_height_m));
            scan.sequence = i as u64 + 1;
            let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
            calibrator.observe(&snapshot, &scan, &map);
            window.push(Arc::new(map));
            snapshot = window.snapshot().with_scales(calibrator.scales());
        }
        // Probes 1–8 m ahead of and beside the last pose, inside the forward field of view.
        let last = path.pose(&terrain, 11, preset.mount_height_m);
        let probes: Vec<[f64; 2]> = (0..400)
            .map(|k| {
                let r = 1.0 + 7.0 * ((k * 37) % 400) as f64 / 400.0;
                let a = -1.2 + 2.4 * ((k * 53) % 400) as f64 / 400.0;
                let p = last * nalgebra::Point3::new(r * a.cos(), r * a.sin(), 0.0);
                [p.x, p.y]
            })
            .collect();
        let raw = coverage95(&window.snapshot(), &terrain, &probes);
        let calibrated = coverage95(&snapshot, &terrain, &probes);
        assert!(
            raw < 0.8,
            "the raw σ already covers {raw:.3}: the test proves nothing"
        );
        assert!(
            calibrated > 0.88,
            "calibrated coverage {calibrated:.3} (raw {raw:.3})"
        );
        let (window_counts, _) = calibrator.counts();
        assert!(window_counts.iter().sum::<usize>() >= 3 * MIN_RESIDUALS);
    }

    #[test]
    fn before_the_first_map_nothing_is_learnt() {
        let mut calibrator = Calibrator::new(true);
        let scan = scan_over_flat(0.0, 1);
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        assert_eq!(calibrator.observe(&MapSnapshot::default(), &scan, &map), 0);
        let nothing = SigmaScales {
            relief_in_heights: true,
            ..SigmaScales::default()
        };
        assert_eq!(calibrator.scales(), nothing);
    }

    #[test]
    fn an_empty_cell_takes_its_nearest_learnt_neighbours_scales() {
        let mut residuals = Residuals::default();
        let r = |sd: f64| Residual {
            r2: sd * sd,
            var: 1e-6,
            noise_var: 0.0,
            weight: 1.0,
            ..Residual::default()
        };
        // Only range bins 1 and 4 of the last class have residuals: errors 2 mm and 20 mm.
        residuals[CLASSES - 1][1] = (0..200)
            .map(|i| r(0.002 * (1.0 + (i % 7) as f64 / 7.0)))
            .collect();
        residuals[CLASSES - 1][4] = (0..200).map(|i| r(0.02 * (1.0 + (i % 7) as f64 / 7.0))).collect();
        let table = table_of(&residuals);
        let f = |c: usize, b: usize| table[c][b].factor(1e-3);
        assert_eq!(f(CLASSES - 1, 0), f(CLASSES - 1, 1), "bin 0 from bin 1");
        assert_eq!(f(CLASSES - 1, 6), f(CLASSES - 1, 4), "bin 6 from bin 4");
        // Bins 2 and 3 lie between: 2 is nearer 1, and 3 nearer 4.
        assert_eq!(f(CLASSES - 1, 2), f(CLASSES - 1, 1));
        assert_eq!(f(CLASSES - 1, 3), f(CLASSES - 1, 4));
        // Classes with no residuals at all copy the nearest class.
        assert_eq!(table[0], table[CLASSES - 1]);
        assert!(f(CLASSES - 1, 4) > 5.0 * f(CLASSES - 1, 1));
    }

    fn residuals(sd: f64, var: f64, n: usize) -> Vec<Residual> {
        // Deterministic standard normal quantiles: an exactly Gaussian sample.
        (0..n)
            .map(|i| {
                let u = (i as f64 + 0.5) / n as f64;
                let z = distrs::Normal::ppf(u, 0.0, 1.0);
                Residual {
                    r2: (sd * z).powi(2),
                    var,
                    noise_var: 0.0,
                    weight: 1.0,
                    ..Residual::default()
                }
            })
            .collect()
    }

    #[test]
    fn a_gaussian_error_three_times_the_claimed_sigma_gets_a_scale_of_three() {
        let r = residuals(0.03, 0.01 * 0.01, 1000);
        let s = scale_of(&r);
        assert!((s - 3.0).abs() < 0.05, "scale {s}");
    }

    #[test]
    fn the_returns_own_noise_is_not_charged_to_the_map() {
        let mut r = residuals(0.05, 0.03 * 0.03, 1000);
        for x in &mut r {
            x.noise_var = 0.04 * 0.04;
        }
        // 0.05² = 0.03² + 0.04²: the map's σ was right.
        let s = scale_of(&r);
        assert!((s - 1.0).abs() < 0.05, "scale {s}");
    }

    #[test]
    fn returns_noisier_than_the_map_widen_its_sigma_but_never_narrow_it() {
        // 3 cm returns against a map claiming 5 mm whose errors are 2 mm: the residuals are the
        // returns' noise; no scale below 1 is shown by them.
        let mut r = residuals(0.0301, 0.005 * 0.005, 1000);
        for x in &mut r {
            x.noise_var = 0.03 * 0.03;
        }
        assert_eq!(scale_of(&r), 1.0);
        // The same returns against a map whose errors are 6 cm (claiming 5 mm): widened.
        let mut r = residuals(0.067, 0.005 * 0.005, 1000);
        for x in &mut r {
            x.noise_var = 0.03 * 0.03;
        }
        let s = scale_of(&r);
        assert!((s - 12.0).abs() < 0.6, "scale {s}");
    }

    #[test]
    fn weights_that_sum_to_nothing_fall_back_to_counts() {
        let mut r = residuals(0.03, 0.01 * 0.01, 1000);
        for x in &mut r {
            x.weight = 0.0;
        }
        let s = scale_of(&r);
        assert!((s - 3.0).abs() < 0.05, "scale {s}");
    }

    #[test]
    fn few_residuals_leave_the_scale_at_one() {
        assert_eq!(scale_of(&residuals(1.0, 1e-6, MIN_RESIDUALS - 1)), 1.0);
    }

    #[test]
    fn bins_double_in_width() {
        assert_eq!(bin_of(0.0), 0);
        assert_eq!(bin_of(2.4), 0);
        assert_eq!(bin_of(2.5), 1);
        assert_eq!(bin_of(39.0), 4);
        assert_eq!(bin_of(500.0), BINS - 1);
    }

    #[test]
    fn the_stride_visits_every_index() {
        for n in [1, 2, 10, 64, 1000, 65_536] {
            let s = coprime_stride(n);
            let mut seen = vec![false; n];
            let mut k = 0;
            for _ in 0..n {
                seen[k] = true;
                k = (k + s) % n;
            }
            assert!(seen.iter().all(|&v| v), "n {n}");
        }
    }
}
