//! Query evaluation over a [`MapSnapshot`]: elevation, variance and rays, in batches.

use super::aggregate::Aggregate;
use super::local::{HeightEstimate, RayEstimate};
use super::scales::MAX_SD_FACTOR;
use super::tiles::smoothstep;
use super::window::MapSnapshot;
use super::LocalRangeMap;
use nalgebra::Vector3;
use rangegp_proto::msg::{ElevationItem, Provenance, Ray, RayItem, Refusal, Source, VarianceItem};
use std::sync::Arc;

/// How many of the nearest window maps are asked per query point (the nearest that answers
/// wins), and how many other maps an answer far from its data is checked against.
const CANDIDATES: usize = 3;

/// Maps whose sensor is within range of map point (x, y), nearest first, at most [`CANDIDATES`],
/// with their index in the snapshot.
fn nearest(snapshot: &MapSnapshot, x: f64, y: f64) -> Vec<(usize, &Arc<LocalRangeMap>)> {
    nearest_where(snapshot, x, y, |_| true)
}

/// [`nearest`] among the maps whose index `keep` accepts.
fn nearest_where(
    snapshot: &MapSnapshot,
    x: f64,
    y: f64,
    keep: impl Fn(usize) -> bool,
) -> Vec<(usize, &Arc<LocalRangeMap>)> {
    let mut near: Vec<(f64, usize)> = snapshot
        .reach()
        .iter()
        .enumerate()
        .filter(|&(i, _)| keep(i))
        .filter_map(|(i, &[sx, sy, range])| {
            let rho2 = (x - sx).powi(2) + (y - sy).powi(2);
            (rho2 < range * range).then_some((rho2, i))
        })
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    let maps = snapshot.maps();
    near.into_iter()
        .take(CANDIDATES)
        .map(|(_, i)| (i, &maps[i]))
        .collect()
}

/// Who answered an elevation query.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answerer {
    /// The window map at this index of [`MapSnapshot::maps`].
    Window(usize),
    /// The world aggregate.
    Aggregate,
}

/// An elevation answer before σ calibration, with what the calibration keys on.
#[derive(Debug, Clone, Copy)]
pub struct RawAnswer {
    /// The map's own estimate (the aggregate's with the grazing its fusing scans saw there,
    /// [`seen_at`](super::aggregate::world::WorldAggregate::seen_at)).
    pub estimate: HeightEstimate,
    /// Who answered.
    pub by: Answerer,
    /// Horizontal distance from the answering map's sensor, metres. The aggregate's: from the
    /// sensors that fused the cells there, as fused with their heights
    /// ([`seen_at`](super::aggregate::world::WorldAggregate::seen_at); from the newest sensor
    /// where a cell keeps none, and infinite without one).
    pub rho_m: f64,
}

/// Window map `i`'s own answer at (x, y), before σ scales, whether or not a query would pick it
/// (the calibrator tests maps that looked from elsewhere than the nearest).
pub fn raw_elevation_of(snapshot: &MapSnapshot, i: usize, x: f64, y: f64) -> Option<RawAnswer> {
    let map = snapshot.maps().get(i)?;
    let [sx, sy, _] = *snapshot.reach().get(i)?;
    map.elevation(x, y).map(|estimate| RawAnswer {
        estimate: with_disagreement(snapshot, i, x, y, estimate),
        by: Answerer::Window(i),
        rho_m: (x - sx).hypot(y - sy),
    })
}

/// [`raw_elevation`] among the window maps whose index `keep` accepts, without the aggregate:
/// the nearest of them that answers (the calibrator tests maps that looked from elsewhere than
/// where the new scan stands).
pub fn raw_window_elevation_where(
    snapshot: &MapSnapshot,
    x: f64,
    y: f64,
    keep: impl Fn(usize) -> bool,
) -> Option<RawAnswer> {
    nearest_where(snapshot, x, y, keep)
        .into_iter()
        .find_map(|(i, _)| raw_elevation_of(snapshot, i, x, y))
}

/// Window maps whose sensors lie within this much farther than the answering map's blend their
/// answers with it, so that an answer never jumps where the nearest map changes (metres).
pub const BLEND_M: f64 = 0.1;

/// Elevation at (x, y) as the maps give it, before the snapshot's σ scales: the answer of the
/// window map whose sensor is nearest among those that answer (nearest is least uncertain: range
/// noise and footprint grow with distance), else the aggregate's where it has fused cells nearby,
/// else none. The choice depends on distance alone, so it changes only where two sensors are
/// equally far, and there [`elevation`] blends (an earlier rule preferred maps whose view of the
/// vertical line ended behind the surface; that test flickered near the lowest ring and moved
/// 1.4 % of answers by over 1 mm, up to 4 cm, under 1 µm moves of the query point).
pub fn raw_elevation(snapshot: &MapSnapshot, x: f64, y: f64) -> Option<RawAnswer> {
    search(snapshot, x, y, false).map(|(primary, _)| primary)
}

/// [`raw_elevation`] and, when the next map that answers has its sensor less than [`BLEND_M`]
/// farther away, that answer with its weight in the blend:
/// ½ where both sensors are equally far, falling smoothly to 0 at [`BLEND_M`]. Where the nearest
/// map changes, the two swap roles at equal weights, so the blend is continuous.
fn blended_elevation(
    snapshot: &MapSnapshot,
    x: f64,
    y: f64,
) -> Option<(RawAnswer, Option<(RawAnswer, f64)>)> {
    search(snapshot, x, y, true)
}

/// The map search behind [`raw_elevation`] and, with `blend`, [`blended_elevation`].
fn search(
    snapshot: &MapSnapshot,
    x: f64,
    y: f64,
    blend: bool,
) -> Option<(RawAnswer, Option<(RawAnswer, f64)>)> {
    let rho = |i: usize| {
        snapshot
            .reach()
            .get(i)
            .map_or(f64::INFINITY, |[sx, sy, _]| (x - sx).hypot(y - sy))
    };
    let mut best: Option<RawAnswer> = None;
    for (i, _) in nearest(snapshot, x, y) {
        if let Some(first) = &best {
            let gap = rho(i) - first.rho_m;
            if !blend || gap >= BLEND_M {
                break;
            }
            if let Some(second) = raw_elevation_of(snapshot, i, x, y) {
                let weight = 0.5 * (1.0 - smoothstep(gap / BLEND_M));
                return Some((*first, Some((second, weight))));
            }
        } else {
            best = raw_elevation_of(snapshot, i, x, y);
        }
    }
    if let Some(first) = best {
        return Some((first, None));
    }
    raw_aggregate_elevation(snapshot, x, y).map(|answer| (answer, None))
}

/// The aggregate's own answer at (x, y), before σ scales, whether or not a window map answers
/// there (the calibrator tests the aggregate on every return).
pub fn raw_aggregate_elevation(snapshot: &MapSnapshot, x: f64, y: f64) -> Option<RawAnswer> {
    let agg = snapshot.aggregate.as_ref()?;
    let newest = snapshot
        .reach()
        .first()
        .map_or(f64::INFINITY, |[sx, sy, _]| (x - sx).hypot(y - sy));
    agg.elevation(x, y).map(|estimate| {
        let seen = agg.seen_at(x, y, newest);
        RawAnswer {
            estimate: HeightEstimate {
                grazing: seen.grazing,
                ..estimate
            },
            by: Answerer::Aggregate,
            rho_m: seen.distance_m,
        }
    })
}

/// Where a window answer lies farther than this from its map's data (metres), the other window
/// maps' disagreement with it starts to count in its variance ...
pub const DISAGREEMENT_FROM_M: f64 = 1.0;
/// ... fully from this distance on (smoothly in between, so that σ never steps).
pub const DISAGREEMENT_FULL_M: f64 = 3.0;

/// `estimate` (window map `i`'s answer at (x, y)) with the other window maps' disagreement added
/// to its variance where it lies far from its data: (w · |g|)², w the scales'
/// `view_disagreement` and |g| the smallest distance, along another map's ray, between that
/// map's mean surface and the answered point, over the [`CANDIDATES`] other maps whose sensors
/// are nearest (x, y) (all 15 others: fewer cells in both bounds, and 16 % more time on a grid).
/// Far from data an answer is the map's smooth continuation across a gap between its rings;
/// where that gap is the shadow of relief, the continuation is a curtain from the ridge to the
/// ground beyond, which views from elsewhere do not share, while seen ground between rings is
/// continued much alike by every view (docs/EVALUATION.md "Calibration", step 9).
fn with_disagreement(
    snapshot: &MapSnapshot,
    i: usize,
    x: f64,
    y: f64,
    estimate: HeightEstimate,
) -> HeightEstimate {
    let weight = snapshot.scales.view_disagreement;
    // Written so that a NaN distance or weight returns the map's own answer.
    if !(weight > 0.0 && estimate.data_m > DISAGREEMENT_FROM_M) {
        return estimate;
    }
    let p = Vector3::new(x, y, estimate.z);
    let gap = nearest_where(snapshot, x, y, |j| j != i)
        .into_iter()
        .filter_map(|(_, m)| m.gap(&p))
        .map(f64::abs)
        .fold(f64::INFINITY, f64::min);
    if !gap.is_finite() {
        return estimate;
    }
    let ramp =
        smoothstep((estimate.data_m - DISAGREEMENT_FROM_M) / (DISAGREEMENT_FULL_M - DISAGREEMENT_FROM_M));
    let var = estimate.var + ramp * (weight * gap).powi(2);
    // The point's σ along the ray widens with the height's, as the calibration's factor does.
    let widen = widening(estimate.var, var);
    HeightEstimate {
        var,
        point_sd: estimate.point_sd.map(|s| s * widen),
        ..estimate
    }
}

/// The factor on σ from a map's own variance `own` to `widened` (1 where the map is certain).
fn widening(own: f64, widened: f64) -> f64 {
    if own > 0.0 {
        (widened / own).sqrt()
    } else {
        1.0
    }
}

/// Elevation at (x, y): `blended_elevation`, each map's σ scaled by the snapshot's calibration
/// ([`super::calibration`]) before the two are mixed (mean and variance of the mixture, which
/// counts their disagreement as uncertainty). An answer whose σ exceeds the snapshot's
/// `max_sigma_m` is refused `too_uncertain`: a number that wide would claim knowledge the maps do
/// not have.
pub fn elevation(snapshot: &MapSnapshot, x: f64, y: f64) -> ElevationItem {
    elevation_with_relief(snapshot, x, y).0
}

/// [`elevation`] with the unseen relief's share of its variance, m² (0 where refused; layers
/// clamp it to the whole): what planner layers need to correlate that share over its own
/// distances ([`super::layers`]).
pub fn elevation_with_relief(snapshot: &MapSnapshot, x: f64, y: f64) -> (ElevationItem, f64) {
    let refused = |refusal: Refusal| {
        let item = ElevationItem {
            z_m: None,
            z_var_m2: None,
            point_sigma_m: None,
            source: Source::None,
            provenance: Provenance::None,
            refusal: Some(refusal),
        };
        (item, 0.0)
    };
    let Some((first, second)) = blended_elevation(snapshot, x, y) else {
        return refused(Refusal::Unobserved);
    };
    let source = match first.by {
        Answerer::Window(_) => Source::Window,
        Answerer::Aggregate => Source::Aggregate,
    };
    let calibrated = |a: &RawAnswer| snapshot.scales.calibrate(source, a.rho_m, &a.estimate);
    let primary = calibrated(&first);
    let (z1, v1) = (first.estimate.z, primary.var_m2);
    let (z, var, relief) = match second {
        None => (z1, v1, primary.relief_m2),
        Some((other, w)) => {
            let other_cal = calibrated(&other);
            let (z2, v2) = (other.estimate.z, other_cal.var_m2);
            let z = (1.0 - w) * z1 + w * z2;
            let second_moment = (1.0 - w) * (v1 + z1 * z1) + w * (v2 + z2 * z2);
            let relief = (1.0 - w) * primary.relief_m2 + w * other_cal.relief_m2;
            (z, (second_moment - z * z).max(0.0), relief)
        }
    };
    // A NaN variance is refused too: `is_some_and` is false for it.
    let within = var
        .sqrt()
        .partial_cmp(&snapshot.max_sigma_m)
        .is_some_and(|o| o.is_le());
    if !within {
        return refused(Refusal::TooUncertain);
    }
    // The primary answer's (weight ≥ ½ in a blend): its sensor's ray and its data.
    let s = primary.sd_factor;
    let item = ElevationItem {
        z_m: Some(z),
        z_var_m2: Some(var),
        point_sigma_m: Some(first.estimate.point_sd.map(|v| v * s)),
        source,
        provenance: provenance(snapshot, &first, x, y),
        refusal: None,
    };
    (item, relief)
}

/// How much data stands behind `answer` at (x, y), graded by the map that gave it, for the
/// answer returned only (the window's nearest-datum search stays off the fusion and calibration
/// paths, which need the height alone).
fn provenance(snapshot: &MapSnapshot, answer: &RawAnswer, x: f64, y: f64) -> Provenance {
    match answer.by {
        Answerer::Window(i) => snapshot.maps()[i].provenance(&Vector3::new(x, y, answer.estimate.z)),
        Answerer::Aggregate => snapshot
            .aggregate
            .as_ref()
            .map_or(Provenance::None, |a| a.provenance(x, y)),
    }
}

/// Elevation variance at (x, y): the same search as [`elevation`]. A range map has no cheaper
/// variance path: the height's variance sits where the vertical line crosses the surface, and
/// finding the crossing needs the mean (a coarser crossing was measured: no faster, and wrong
/// by up to 40× between training rays, where the variance dips).
pub fn variance(snapshot: &MapSnapshot, x: f64, y: f64) -> VarianceItem {
    let e = elevation(snapshot, x, y);
    VarianceItem {
        z_var_m2: e.z_var_m2,
        source: e.source,
        refusal: e.refusal,
    }
}

/// Casts one ray (already validated: finite, non-zero direction, positive range) over the
/// whole map: the nearest window maps and the aggregate. Preference: a window hit on observed
/// ground; else the surer hit (smaller calibrated range variance) of the best window hit and the
/// aggregate's (a window map far from the hit sees it at a grazing angle; the aggregate fused it
/// from nearer scans), then a
/// window's no-hit (its hit probability from the closest approach), the aggregate's no-hit;
/// with no map knowing anything along the ray, no hit probability at all.
pub fn ray(snapshot: &MapSnapshot, ray: &Ray) -> RayItem {
    let origin = Vector3::from(ray.origin_m);
    let dir = Vector3::from(ray.direction).normalize();
    let mut near: Vec<(f64, usize, &Arc<LocalRangeMap>)> = snapshot
        .maps()
        .iter()
        .enumerate()
        .map(|(i, m)| ((m.sensor_position() - origin).norm(), i, m))
        .filter(|(d, _, m)| *d < m.max_range() + ray.max_range_m)
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Each map casts with its own calibrated σ, so that a grazing ray's band, its range variance
    // and its hit probability all see the σ a planner is given.
    let answers: Vec<_> = near
        .into_iter()
        .take(CANDIDATES)
        .filter_map(|(_, i, m)| {
            let factor = |p: &Vector3<f64>| map_sd_factor(snapshot, i, p);
            m.cast(origin, dir, ray.max_range_m, &factor)
        })
        .collect();
    let window_hit = answers.iter().filter(|a| a.range.is_some()).min_by(|a, b| {
        a.range_var
            .unwrap_or(f64::INFINITY)
            .total_cmp(&b.range_var.unwrap_or(f64::INFINITY))
    });
    // A window hit on ground its scan measured (observed) stands; otherwise the aggregate, which
    // may have fused that ground from nearer scans, is asked too (a cast over it costs a few
    // hundred µs).
    let settled = window_hit.is_some_and(|w| w.provenance == Provenance::Observed);
    let aggregate = snapshot.aggregate.as_ref().filter(|_| !settled).and_then(|a| {
        let factor = |p: &Vector3<f64>| sd_factor(snapshot, Source::Aggregate, p);
        a.cast(origin, dir, ray.max_range_m, &factor)
    });
    let window_miss = answers
        .iter()
        .max_by(|a, b| a.hit_probability.total_cmp(&b.hit_probability));
    // Each hit's range variance is calibrated already (the casts took the σ factor).
    let answer = match (window_hit, aggregate) {
        (Some(w), Some(a)) if a.range.is_some() => {
            let var = |e: &RayEstimate| e.range_var.unwrap_or(f64::INFINITY);
            Some(if var(&a) < var(w) {
                (a, Source::Aggregate)
            } else {
                (*w, Source::Window)
            })
        }
        (Some(w), _) => Some((*w, Source::Window)),
        (None, Some(a)) if a.range.is_some() => Some((a, Source::Aggregate)),
        (None, aggregate) => match (window_miss, aggregate) {
            (Some(w), _) => Some((*w, Source::Window)),
            (None, Some(a)) => Some((a, Source::Aggregate)),
            (None, None) => None,
        },
    };
    match answer {
        Some((a, source)) => {
            let range_var = a.range.and(a.range_var);
            RayItem {
                range_m: a.range,
                range_var_m2: range_var,
                hit_probability: Some(a.hit_probability),
                hit_point_m: a.range.map(|t| (origin + dir * t).into()),
                hit_sigma_m: range_var.map(|v| (dir.abs() * v.max(0.0).sqrt()).into()),
                source,
                provenance: a.provenance,
            }
        }
        None => RayItem {
            range_m: None,
            range_var_m2: None,
            hit_probability: None,
            hit_point_m: None,
            hit_sigma_m: None,
            source: Source::None,
            provenance: Provenance::None,
        },
    }
}

/// The snapshot's σ calibration for `source` at map point `p`, as a factor on σ: the one the
/// height answer there gets ([`super::scales::Calibrated::sd_factor`]; a ray's range
/// uncertainty is the height's seen along the ray); 1 where no map answers.
fn sd_factor(snapshot: &MapSnapshot, source: Source, p: &Vector3<f64>) -> f64 {
    raw_elevation(snapshot, p.x, p.y).map_or(1.0, |a| {
        snapshot.scales.calibrate(source, a.rho_m, &a.estimate).sd_factor
    })
}

/// The factor from window map `i`'s own σ to its calibrated height answer's at map point `p`
/// (its range σ there is what a ray it casts scales: its distance from its own data and the
/// other views' disagreement with it, not the nearest map's); [`sd_factor`] where it gives none.
/// `i` must index the snapshot's maps.
fn map_sd_factor(snapshot: &MapSnapshot, i: usize, p: &Vector3<f64>) -> f64 {
    let map = &snapshot.maps()[i];
    match map.elevation(p.x, p.y) {
        Some(own) => {
            let s = map.sensor_position();
            let rho = (p.x - s.x).hypot(p.y - s.y);
            let e = with_disagreement(snapshot, i, p.x, p.y, own);
            let factor = snapshot.scales.calibrate(Source::Window, rho, &e).sd_factor;
            (factor * widening(own.var, e.var)).min(MAX_SD_FACTOR.max(factor))
        }
        None => sd_factor(snapshot, Source::Window, p),
    }
}

/// Maps `f` over `items` on up to `threads` scoped threads, keeping order.
pub fn par_map<T: Sync, R: Send>(items: &[T], threads: usize, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let threads = threads.max(1).min(items.len().div_ceil(16).max(1));
    if threads == 1 {
        return items.iter().map(&f).collect();
    }
    let chunk = items.len().div_ceil(threads);
    std::thread::scope(|scope| {
        let handles: Vec<_> = items
            .chunks(chunk)
            .map(|c| scope.spawn(|| c.iter().map(&f).collect::<Vec<R>>()))
            .collect();
        handles
            .into_iter()
            .flat_map(|h| match h.join() {
                Ok(v) => v,
                Err(panic) => std::panic::resume_unwind(panic),
            })
            .collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{family_terrain, params, scan_by, scan_of};
    use crate::map::Window;
    use rand::{Rng, SeedableRng};

    /// A window of seed-000 maps along a wander path over the crater terrain, and the path.
    fn crater_window(scans: usize) -> (MapSnapshot, Vec<nalgebra::Isometry3<f64>>) {
        let terrain = family_terrain("craters", 1, 60.0);
        let preset = rangegp_sim::ScannerPreset::seed000();
        let path = rangegp_sim::Path::wander(5, &terrain, scans, 0.5, 0.25);
        let mut window = Window::new(16);
        let mut poses = Vec::new();
        for i in 0..scans {
            let pose = path.pose(&terrain, i, preset.mount_height_m);
            let mut scan = scan_of(&terrain, pose);
            scan.sequence = i as u64 + 1;
            window.push(Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit")));
            poses.push(pose);
        }
        (window.snapshot(), poses)
    }

    #[test]
    fn far_from_its_data_an_answer_counts_the_other_views_disagreement() {
        // Four VLP-16 scans a metre apart over rough relief: between its rings and behind
        // crests, ground lies metres from any return.
        let terrain = family_terrain("fbm-h05-30deg", 2, 60.0);
        let preset = rangegp_sim::ScannerPreset::vlp16();
        let path = rangegp_sim::Path::wander(7, &terrain, 4, 1.0, 0.1);
        let mut window = Window::new(4);
        let mut poses = Vec::new();
        for k in 0..4 {
            let pose = path.pose(&terrain, k, preset.mount_height_m);
            let mut scan = scan_by(&preset, &terrain, pose);
            scan.sequence = k as u64 + 1;
            window.push(Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit")));
            poses.push(pose);
        }
        let plain = window.snapshot();
        let mut scales = plain.scales;
        scales.view_disagreement = 0.3;
        let with = plain.with_aggregate(None).with_scales(scales);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let (mut near, mut far, mut widened) = (0, 0, 0);
        for _ in 0..20_000 {
            let pose = poses[rng.random_range(0..poses.len())];
            let (r, a) = (rng.random_range(2.0..25.0), rng.random_range(-3.1..3.1));
            let p = pose * nalgebra::Point3::new(r * f64::cos(a), r * f64::sin(a), 0.0);
            let i = rng.random_range(0..plain.maps().len());
            let (Some(own), Some(counted)) = (
                raw_elevation_of(&plain, i, p.x, p.y),
                raw_elevation_of(&with, i, p.x, p.y),
            ) else {
                continue;
            };
            let (e, c) = (own.estimate, counted.estimate);
            assert_eq!(e.z, c.z, "the mean is the map's own");
            if e.data_m <= DISAGREEMENT_FROM_M {
                near += 1;
                assert_eq!(e.var, c.var, "near its data an answer is the map's own");
                continue;
            }
            let q = Vector3::new(p.x, p.y, e.z);
            let gap = nearest_where(&plain, p.x, p.y, |j| j != i)
                .into_iter()
                .filter_map(|(_, m)| m.gap(&q))
                .map(f64::abs)
                .fold(f64::INFINITY, f64::min);
            if e.data_m >= DISAGREEMENT_FULL_M && gap.is_finite() {
                far += 1;
                let expected = e.var + (0.3 * gap).powi(2);
                assert!(
                    (c.var - expected).abs() <= 1e-12 + 1e-9 * expected,
                    "{} vs {expected}",
                    c.var
                );
                widened += usize::from(c.var > 4.0 * e.var);
                // The point's σ and the σ factor of a ray this map casts widen with the height's.
                let widen = (c.var / e.var).sqrt();
                let z_sd = e.point_sd[2] * widen;
                assert!((c.point_sd[2] - z_sd).abs() <= 1e-12 + 1e-9 * z_sd);
                let ray_factor = map_sd_factor(&with, i, &q);
                assert!((ray_factor - widen.min(MAX_SD_FACTOR)).abs() <= 1e-9 * widen);
            }
        }
        assert!(near > 1_000 && far > 500, "near {near}, far {far}");
        assert!(
            widened > 0,
            "some far answer disagrees with another view by far more than its σ"
        );
    }

    #[test]
    fn a_micrometre_move_of_the_query_point_never_moves_the_answer_by_a_millimetre() {
        let (snapshot, poses) = crater_window(8);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let (mut both, mut jumps, mut worst) = (0, 0, 0.0f64);
        for _ in 0..10_000 {
            let pose = poses[rng.random_range(0..poses.len())];
            let (r, a) = (rng.random_range(0.5..9.0), rng.random_range(-1.5..1.5));
            let p = pose * nalgebra::Point3::new(r * f64::cos(a), r * f64::sin(a), 0.0);
            let d = rng.random_range(0.0..std::f64::consts::TAU);
            let (x, y) = (p.x + 1e-6 * d.cos(), p.y + 1e-6 * d.sin());
            let (Some(z0), Some(z1)) = (elevation(&snapshot, p.x, p.y).z_m, elevation(&snapshot, x, y).z_m)
            else {
                continue;
            };
            both += 1;
            worst = worst.max((z1 - z0).abs());
            if (z1 - z0).abs() > 1e-3 {
                jumps += 1;
            }
        }
        assert!(both > 5_000, "only {both} answered");
        assert_eq!(
            jumps, 0,
            "{jumps} of {both} answers jumped by > 1 mm (worst {worst} m)"
        );
    }

    #[test]
    fn where_the_nearest_map_changes_the_answer_blends_instead_of_stepping() {
        // Two scanners side by side, 1 m apart, both looking along +x over the craters: the
        // nearest map changes on the line y = 0.5 ahead of them.
        let terrain = family_terrain("craters", 1, 60.0);
        let mut window = Window::new(4);
        for (k, y) in [0.0, 1.0].into_iter().enumerate() {
            let z = terrain.height(0.0, y).expect("on the terrain") + 0.75;
            let pose = nalgebra::Isometry3::translation(0.0, y, z);
            let mut scan = scan_of(&terrain, pose);
            scan.sequence = k as u64 + 1;
            window.push(Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit")));
        }
        let snapshot = window.snapshot();
        let (m0, m1) = (&snapshot.maps()[0], &snapshot.maps()[1]);
        // Where on that line, 2–9 m ahead, the two maps disagree most.
        let x = (20..=90)
            .map(|k| k as f64 / 10.0)
            .filter_map(|x| {
                let (a, b) = (m0.elevation(x, 0.5)?, m1.elevation(x, 0.5)?);
                Some(((a.z - b.z).abs(), x))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .expect("both maps see ahead")
            .1;
        let middle = nalgebra::Vector2::new(x, 0.5);
        let along = nalgebra::Vector2::new(0.0, 1.0);
        let (mut switched, mut worst_raw, mut worst) = (false, 0.0f64, 0.0f64);
        let mut last: Option<(RawAnswer, f64)> = None;
        for k in -300..=300 {
            let p = middle + along * (k as f64 * 1e-3);
            let raw = raw_elevation(&snapshot, p.x, p.y).expect("answered");
            let z = elevation(&snapshot, p.x, p.y).z_m.expect("answered");
            if let Some((prev, prev_z)) = last {
                switched |= prev.by != raw.by;
                worst_raw = worst_raw.max((raw.estimate.z - prev.estimate.z).abs());
                worst = worst.max((z - prev_z).abs());
            }
            last = Some((raw, z));
        }
        assert!(switched, "the walk never changed the nearest map");
        assert!(
            worst_raw > 1e-3,
            "the maps agree to {worst_raw} m here: the test proves nothing"
        );
        assert!(worst < 5e-4, "a 1 mm step moved the answer by {worst} m");
    }

    #[test]
    fn a_map_scales_its_rays_by_its_own_distance_from_data_not_the_nearest_maps() {
        // Two scanners 5 m apart along x, both looking along +x: ahead of the front one the
        // front map is the nearest, and the back map, 5 m farther, has data there of its own at
        // other distances. With the unseen relief growing with distance from data, each map's
        // factor is the one its own distance gives.
        let terrain = family_terrain("craters", 1, 60.0);
        let mut window = Window::new(4);
        for (k, x) in [-5.0, 0.0].into_iter().enumerate() {
            let z = terrain.height(x, 0.0).expect("on the terrain") + 0.75;
            let mut scan = scan_of(&terrain, nalgebra::Isometry3::translation(x, 0.0, z));
            scan.sequence = k as u64 + 1;
            window.push(Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit")));
        }
        let mut scales = crate::map::scales::SigmaScales {
            relief_in_heights: true,
            ..Default::default()
        };
        scales.relief.var_m2 = std::array::from_fn(|b| 1e-3 * crate::map::scales::data_centre_m(b));
        let snapshot = window.snapshot().with_scales(scales);
        let back_index = snapshot
            .maps()
            .iter()
            .position(|m| m.sensor_position().x < -4.0)
            .expect("the back map");
        let back = &snapshot.maps()[back_index];
        // Where the back map's data lie farthest beyond the nearest map's.
        let (gap, p, own_estimate) = (0..=24)
            .flat_map(|i| (0..=16).map(move |j| (3.0 + 0.25 * f64::from(i), -2.0 + 0.25 * f64::from(j))))
            .filter_map(|(x, y)| {
                let e = back.elevation(x, y)?;
                let nearest = raw_elevation(&snapshot, x, y)?;
                Some((e.data_m - nearest.estimate.data_m, Vector3::new(x, y, e.z), e))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .expect("the back map answers ahead of the front one");
        assert!(gap > 0.2, "the premise: the back map's data only {gap} m farther");
        let own = map_sd_factor(&snapshot, back_index, &p);
        let rho = (p.x + 5.0).hypot(p.y);
        let own_calibration = snapshot.scales.calibrate(Source::Window, rho, &own_estimate);
        let expected = own_calibration.sd_factor;
        assert!(
            (own - expected).abs() <= 1e-9 * expected,
            "{own} against {expected}"
        );
        // Its own σ so scaled is its own calibrated height σ there; the nearest map's factor
        // (the front map's, near its data) would give another.
        let calibrated = own_calibration.var_m2.sqrt();
        assert!((own_estimate.var.sqrt() * own - calibrated).abs() <= 1e-9 * calibrated);
        let nearest = sd_factor(&snapshot, Source::Window, &p);
        assert!(
            (own - nearest).abs() > 0.1 * nearest,
            "the back map's factor {own} against the nearest map's {nearest}"
        );
    }

    #[test]
    fn an_answer_wider_than_the_bound_is_refused_as_too_uncertain_and_unseen_ground_as_unobserved() {
        let (snapshot, poses) = crater_window(4);
        let ahead = poses[3] * nalgebra::Point3::new(3.0, 0.5, 0.0);
        let answered = elevation(&snapshot, ahead.x, ahead.y);
        let sd = answered.z_var_m2.expect("answered").sqrt();
        assert_eq!(answered.refusal, None);
        let bounded = snapshot.clone().with_max_sigma(0.5 * sd);
        let refused = elevation(&bounded, ahead.x, ahead.y);
        assert_eq!((refused.z_m, refused.z_var_m2), (None, None));
        assert_eq!(refused.refusal, Some(Refusal::TooUncertain));
        assert_eq!(
            (refused.provenance, refused.point_sigma_m),
            (Provenance::None, None)
        );
        assert_ne!(answered.provenance, Provenance::None);
        assert_eq!(
            variance(&bounded, ahead.x, ahead.y).refusal,
            Some(Refusal::TooUncertain)
        );
        let far = elevation(&snapshot, ahead.x + 500.0, ahead.y);
        assert_eq!(
            (far.refusal, far.provenance),
            (Some(Refusal::Unobserved), Provenance::None)
        );
    }
}
