//! Seed-000 scans for evaluation: cast a scan, keep 20 % of its returns (noisy) for training and
//! the other 80 % (exact) as held-out test rays with their true hit points.

use nalgebra::Isometry3;
use rand::seq::SliceRandom;
use rand::Rng;
use rangegp_service::scan::{RayObservation, ScanInput};
use rangegp_sim::sensor::direction;
use rangegp_sim::{simulate_scan, ScannerPreset, Surface};

/// A held-out ray with its exact answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TestRay {
    /// Polar angle from the sensor's +z axis, radians.
    pub inclination: f64,
    /// Azimuth, radians.
    pub azimuth: f64,
    /// Exact range to the surface, metres.
    pub range: f64,
    /// Exact hit point in the map frame.
    pub point: [f64; 3],
    /// Unit direction in the map frame.
    pub dir: [f64; 3],
}

/// One scan split into training input and held-out truth.
#[derive(Debug, Clone)]
pub struct SplitScan {
    /// What a map may be fitted to: the training rays, noisy.
    pub train: ScanInput,
    /// What it is scored on.
    pub test: Vec<TestRay>,
}

/// Casts `preset` from `pose` against `surface`, drops rays without a return, and keeps a random
/// `train_fraction` of the rest (with sensor noise) for training.
pub fn split_scan<S: Surface + ?Sized, R: Rng>(
    surface: &S,
    pose: Isometry3<f64>,
    preset: &ScannerPreset,
    train_fraction: f64,
    sequence: u64,
    rng: &mut R,
) -> SplitScan {
    let mut rays: Vec<_> = simulate_scan(surface, &pose, preset, rng)
        .into_iter()
        .filter(|r| r.true_range_m.is_some())
        .collect();
    rays.shuffle(rng);
    let n_train = ((rays.len() as f64 * train_fraction).round() as usize).min(rays.len());
    let origin = pose.translation.vector;
    let test = rays[n_train..]
        .iter()
        .filter_map(|r| {
            let range = r.true_range_m?;
            let w = pose.rotation * direction(r.inclination_rad, r.azimuth_rad);
            let p = origin + w * range;
            Some(TestRay {
                inclination: r.inclination_rad,
                azimuth: r.azimuth_rad,
                range,
                point: [p.x, p.y, p.z],
                dir: [w.x, w.y, w.z],
            })
        })
        .collect();
    let mut train: Vec<RayObservation> = rays[..n_train]
        .iter()
        .filter_map(|r| {
            Some(RayObservation {
                inclination: r.inclination_rad,
                azimuth: r.azimuth_rad,
                range: r.measured_range_m?,
            })
        })
        .collect();
    // Ring-major order, as a driver delivers them.
    train.sort_by(|a, b| {
        (a.inclination, a.azimuth)
            .partial_cmp(&(b.inclination, b.azimuth))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    SplitScan {
        train: ScanInput {
            publisher_id: 0,
            sequence,
            stamp_ns: sequence * 100_000_000,
            pose,
            max_range_m: preset.max_range_m,
            range_noise_per_m: preset.range_noise_per_m,
            range_noise_floor_m: preset.range_noise_floor_m,
            rays: train,
        },
        test,
    }
}

/// A level seed-000 pose at a uniformly random place at least `margin_m` inside the map edge,
/// with a random heading.
pub fn random_pose<R: Rng>(
    terrain: &rangegp_sim::Heightmap,
    margin_m: f64,
    mount_height_m: f64,
    rng: &mut R,
) -> Isometry3<f64> {
    let lim = terrain.half_extent() - margin_m;
    let (x, y) = (rng.random_range(-lim..lim), rng.random_range(-lim..lim));
    let heading = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
    rangegp_sim::level_pose(terrain, x, y, heading, mount_height_m)
}
