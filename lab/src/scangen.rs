//! Simulated scans as wire messages: the scan generator behind the demo, tests and load tests.

use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_proto::scan::{ScanHeader, ScanPoint, FLAG_NO_RETURN, FLAG_RING_COLUMN_VALID};
use rangegp_ros::scan::{pose_header, with_twist};
use rangegp_sim::{simulate_scan, CraterParams, Heightmap, Path, ScannerPreset, SimRay, SweepMotion};

/// Converts simulated rays taken from `pose` into a header (sequence and publisher id left for
/// the publisher) and the point slice.
pub fn to_message(
    preset: &ScannerPreset,
    pose: &Isometry3<f64>,
    rays: &[SimRay],
    stamp_ns: u64,
) -> (ScanHeader, Vec<ScanPoint>) {
    let header = ScanHeader {
        point_count: rays.len() as u32,
        ..pose_header(pose, stamp_ns, preset.max_range_m, preset.range_noise_per_m)
    };
    let points = rays
        .iter()
        .map(|r| ScanPoint {
            range_m: r.measured_range_m.unwrap_or(0.0) as f32,
            inclination_rad: r.inclination_rad as f32,
            azimuth_rad: r.azimuth_rad as f32,
            ring: r.ring,
            column: r.column,
            flags: FLAG_RING_COLUMN_VALID
                | if r.measured_range_m.is_none() {
                    FLAG_NO_RETURN
                } else {
                    0
                },
            reserved: 0,
            time_offset_ns: (r.time_offset_s * 1e9).round() as u32,
        })
        .collect();
    (header, points)
}

/// `header` with the sweep's twist (the daemon deskews each point by its `time_offset_ns`).
pub fn with_motion(header: ScanHeader, motion: &SweepMotion) -> ScanHeader {
    with_twist(header, motion.linear_mps.into(), motion.angular_radps.into())
}

/// A seeded world (terrain, path, sensor) producing scans along the path.
#[derive(Debug, Clone)]
pub struct ScanGenerator {
    /// Ground truth.
    pub terrain: Heightmap,
    /// The rover's path.
    pub path: Path,
    /// Sensor model.
    pub preset: ScannerPreset,
    /// Side of the chassis the sensor tilts with, metres (`None`: level on any slope).
    pub chassis_m: Option<f64>,
    seed: u64,
    rng: Pcg64,
}

/// One generated scan with its ground truth pose.
#[derive(Debug, Clone)]
pub struct GeneratedScan {
    /// Header (no sequence / publisher id yet).
    pub header: ScanHeader,
    /// Points.
    pub points: Vec<ScanPoint>,
    /// Sensor pose.
    pub pose: Isometry3<f64>,
}

impl ScanGenerator {
    /// A cratered world of `size_m` metres from `seed`, with a wander path of `scans` poses
    /// `step_m` apart.
    pub fn new(seed: u64, size_m: f64, preset: ScannerPreset, scans: usize, step_m: f64) -> Self {
        Self::on(
            Heightmap::cratered(seed, &CraterParams::sized(size_m)),
            seed,
            preset,
            scans,
            step_m,
        )
    }

    /// The same on `terrain` (a DEM, say): a wander path from `seed` of `scans` poses `step_m`
    /// apart.
    pub fn on(terrain: Heightmap, seed: u64, preset: ScannerPreset, scans: usize, step_m: f64) -> Self {
        let path = Path::wander(seed ^ 0x5eed, &terrain, scans, step_m, 0.25);
        Self {
            terrain,
            path,
            preset,
            chassis_m: None,
            seed,
            rng: Pcg64::seed_from_u64(seed ^ 0x0015e),
        }
    }

    /// The same with the sensor on a chassis `side_m` square whose wheels rest on the ground, so
    /// that it tilts with the slopes it drives (`None`: level; [`rangegp_sim::chassis_pose`]).
    pub fn with_chassis(self, side_m: Option<f64>) -> Self {
        Self {
            chassis_m: side_m,
            ..self
        }
    }

    /// Scans on the path.
    pub fn len(&self) -> usize {
        self.path.waypoints.len()
    }

    /// True when the path is empty.
    pub fn is_empty(&self) -> bool {
        self.path.waypoints.is_empty()
    }

    /// Simulates the scan at waypoint `i` (noise drawn from the generator's stream).
    pub fn scan(&mut self, i: usize, stamp_ns: u64) -> GeneratedScan {
        let Self {
            terrain,
            path,
            preset,
            chassis_m,
            rng,
            ..
        } = self;
        let pose = path.pose_on(terrain, i, preset.mount_height_m, *chassis_m);
        generate(terrain, pose, preset, stamp_ns, rng)
    }

    /// Simulates the scan at waypoint `i` with noise from a stream of its own, so that scans
    /// can be made in parallel and still reproducibly.
    pub fn scan_independent(&self, i: usize, stamp_ns: u64) -> GeneratedScan {
        let stream = (self.seed ^ 0x1dea).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ i as u64;
        let rng = &mut Pcg64::seed_from_u64(stream);
        let pose = self
            .path
            .pose_on(&self.terrain, i, self.preset.mount_height_m, self.chassis_m);
        generate(&self.terrain, pose, &self.preset, stamp_ns, rng)
    }
}

/// The scan from `pose`, noise drawn from `rng`.
fn generate(
    terrain: &Heightmap,
    pose: Isometry3<f64>,
    preset: &ScannerPreset,
    stamp_ns: u64,
    rng: &mut Pcg64,
) -> GeneratedScan {
    let rays = simulate_scan(terrain, &pose, preset, rng);
    let (header, points) = to_message(preset, &pose, &rays, stamp_ns);
    GeneratedScan { header, points, pose }
}

/// Nanoseconds since the Unix epoch now (0 if the clock is before 1970).
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::SimSensorArgs;

    #[test]
    fn a_sensor_told_to_lose_weak_returns_sends_fewer_from_the_same_pose() {
        let returns = |preset: ScannerPreset| {
            let mut world = ScanGenerator::new(3, 100.0, preset, 2, 1.0);
            let scan = world.scan(0, 0);
            scan.points
                .iter()
                .filter(|p| p.flags & FLAG_NO_RETURN == 0)
                .count()
        };
        let sensor = |weak_returns_m| SimSensorArgs {
            weak_returns_m,
            ..SimSensorArgs::default()
        };
        let all = returns(sensor(None).preset(ScannerPreset::vlp16()));
        let weak = returns(sensor(Some(15.0)).preset(ScannerPreset::vlp16()));
        assert!(weak > 0 && weak < all, "{weak} of {all} returns kept");
    }
}
