//! Shared fixtures of the map tests: the seed-000 map parameters and a simulated scan.

use super::local::{MapParams, PriorKind, RangeTarget};
use super::tiles::Tiling;
use crate::gp::{JitterPolicy, Kernel};
use crate::scan::{RayObservation, ScanInput};
use nalgebra::Isometry3;
use rand::SeedableRng;
use rangegp_sim::{simulate_scan, Heightmap, ScannerPreset};

/// Seed-000 local-map parameters (flat-ground prior, the configured kernel defaults).
pub(crate) fn params() -> MapParams {
    MapParams {
        kernel: Kernel::matern32(5e-4, 0.97),
        sphere_radius_m: Some(10.0),
        nugget_m2: 1e-6,
        max_training_rays: 2000,
        tiling: Tiling::default(),
        prior: PriorKind::FlatGround {
            sensor_height_m: 0.75,
        },
        target: RangeTarget::Range,
        jitter: JitterPolicy::default(),
        variance_calibration: crate::map::tiles::VarianceCalibration::None,
        index_data: true,
        view_ceiling: true,
    }
}

/// A rover's planner layers (the `[layers]` defaults) under a Gaussian error of the default
/// correlation length.
pub(crate) fn layer_model() -> super::layers::LayerModel {
    super::layers::LayerModel {
        robot: rangegp_proto::msg::RobotModel {
            footprint_radius_m: 0.3,
            max_slope_deg: 20.0,
            max_step_m: 0.2,
            lethal_risk: 0.5,
        },
        error_length_m: super::scales::DEFAULT_ERROR_LENGTH_M,
        tails: super::scales::TailShape::default(),
        relief: super::scales::Relief::default(),
    }
}

/// The terrain of the sim family called `name`, built from `seed` over `size_m` × `size_m`.
pub(crate) fn family_terrain(name: &str, seed: u64, size_m: f64) -> Heightmap {
    rangegp_sim::family::family()
        .into_iter()
        .find(|t| t.name == name)
        .unwrap_or_else(|| panic!("no terrain {name} in the sim family"))
        .build(seed, size_m)
}

/// A noisy seed-000 scan of `terrain` from 0.75 m above the ground at its centre.
pub(crate) fn scan_at_centre(terrain: &Heightmap) -> ScanInput {
    let ground = terrain.height(0.0, 0.0).expect("the centre lies on the terrain");
    scan_of(terrain, Isometry3::translation(0.0, 0.0, ground + 0.75))
}

/// A noisy seed-000 scan of `terrain` from `pose` (returns only).
pub(crate) fn scan_of(terrain: &Heightmap, pose: Isometry3<f64>) -> ScanInput {
    scan_by(&ScannerPreset::seed000(), terrain, pose)
}

/// A noisy scan of `terrain` by `preset` from `pose` (returns only).
pub(crate) fn scan_by(preset: &ScannerPreset, terrain: &Heightmap, pose: Isometry3<f64>) -> ScanInput {
    let rays = simulate_scan(terrain, &pose, preset, &mut rand_pcg::Pcg64::seed_from_u64(5));
    ScanInput {
        publisher_id: 1,
        sequence: 1,
        stamp_ns: 0,
        pose,
        max_range_m: preset.max_range_m,
        range_noise_per_m: preset.range_noise_per_m,
        range_noise_floor_m: preset.range_noise_floor_m,
        rays: rays
            .iter()
            .filter_map(|r| {
                r.measured_range_m.map(|range| RayObservation {
                    inclination: r.inclination_rad,
                    azimuth: r.azimuth_rad,
                    range,
                })
            })
            .collect(),
    }
}
