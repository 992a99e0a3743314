//! Which returns of a scan test the maps, and the ground area each stands for.

use super::{Return, PER_BIN_PER_SCAN};
use crate::gp::sphere;
use crate::map::scales::{bin_of, BINS};
use crate::map::LocalRangeMap;
use crate::scan::{RayObservation, ScanInput};
use nalgebra::Vector3;
use std::collections::HashMap;

/// Step of the finite differences that give a return's surface normal, radians (0.1°).
const NORMAL_STEP_RAD: f64 = 1.745e-3;
/// Floor of the cosine between a ray and the surface normal in a return's area weight (a
/// return grazing the surface at under 3° counts as if at 3°).
const MIN_COS_INCIDENCE: f64 = 0.05;

/// A sampled return: its map point, its noise variance along z (m²) and the ground area it
/// stands for ([`area_weight`]).
pub(super) type Sampled = (Vector3<f64>, f64, f64);

/// Horizontal radius of the patch of a scan's returns whose mean stands for a sampled return,
/// metres: well inside the correlation lengths of the maps' errors the calibrator learns
/// (0.19–0.82 m, docs/EVALUATION.md "Planner layers"), so the patch shares its map's error, while
/// its returns' noises, independent, average down.
pub(super) const PATCH_RADIUS_M: f64 = 0.05;

/// Up to [`PER_BIN_PER_SCAN`] returns of `scan` per range bin from `reference` (a sensor position),
/// spread over the scan by a stride coprime with its size; each as the mean map point of its
/// patch ([`patch_means`]), that mean's noise variance along z and the ground area the return
/// stands for ([`area_weight`]).
pub(super) fn stratified_sample(
    scan: &ScanInput,
    map: &LocalRangeMap,
    reference: &Vector3<f64>,
) -> Vec<Sampled> {
    let n = scan.rays.len();
    let mut quota = [PER_BIN_PER_SCAN; BINS];
    let mut out = Vec::with_capacity(BINS * PER_BIN_PER_SCAN);
    if n == 0 {
        return out;
    }
    let stride = coprime_stride(n);
    let mut k = (scan.sequence as usize).wrapping_mul(2_654_435_761) % n;
    for _ in 0..n {
        let ray = &scan.rays[k];
        k = (k + stride) % n;
        let (p, noise_var) = map_return(scan, ray);
        let bin = bin_of((p.x - reference.x).hypot(p.y - reference.y));
        if quota[bin] == 0 {
            continue;
        }
        quota[bin] -= 1;
        let weight = area_weight(scan, map, ray.inclination, ray.azimuth, ray.range);
        out.push((p, noise_var, weight));
        if quota.iter().all(|&q| q == 0) {
            break;
        }
    }
    patch_means(scan, &mut out);
    out
}

/// Replaces each sampled return of `sample` (map point, noise variance along z, weight) by the
/// mean of the returns of `scan` within [`PATCH_RADIUS_M`] of it horizontally and on its surface
/// (heights within the radius plus three noise σ of both: a 45° bound, so a patch at a step
/// keeps the sampled return's side), with the mean's noise variance. Near the sensor a return's
/// noise can be several times the map's error, and a test of single returns then cannot tell a
/// map right from one too sure; the mean of k returns has a k-th of the noise and the same map
/// error.
pub(super) fn patch_means(scan: &ScanInput, sample: &mut [Sampled]) {
    let r = PATCH_RADIUS_M;
    let key = |p: &Vector3<f64>| ((p.x / r).floor() as i64, (p.y / r).floor() as i64);
    let mut near: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (i, (p, _, _)) in sample.iter().enumerate() {
        let (x, y) = key(p);
        for dx in -1..=1 {
            for dy in -1..=1 {
                near.entry((x + dx, y + dy)).or_default().push(i);
            }
        }
    }
    // Per sampled return: the sum of its patch's offsets from it, of their noise variances, and
    // their count.
    let mut sums = vec![(Vector3::zeros(), 0.0, 0usize); sample.len()];
    for ray in &scan.rays {
        let (q, q_var) = map_return(scan, ray);
        let Some(ids) = near.get(&key(&q)) else {
            continue;
        };
        for &i in ids {
            let (p, noise_var, _) = sample[i];
            let d = q - p;
            if d.xy().norm() <= r && d.z.abs() <= r + 3.0 * (noise_var.sqrt() + q_var.sqrt()) {
                let s = &mut sums[i];
                s.0 += d;
                s.1 += q_var;
                s.2 += 1;
            }
        }
    }
    for ((p, noise_var, _), (offsets, var_sum, k)) in sample.iter_mut().zip(sums) {
        if k > 1 {
            let k = k as f64;
            *p += offsets / k;
            *noise_var = var_sum / (k * k);
        }
    }
}

/// Return `ray` of `scan` in the map frame, with its range noise's variance along z (m²).
pub(super) fn map_return(scan: &ScanInput, ray: &RayObservation) -> Return {
    let [x, y, z] = sphere::to_sphere(ray.inclination, ray.azimuth, 1.0);
    let dir = scan.pose.rotation * Vector3::new(x, y, z);
    let sd = scan.range_sd(ray.range) * dir.z;
    (scan.pose.translation.vector + dir * ray.range, sd * sd)
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
pub(super) fn coprime_stride(n: usize) -> usize {
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
