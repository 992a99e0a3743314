//! A simulated drive mapped as the daemon maps it (validation, local maps, the window, the world
//! aggregate, prequential σ calibration, one snapshot after each scan): the scene the
//! calibration and view evaluations query.

use super::progress;
use crate::scangen::to_message;
use anyhow::Result;
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_service::config::Config;
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::calibration::Calibrator;
use rangegp_service::map::local::tilt_of;
use rangegp_service::map::{LocalRangeMap, MapSnapshot, Window};
use rangegp_service::scan::ScanInput;
use rangegp_sim::{simulate_scan, Heightmap, Path, ScannerPreset};
use rayon::prelude::*;
use std::sync::Arc;

/// How to drive: the scans, their seeds and stamps, and what the aggregate does.
pub(super) struct Drive<'a> {
    /// Daemon configuration mapped with (its window, calibration and aggregate settings).
    pub config: &'a Config,
    /// Poses along the wandering path.
    pub scans: usize,
    /// Distance between consecutive poses, metres (the robot's speed over its scan rate).
    pub step_m: f64,
    /// Side of the chassis the sensor tilts with, metres (`None`: the sensor stays level).
    pub chassis_m: Option<f64>,
    /// Scans taken after the drive from where it ended, the robot standing still.
    pub stop_scans: usize,
    /// Seed of the path.
    pub path_seed: u64,
    /// Seed of scan `i`'s noise.
    pub scan_seed: &'a (dyn Fn(usize) -> u64 + Sync),
    /// Stamp of scan `i` is `stamp_base + i`.
    pub stamp_base: u64,
    /// Evict aggregate tiles beyond `aggregate.radius_m`, as the daemon does (else keep all).
    pub evict: bool,
    /// Show a progress bar while simulating.
    pub progress: bool,
    /// Numbers of scans mapped after which the snapshot is kept as well (besides the last).
    pub keep_after: &'a [usize],
}

/// The drive's path, poses and the snapshot after its last scan.
pub(super) struct MappedDrive {
    /// The path driven.
    pub path: Path,
    /// The sensor pose of each scan.
    pub poses: Vec<Isometry3<f64>>,
    /// The maps as queries see them after the last scan.
    pub snapshot: MapSnapshot,
    /// The maps after each of [`Drive::keep_after`]'s numbers of scans, in the order the drive
    /// reached them (those beyond the drive are left out).
    pub kept: Vec<MapSnapshot>,
}

/// Simulates and maps `drive` on `terrain` with `preset`.
pub(super) fn map_drive(terrain: &Heightmap, preset: &ScannerPreset, drive: &Drive) -> Result<MappedDrive> {
    let config = drive.config;
    let params = config.map_params();
    // The same curvature at any step: 0.25 rad of turn at most per metre driven.
    let path = Path::wander(
        drive.path_seed,
        terrain,
        drive.scans,
        drive.step_m,
        0.25 * drive.step_m,
    );
    let poses: Vec<Isometry3<f64>> = (0..drive.scans + drive.stop_scans)
        .map(|i| {
            path.pose_on(
                terrain,
                i.min(drive.scans - 1),
                preset.mount_height_m,
                drive.chassis_m,
            )
        })
        .collect();
    if let Some(side) = drive.chassis_m {
        let mut tilts: Vec<f64> = poses.iter().map(|p| tilt_of(p).to_degrees()).collect();
        tilts.sort_by(f64::total_cmp);
        eprintln!(
            "  {} on a {side} m chassis: sensor tilt median {:.1}°, max {:.1}°",
            preset.name,
            tilts[tilts.len() / 2],
            tilts[tilts.len() - 1]
        );
    }
    let bar = drive
        .progress
        .then(|| progress::bar(poses.len() as u64, &format!("  {} scans", preset.name)));
    let messages: Vec<_> = poses
        .par_iter()
        .enumerate()
        .map(|(i, pose)| {
            let mut rng = Pcg64::seed_from_u64((drive.scan_seed)(i));
            let rays = simulate_scan(terrain, pose, preset, &mut rng);
            let (mut header, points) = to_message(preset, pose, &rays, drive.stamp_base + i as u64);
            header.protocol_version = rangegp_proto::PROTOCOL_VERSION;
            header.sequence = i as u64 + 1;
            if let Some(bar) = &bar {
                bar.inc(1);
            }
            (header, points)
        })
        .collect();
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    let limits = ValidationLimits {
        max_future_ns: u64::MAX,
        ..config.validation_limits()
    };
    let mut window = Window::new(config.window.capacity);
    let mut world = WorldAggregate::new(WorldParams::default());
    let mut calibrator = calibrator_for(config);
    let mut snapshot = MapSnapshot::default().with_max_sigma(config.query.max_sigma_m);
    let mut kept = Vec::with_capacity(drive.keep_after.len());
    for (mapped, (header, points)) in messages.iter().enumerate() {
        let input = validate(header, points, &limits, 0)
            .map_err(|r| anyhow::anyhow!("scan rejected: {}", r.as_str()))?;
        let map = Arc::new(LocalRangeMap::fit(&input, &params)?);
        let scales = calibrator.as_mut().map(|c| {
            c.observe(&snapshot, &input, &map);
            c.scales()
        });
        if config.aggregate.enabled {
            if let Some(scales) = &scales {
                world.set_window_scales(scales);
            }
            let radius_m = if drive.evict {
                config.aggregate.radius_m
            } else {
                f64::INFINITY
            };
            world.insert_and_evict(&input, &map, radius_m)?;
        }
        window.push(map);
        snapshot = window
            .snapshot()
            .with_aggregate(config.aggregate.enabled.then(|| Arc::new(world.clone())))
            .with_scales(scales.unwrap_or_default())
            .with_max_sigma(config.query.max_sigma_m);
        if drive.keep_after.contains(&(mapped + 1)) {
            kept.push(snapshot.clone());
        }
    }
    Ok(MappedDrive {
        path,
        poses,
        snapshot,
        kept,
    })
}

/// The daemon's σ calibrator as `config` sets it up (none when it turns it off).
fn calibrator_for(config: &Config) -> Option<Calibrator> {
    config
        .gp
        .prequential_calibration
        .then(|| Calibrator::new(config.gp.unseen_relief).with_view_disagreement(config.gp.view_disagreement))
}

/// Learns the window's σ scales from a drive's scans as the daemon learns them, for drives that
/// fold their scans into an aggregate directly: the scales weigh what the aggregate fuses.
pub(super) struct ScaleLearner {
    calibrator: Option<Calibrator>,
    window: Window,
}

impl ScaleLearner {
    /// Nothing learnt yet; nothing will be when `config` turns the prequential calibration off.
    pub(super) fn new(config: &Config) -> Self {
        Self {
            calibrator: calibrator_for(config),
            window: Window::new(config.window.capacity),
        }
    }

    /// Learns from `map` (of `input`) against the maps before it, hands `world` the scales, and
    /// keeps the map in the window.
    pub(super) fn observe(&mut self, input: &ScanInput, map: Arc<LocalRangeMap>, world: &mut WorldAggregate) {
        if let Some(c) = self.calibrator.as_mut() {
            c.observe(&self.window.snapshot().with_scales(c.scales()), input, &map);
            world.set_window_scales(&c.scales());
        }
        self.window.push(map);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_drive_keeps_the_snapshots_it_is_asked_for_and_none_past_its_end() {
        let terrain = Heightmap::flat(80.0, 0.1, 0.0);
        let config = Config::default();
        let drive = Drive {
            config: &config,
            scans: 3,
            step_m: 1.0,
            chassis_m: None,
            stop_scans: 0,
            path_seed: 1,
            scan_seed: &|i| i as u64,
            stamp_base: 1_000,
            evict: true,
            progress: false,
            keep_after: &[1, 2, 9],
        };
        let mapped = map_drive(&terrain, &ScannerPreset::vlp16(), &drive).expect("flat ground maps");
        let maps: Vec<usize> = mapped.kept.iter().map(|s| s.maps().len()).collect();
        assert_eq!(maps, [1, 2]);
        assert_eq!(mapped.snapshot.maps().len(), 3);
    }
}
