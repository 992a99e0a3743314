//! Query evaluation over a [`MapSnapshot`]: elevation, variance and rays, in batches.

use super::aggregate::Aggregate;
use super::local::HeightEstimate;
use super::window::MapSnapshot;
use super::LocalRangeMap;
use nalgebra::Vector3;
use rangegp_proto::msg::{ElevationItem, Ray, RayItem, Source, VarianceItem};
use std::sync::Arc;

/// How many of the nearest window maps are asked per query point (the least uncertain wins).
const CANDIDATES: usize = 3;

/// Maps whose sensor is within range of map point (x, y), nearest first, at most [`CANDIDATES`],
/// with their index in the snapshot.
fn nearest(snapshot: &MapSnapshot, x: f64, y: f64) -> Vec<(usize, &Arc<LocalRangeMap>)> {
    let mut near: Vec<(f64, usize)> = snapshot
        .reach()
        .iter()
        .enumerate()
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
    /// The map's own estimate.
    pub estimate: HeightEstimate,
    /// Who answered.
    pub by: Answerer,
    /// Horizontal distance from the answering map's sensor (the aggregate: from the newest
    /// sensor position; infinite without one), metres.
    pub rho_m: f64,
}

/// Elevation at (x, y) as the maps give it, before the snapshot's σ scales: the answer of the
/// window map whose sensor is nearest among those whose view of the vertical line ends behind the
/// surface (nearest is least uncertain: range noise and footprint grow with distance; such a view
/// crosses the surface for certain), else of the nearest whose view crosses it anywhere (an
/// overhang seen from below), else the aggregate's where it has fused cells nearby, else none.
/// Checking the end of the view first costs one mean evaluation and spares a whole search of
/// maps that cannot answer, like the nearest map at a point inside its sensor's blind zone (the
/// field of view's part of the line is all free space).
pub fn raw_elevation(snapshot: &MapSnapshot, x: f64, y: f64) -> Option<RawAnswer> {
    let mut deferred = Vec::new();
    let mut best = None;
    for (i, m) in nearest(snapshot, x, y) {
        let Some(view) = m.vertical_view(x, y) else {
            continue;
        };
        if !view.ends_behind_surface() {
            deferred.push((i, m, view));
        } else if let Some(e) = m.elevation_in(x, y, &view) {
            best = Some((i, e));
            break;
        }
    }
    let best = best.or_else(|| {
        deferred
            .iter()
            .find_map(|(i, m, view)| m.elevation_in(x, y, view).map(|e| (*i, e)))
    });
    let rho = |i: usize| {
        snapshot
            .reach()
            .get(i)
            .map_or(f64::INFINITY, |[sx, sy, _]| (x - sx).hypot(y - sy))
    };
    match best {
        Some((i, estimate)) => Some(RawAnswer {
            estimate,
            by: Answerer::Window(i),
            rho_m: rho(i),
        }),
        None => {
            let agg = snapshot.aggregate.as_ref()?;
            agg.elevation(x, y).map(|estimate| RawAnswer {
                estimate,
                by: Answerer::Aggregate,
                rho_m: rho(0),
            })
        }
    }
}

/// Elevation at (x, y): [`raw_elevation`] with its σ scaled by the snapshot's calibration
/// ([`super::calibration`]).
pub fn elevation(snapshot: &MapSnapshot, x: f64, y: f64) -> ElevationItem {
    match raw_elevation(snapshot, x, y) {
        Some(a) => {
            let source = match a.by {
                Answerer::Window(_) => Source::Window,
                Answerer::Aggregate => Source::Aggregate,
            };
            let s = snapshot.scales.factor(source, a.rho_m, &a.estimate);
            ElevationItem {
                z_m: Some(a.estimate.z),
                z_var_m2: Some(a.estimate.var * s * s),
                source,
                observed: true,
            }
        }
        None => ElevationItem {
            z_m: None,
            z_var_m2: None,
            source: Source::None,
            observed: false,
        },
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
    }
}

/// Casts one ray (already validated: finite, non-zero direction, positive range).
pub fn ray(snapshot: &MapSnapshot, ray: &Ray) -> RayItem {
    let origin = Vector3::from(ray.origin_m);
    let dir = Vector3::from(ray.direction).normalize();
    let mut near: Vec<(f64, &Arc<LocalRangeMap>)> = snapshot
        .maps()
        .iter()
        .map(|m| ((m.sensor_position() - origin).norm(), m))
        .filter(|(d, m)| *d < m.max_range() + ray.max_range_m)
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    let answers: Vec<_> = near
        .into_iter()
        .take(CANDIDATES)
        .filter_map(|(_, m)| m.cast(origin, dir, ray.max_range_m))
        .collect();
    let hit = answers.iter().filter(|a| a.range.is_some()).min_by(|a, b| {
        a.range_var
            .unwrap_or(f64::INFINITY)
            .total_cmp(&b.range_var.unwrap_or(f64::INFINITY))
    });
    let best = hit.or_else(|| {
        answers
            .iter()
            .max_by(|a, b| a.hit_probability.total_cmp(&b.hit_probability))
    });
    match best {
        Some(a) => RayItem {
            range_m: a.range,
            range_var_m2: a.range_var,
            hit_probability: a.hit_probability,
            hit_point_m: a.range.map(|t| (origin + dir * t).into()),
            source: Source::Window,
        },
        None => RayItem {
            range_m: None,
            range_var_m2: None,
            hit_probability: 0.0,
            hit_point_m: None,
            source: Source::None,
        },
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
