//! Tiled local experts for whole scans (seed 004 §III-B, seed 002 §III-E): the observed angle
//! box is cut into a grid of tiles, each tile an exact GP on the rays of its box grown by an
//! overlap margin, fitted in parallel. Predictions blend the experts that cover an angle with a
//! partition of unity whose weights fall to zero at each tile's outer edge, so the blended mean
//! and variance are continuous across tile borders (no seams by construction).

use super::embedding::Embedding;
use crate::gp::{CholeskyError, ExactGp, JitterPolicy, Kernel};
use rayon::prelude::*;
use std::f64::consts::TAU;

/// How a scan is cut into experts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tiling {
    /// Training rays per tile at most (an even stride over the tile's rays beyond it).
    pub max_rays_per_tile: usize,
    /// Overlap margin on each side, as a fraction of the tile's core size.
    pub overlap: f64,
}

impl Default for Tiling {
    fn default() -> Self {
        Self {
            max_rays_per_tile: 128,
            overlap: 0.15,
        }
    }
}

/// One training ray: direction and de-meaned target with its noise variance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainingRay {
    /// Inclination, radians.
    pub inclination: f64,
    /// Azimuth, radians.
    pub azimuth: f64,
    /// Range minus the prior mean, metres.
    pub residual: f64,
    /// Noise variance, m².
    pub noise_var: f64,
}

/// The grid of tiles over an inclination interval × azimuth arc.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Grid {
    theta0: f64,
    dtheta: f64,
    rows: usize,
    phi0: f64,
    dphi: f64,
    cols: usize,
    full_turn: bool,
    margin_theta: f64,
    margin_phi: f64,
}

impl Grid {
    /// Azimuth relative to the arc start, in [0, 2π).
    fn rel_phi(&self, phi: f64) -> f64 {
        rem_turn(phi - self.phi0)
    }

    /// The tiles whose extended box may contain (θ, relative φ), row by row, as their index in
    /// the row-major tile list and their weight there: the product of ramps over the overlap
    /// margins, zero outside the tile's support. Each row's and each column's ramp is
    /// computed once (a query blends up to nine tiles of three rows and three columns).
    fn covering(&self, theta: f64, rel: f64) -> ([(usize, f64); 9], usize) {
        let r = floor_index((theta - self.theta0) / self.dtheta);
        let c = floor_index(rel / self.dphi);
        let (rows, cols) = (self.rows as i64, self.cols as i64);
        let mut row_weights = [(0usize, 0.0f64); 3];
        let mut n_rows = 0;
        for rr in (r - 1..=r + 1).filter(|rr| (0..rows).contains(rr)) {
            let rr = rr as usize;
            let lo = self.theta0 + rr as f64 * self.dtheta;
            let w = ramp(
                theta,
                lo,
                self.dtheta,
                self.margin_theta,
                rr == 0,
                rr + 1 == self.rows,
            );
            row_weights[n_rows] = (rr, w);
            n_rows += 1;
        }
        let mut col_weights = [(0usize, 0.0f64); 3];
        let mut n_cols = 0;
        for cc in c - 1..=c + 1 {
            let cc = if self.full_turn { cc.rem_euclid(cols) } else { cc };
            if !(0..cols).contains(&cc) {
                continue;
            }
            let cc = cc as usize;
            col_weights[n_cols] = (cc, self.column_weight(cc, rel));
            n_cols += 1;
        }
        let mut out = [(0usize, 0.0f64); 9];
        let mut n = 0;
        for &(rr, wt) in &row_weights[..n_rows] {
            for &(cc, wc) in &col_weights[..n_cols] {
                out[n] = (rr * self.cols + cc, wt * wc);
                n += 1;
            }
        }
        (out, n)
    }

    /// The azimuth ramp of column `c` at relative φ `rel` (a full turn measured from the
    /// column's centre, so the ramp wraps).
    fn column_weight(&self, c: usize, rel: f64) -> f64 {
        let lo = c as f64 * self.dphi;
        let rel = if self.full_turn {
            let centre = lo + self.dphi / 2.0;
            centre + rem_turn(rel - centre + TAU / 2.0) - TAU / 2.0
        } else {
            rel
        };
        let open_ends = !self.full_turn;
        ramp(
            rel,
            lo,
            self.dphi,
            self.margin_phi,
            open_ends && c == 0,
            open_ends && c + 1 == self.cols,
        )
    }
}

/// `x.rem_euclid(2π)` without a division within a turn of [0, 2π), where the remainder is
/// exact and the same number comes out.
fn rem_turn(x: f64) -> f64 {
    if (0.0..TAU).contains(&x) {
        x
    } else if x > -TAU && x < 0.0 {
        x + TAU
    } else if (TAU..2.0 * TAU).contains(&x) {
        x - TAU
    } else {
        x.rem_euclid(TAU)
    }
}

/// `x.floor()` as an index without a libm call (the targeted x86-64 baseline has no rounding
/// instruction).
fn floor_index(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t - 1
    } else {
        t
    }
}

/// 1 inside [lo + m, lo + w − m], falling smoothly to 0 at lo − m and lo + w + m; an `open` end
/// stays at 1 beyond the grid so the outermost tiles cover the whole observed box.
fn ramp(x: f64, lo: f64, w: f64, m: f64, open_low: bool, open_high: bool) -> f64 {
    let up = if open_low {
        1.0
    } else {
        smoothstep((x - (lo - m)) / (2.0 * m))
    };
    let down = if open_high {
        1.0
    } else {
        smoothstep(((lo + w + m) - x) / (2.0 * m))
    };
    up * down
}

/// 0 below 0, 1 above 1, and 3t² − 2t³ between: a ramp with zero slope at both ends.
pub(crate) fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// How each local expert's predictive variance is tied to its own data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VarianceCalibration {
    /// As the kernel says: the variance depends on where the rays are, never on what they say.
    None,
    /// Scaled by the mean square of the expert's standardised leave-one-out residuals (each
    /// training ray predicted from the others), shrunk toward 1 by [`LOO_PRIOR_RAYS`]
    /// pseudo-residuals: rough or misfit terrain widens σ, terrain the kernel explains keeps it.
    LeaveOneOut,
    /// As [`Self::LeaveOneOut`], but the scale at each query is the kernel-weighted mean of the
    /// squared residuals of the rays near it ([`crate::gp::ExactGp::set_local_variance_scale`]):
    /// within one tile a rim or a step widens σ around itself, not over the whole tile.
    #[default]
    LocalLeaveOneOut,
}

/// Pseudo-residuals of scale 1 added to every expert's leave-one-out evidence (a small tile
/// cannot move its scale far).
pub const LOO_PRIOR_RAYS: f64 = 8.0;
/// Bounds of a leave-one-out variance scale.
pub const LOO_SCALE_BOUNDS: (f64, f64) = (0.25, 1e6);

/// The variance scale of an expert whose standardised leave-one-out residuals are `z`.
pub fn loo_scale(z: &[f64]) -> f64 {
    let squares: f64 = z.iter().map(|v| v * v).sum();
    let scale = (squares + LOO_PRIOR_RAYS) / (z.len() as f64 + LOO_PRIOR_RAYS);
    scale.clamp(LOO_SCALE_BOUNDS.0, LOO_SCALE_BOUNDS.1)
}

/// A scan's range residual modelled by a grid of exact-GP experts.
#[derive(Debug, Clone)]
pub struct TiledGp {
    grid: Grid,
    experts: Vec<Option<ExactGp>>,
    embedding: Embedding,
}

impl TiledGp {
    /// Fits the experts of `rays` (non-empty) in parallel on the rayon pool.
    pub fn fit(
        rays: &[TrainingRay],
        kernel: Kernel,
        embedding: Embedding,
        tiling: Tiling,
        jitter: JitterPolicy,
    ) -> Result<Self, CholeskyError> {
        assert!(!rays.is_empty(), "no training rays");
        let (mut tmin, mut tmax) = (f64::INFINITY, f64::NEG_INFINITY);
        let mut az: Vec<f64> = Vec::with_capacity(rays.len());
        for r in rays {
            tmin = tmin.min(r.inclination);
            tmax = tmax.max(r.inclination);
            az.push(r.azimuth.rem_euclid(TAU));
        }
        az.sort_by(f64::total_cmp);
        let (mut gap, mut start) = (az[0] + TAU - az[az.len() - 1], az[0]);
        for w in az.windows(2) {
            if w[1] - w[0] > gap {
                gap = w[1] - w[0];
                start = w[1];
            }
        }
        let width = (TAU - gap).max(1e-6);
        let full_turn = gap < 5f64.to_radians();
        let arc = if full_turn { TAU } else { width };
        let theta_span = (tmax - tmin).max(1e-6);
        let core = tiling.max_rays_per_tile as f64 / (1.0 + 2.0 * tiling.overlap).powi(2);
        let tiles = (rays.len() as f64 / core).ceil().max(1.0);
        let aspect = theta_span / (arc * ((tmin + tmax) / 2.0).sin().max(0.1));
        let rows = ((tiles * aspect).sqrt().round() as usize).clamp(1, tiles as usize);
        let cols = ((tiles / rows as f64).ceil() as usize).max(1);
        let grid = Grid {
            theta0: tmin,
            dtheta: theta_span / rows as f64 * (1.0 + 1e-9),
            rows,
            phi0: if full_turn { 0.0 } else { start },
            dphi: arc / cols as f64 * (1.0 + 1e-9),
            cols,
            full_turn,
            margin_theta: tiling.overlap * theta_span / rows as f64,
            margin_phi: tiling.overlap * arc / cols as f64,
        };
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); rows * cols];
        for (i, r) in rays.iter().enumerate() {
            let (tiles, n) = grid.covering(r.inclination, grid.rel_phi(r.azimuth));
            for &(k, w) in &tiles[..n] {
                if w > 0.0 {
                    members[k].push(i);
                }
            }
        }
        let experts = members
            .par_iter()
            .map(|idx| {
                if idx.is_empty() {
                    return Ok(None);
                }
                let stride = idx.len().div_ceil(tiling.max_rays_per_tile.max(1));
                let chosen: Vec<&TrainingRay> = idx.iter().step_by(stride).map(|&i| &rays[i]).collect();
                let inputs = chosen
                    .iter()
                    .map(|r| embedding.point(r.inclination, r.azimuth))
                    .collect();
                let targets: Vec<f64> = chosen.iter().map(|r| r.residual).collect();
                let noise: Vec<f64> = chosen.iter().map(|r| r.noise_var).collect();
                ExactGp::fit(kernel, inputs, &targets, &noise, jitter).map(Some)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            grid,
            experts,
            embedding,
        })
    }

    /// Calibrates every expert's variance to its own data (in parallel); see
    /// [`VarianceCalibration`].
    pub fn calibrate(&mut self, policy: VarianceCalibration) {
        if policy == VarianceCalibration::None {
            return;
        }
        self.experts.par_iter_mut().flatten().for_each(|gp| {
            let z = gp.loo_residuals();
            let scale = loo_scale(&z);
            if policy == VarianceCalibration::LocalLeaveOneOut {
                gp.set_local_variance_scale(&z, scale, 0.0);
            } else {
                gp.set_variance_scale(scale);
            }
        });
    }

    /// Experts (tiles with rays).
    pub fn tiles(&self) -> usize {
        self.experts.iter().flatten().count()
    }

    /// Experts whose factorisation needed diagonal jitter.
    pub fn jittered_tiles(&self) -> usize {
        self.experts
            .iter()
            .flatten()
            .filter(|gp| gp.jitter() > 0.0)
            .count()
    }

    /// Training rays over all experts (overlaps counted in each).
    pub fn training_rays(&self) -> usize {
        self.experts.iter().flatten().map(ExactGp::len).sum()
    }

    /// Blended residual mean along the ray (θ, φ), whose sensor-frame unit direction is `u`
    /// (the caller has it: no trigonometry here); O(n) per covering expert.
    pub fn mean_along(&self, inclination: f64, azimuth: f64, u: [f64; 3]) -> f64 {
        let x = self.embedding.point_of_unit(u);
        self.blend(inclination, azimuth, |gp| (gp.mean(&x), 0.0)).0
    }

    /// Distance, in kernel-input metres, from direction (θ, φ) to the nearest training ray of
    /// the experts that answer there (what [`super::local::provenance_of`] grades).
    pub fn nearest_datum(&self, inclination: f64, azimuth: f64) -> f64 {
        let x = self.embedding.point(inclination, azimuth);
        let (tiles, n) = self.grid.covering(inclination, self.grid.rel_phi(azimuth));
        let mut nearest = f64::INFINITY;
        let mut fallback = None;
        for &(k, w) in &tiles[..n] {
            let Some(gp) = &self.experts[k] else {
                continue;
            };
            fallback.get_or_insert(gp);
            if w > 0.0 {
                nearest = nearest.min(gp.nearest_input_distance(&x));
            }
        }
        if nearest.is_finite() {
            return nearest;
        }
        fallback
            .or_else(|| self.experts.iter().flatten().next())
            .map_or(f64::INFINITY, |gp| gp.nearest_input_distance(&x))
    }

    /// Blended residual mean and variance (mixture of the covering experts).
    pub fn mean_variance(&self, inclination: f64, azimuth: f64) -> (f64, f64) {
        let x = self.embedding.point(inclination, azimuth);
        self.blend(inclination, azimuth, |gp| gp.mean_variance(&x))
    }

    /// [`Self::mean_variance`] of many rays at once: each expert predicts all the rays it
    /// covers together (one multi-column triangular solve per block, so its factor is read once
    /// per block rather than once per ray), then the answers are blended with the same weights.
    pub fn mean_variance_batch(&self, angles: &[(f64, f64)]) -> Vec<(f64, f64)> {
        let mut assigned: Vec<Vec<(usize, f64)>> = vec![Vec::new(); self.experts.len()];
        let any_expert = self.experts.iter().position(Option::is_some);
        for (q, &(theta, phi)) in angles.iter().enumerate() {
            let (tiles, n) = self.grid.covering(theta, self.grid.rel_phi(phi));
            let (mut covered, mut nearest) = (false, None);
            for &(k, w) in &tiles[..n] {
                if self.experts[k].is_none() {
                    continue;
                }
                nearest.get_or_insert(k);
                if w > 0.0 {
                    assigned[k].push((q, w));
                    covered = true;
                }
            }
            // Outside every tile's support: the nearest expert answers alone, as in `blend`.
            if let (false, Some(k)) = (covered, nearest.or(any_expert)) {
                assigned[k].push((q, 1.0));
            }
        }
        let points: Vec<[f64; 3]> = angles
            .iter()
            .map(|&(theta, phi)| self.embedding.point(theta, phi))
            .collect();
        let mut sums = vec![[0.0; 3]; angles.len()];
        for (gp, queries) in self.experts.iter().zip(&assigned) {
            let Some(gp) = gp else { continue };
            if queries.is_empty() {
                continue;
            }
            let xs: Vec<[f64; 3]> = queries.iter().map(|&(q, _)| points[q]).collect();
            let (means, vars) = gp.predict_batch(&xs);
            for ((&(q, w), m), v) in queries.iter().zip(means).zip(vars) {
                let s = &mut sums[q];
                s[0] += w;
                s[1] += w * m;
                s[2] += w * (v + m * m);
            }
        }
        sums.iter()
            .map(|&[wsum, m1, m2]| {
                if wsum > 0.0 {
                    let mean = m1 / wsum;
                    (mean, (m2 / wsum - mean * mean).max(0.0))
                } else {
                    (0.0, 0.0)
                }
            })
            .collect()
    }

    fn blend(&self, inclination: f64, azimuth: f64, f: impl Fn(&ExactGp) -> (f64, f64)) -> (f64, f64) {
        let (tiles, n) = self.grid.covering(inclination, self.grid.rel_phi(azimuth));
        let (mut wsum, mut m1, mut m2) = (0.0, 0.0, 0.0);
        let mut fallback = None;
        for &(k, w) in &tiles[..n] {
            let Some(gp) = &self.experts[k] else {
                continue;
            };
            fallback.get_or_insert(gp);
            if w > 0.0 {
                let (m, v) = f(gp);
                wsum += w;
                m1 += w * m;
                m2 += w * (v + m * m);
            }
        }
        if wsum > 0.0 {
            let mean = m1 / wsum;
            return (mean, (m2 / wsum - mean * mean).max(0.0));
        }
        // Outside every tile's support (beyond the observed box): the nearest expert answers.
        match fallback.or_else(|| self.experts.iter().flatten().next()) {
            Some(gp) => f(gp),
            None => (0.0, 0.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loo_scale_follows_the_residuals_and_is_shrunk_for_small_tiles() {
        assert!((loo_scale(&[1.0; 100]) - 1.0).abs() < 1e-12);
        assert!((loo_scale(&[3.0; 92]) - (9.0 * 92.0 + 8.0) / 100.0).abs() < 1e-12);
        assert!(loo_scale(&[3.0; 2]) < 3.0, "two rays cannot claim a scale of 9");
        assert_eq!(loo_scale(&[0.0; 1000]), LOO_SCALE_BOUNDS.0);
    }
    use crate::gp::sphere;
    use crate::map::prior::Prior;
    use nalgebra::{UnitQuaternion, Vector3};
    use rand::SeedableRng;
    use rangegp_sim::{simulate_scan, CraterParams, Heightmap, ScannerPreset};

    /// A denser seed-000 scanner (25 rings × 161 columns) over cratered ground: about 3000
    /// returns for training, and held-out rays between them with exact ranges.
    fn scan() -> (Vec<TrainingRay>, Vec<(f64, f64, f64)>) {
        let terrain = Heightmap::cratered(21, &CraterParams::sized(40.0));
        let pose = rangegp_sim::level_pose(&terrain, 0.0, 0.0, 0.0, 0.75);
        let grid = |rings: usize, cols: usize, offset: f64| ScannerPreset {
            name: "dense",
            inclinations_rad: (0..rings)
                .map(|i| (90.0 + 15.0 * (i as f64 + offset) / (rings - 1) as f64).to_radians())
                .collect(),
            azimuths_rad: (0..cols)
                .map(|i| (-90.0 + 180.0 * (i as f64 + offset) / (cols - 1) as f64).to_radians())
                .collect(),
            ..ScannerPreset::seed000()
        };
        let prior = Prior::flat_ground(0.75, &UnitQuaternion::identity(), 10.0);
        let unit = |t: f64, p: f64| Vector3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos());
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let train = simulate_scan(&terrain, &pose, &grid(25, 161, 0.0), &mut rng)
            .into_iter()
            .filter_map(|r| {
                let range = r.measured_range_m?;
                Some(TrainingRay {
                    inclination: r.inclination_rad,
                    azimuth: r.azimuth_rad,
                    residual: range - prior.range(&unit(r.inclination_rad, r.azimuth_rad)),
                    noise_var: (0.0075 / 29.0 * range).powi(2) + 1e-6,
                })
            })
            .collect();
        let test = simulate_scan(&terrain, &pose, &grid(24, 160, 0.5), &mut rng)
            .into_iter()
            .filter_map(|r| {
                let t = r.true_range_m?;
                Some((
                    r.inclination_rad,
                    r.azimuth_rad,
                    t - prior.range(&unit(r.inclination_rad, r.azimuth_rad)),
                ))
            })
            .collect();
        (train, test)
    }

    fn rmse(test: &[(f64, f64, f64)], predict: impl Fn(f64, f64) -> f64) -> f64 {
        let se: f64 = test
            .iter()
            .map(|&(t, p, truth)| (predict(t, p) - truth).powi(2))
            .sum();
        (se / test.len() as f64).sqrt()
    }

    #[test]
    fn tiled_experts_stay_within_5_percent_of_one_exact_gp_and_have_no_seams() {
        let (train, test) = scan();
        assert!(
            train.len() > 2000 && train.len() <= 3000,
            "{} training rays",
            train.len()
        );
        let kernel = Kernel::matern32(2.302, 1.206);
        let inputs = train
            .iter()
            .map(|r| sphere::to_sphere(r.inclination, r.azimuth, 10.0))
            .collect();
        let targets: Vec<f64> = train.iter().map(|r| r.residual).collect();
        let noise: Vec<f64> = train.iter().map(|r| r.noise_var).collect();
        let exact = ExactGp::fit(kernel, inputs, &targets, &noise, JitterPolicy::default()).expect("exact");
        let tiled = TiledGp::fit(
            &train,
            kernel,
            Embedding::sphere(10.0),
            Tiling::default(),
            JitterPolicy::default(),
        )
        .expect("tiled");
        assert!(tiled.tiles() >= 12, "only {} tiles", tiled.tiles());
        let e = rmse(&test, |t, p| exact.mean(&sphere::to_sphere(t, p, 10.0)));
        let t = rmse(&test, |th, p| {
            tiled.mean_along(th, p, sphere::to_sphere(th, p, 1.0))
        });
        eprintln!(
            "held-out range RMSE: exact {e:.5} m, tiled {t:.5} m over {} tiles",
            tiled.tiles()
        );
        assert!(t <= 1.05 * e, "tiled RMSE {t} vs exact {e}");

        // Dense sweeps across every tile border in both directions. A seam is a step the tiled
        // model takes between neighbouring angles that the exact model does not take: compare
        // the two models' increments, in units of 3σ of the tiled model.
        let exact_mean = |t: f64, p: f64| exact.mean(&sphere::to_sphere(t, p, 10.0));
        let mut worst: f64 = 0.0;
        let mut check = |a: (f64, f64), b: (f64, f64)| {
            let (ta, tb) = (tiled.mean_variance(a.0, a.1), tiled.mean_variance(b.0, b.1));
            let step = (tb.0 - ta.0) - (exact_mean(b.0, b.1) - exact_mean(a.0, a.1));
            worst = worst.max(step.abs() / (3.0 * ta.1.min(tb.1).sqrt()));
        };
        for k in 0..6 {
            let theta = (90.5 + 2.7 * k as f64).to_radians();
            for i in 0..2000 {
                let (p0, p1) = (
                    -1.55 + 3.1 * i as f64 / 2000.0,
                    -1.55 + 3.1 * (i + 1) as f64 / 2000.0,
                );
                check((theta, p0), (theta, p1));
            }
        }
        for k in 0..8 {
            let phi = (-80.0 + 22.0 * k as f64).to_radians();
            for i in 0..1000 {
                let (t0, t1) = (
                    1.571 + 0.26 * i as f64 / 1000.0,
                    1.571 + 0.26 * (i + 1) as f64 / 1000.0,
                );
                check((t0, phi), (t1, phi));
            }
        }
        assert!(
            worst < 1.0,
            "a jump of {:.2} × 3σ between neighbouring angles",
            worst
        );
    }

    #[test]
    fn full_turn_scans_wrap_without_a_seam_at_plus_minus_pi() {
        let rays: Vec<TrainingRay> = (0..720)
            .map(|i| {
                let phi = -std::f64::consts::PI + TAU * i as f64 / 720.0;
                TrainingRay {
                    inclination: 1.6 + 0.05 * (i % 4) as f64,
                    azimuth: phi,
                    residual: (2.0 * phi).cos() * 0.3,
                    noise_var: 1e-6,
                }
            })
            .collect();
        let gp = TiledGp::fit(
            &rays,
            Kernel::matern32(1.0, 0.8),
            Embedding::sphere(10.0),
            Tiling {
                max_rays_per_tile: 64,
                overlap: 0.25,
            },
            JitterPolicy::default(),
        )
        .expect("fit");
        assert!(gp.tiles() > 8);
        let mean = |t: f64, p: f64| gp.mean_along(t, p, sphere::to_sphere(t, p, 1.0));
        let below = mean(1.675, std::f64::consts::PI - 1e-4);
        let above = mean(1.675, -std::f64::consts::PI + 1e-4);
        assert!((below - above).abs() < 1e-3, "{below} vs {above}");
        assert!((below - 0.3).abs() < 0.02);
    }

    #[test]
    fn batched_prediction_equals_one_ray_at_a_time() {
        let (train, test) = scan();
        let tiled = TiledGp::fit(
            &train,
            Kernel::matern32(5e-4, 0.97),
            Embedding::sphere(10.0),
            Tiling::default(),
            JitterPolicy::default(),
        )
        .expect("tiled");
        // Held-out rays, plus some outside the observed box (the nearest expert answers).
        let mut angles: Vec<(f64, f64)> = test.iter().step_by(7).map(|&(t, p, _)| (t, p)).collect();
        angles.extend([(1.2, 0.0), (2.2, 2.5), (1.7, -3.0)]);
        let batch = tiled.mean_variance_batch(&angles);
        for (&(t, p), &(m, v)) in angles.iter().zip(&batch) {
            let (m1, v1) = tiled.mean_variance(t, p);
            assert!(
                (m - m1).abs() <= 1e-9 * (1.0 + m1.abs()),
                "mean at ({t}, {p}): {m} vs {m1}"
            );
            assert!(
                (v - v1).abs() <= 1e-7 * v1 + 1e-15,
                "variance at ({t}, {p}): {v} vs {v1}"
            );
        }
    }
}
