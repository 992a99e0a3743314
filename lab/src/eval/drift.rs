//! Pose corrections in `rangegp-eval world` (issue 17): a drive mapped with drifting odometry,
//! then a loop closure that gives every scan its true pose, against the same drive mapped with
//! the true poses; and the time a correction of a 500 m trajectory takes.
//!
//! Both drives go through the daemon's own code: validation, the local fit, the world
//! aggregate's insert with its ledger, and `correct_aggregate` (what the aggregate thread runs
//! when a correction arrives).

use super::drive::ScaleLearner;
use super::{progress, FamilyOptions};
use crate::scangen::to_message;
use anyhow::Result;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_proto::msg::{CorrectionRequest, PoseCorrection, Rigid};
use rangegp_service::checkpoint::{self, PageStore};
use rangegp_service::daemon::correct_aggregate;
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::aggregate::ledger::{CellEdit, FusedCell, Ledger, ScanRaster};
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::aggregate::Aggregate;
use rangegp_service::map::correction::Correction;
use rangegp_service::map::LocalRangeMap;
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, simulate_scan, Heightmap, OdometryDrift, Path, ScannerPreset};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

/// The drift part of `world.json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct DriftReport {
    /// Aggregate elevation RMSE mapped with the drifting odometry, metres.
    pub before: f64,
    /// The same map after the loop closure's correction, metres.
    pub after: f64,
    /// The same drive mapped with the true poses, metres.
    pub free: f64,
    /// Points scored (answered by all three maps).
    pub points: usize,
    /// Length of each drive, metres.
    pub drive_m: f64,
    /// Odometry's position error at the end of each drive, metres (mean over terrains).
    pub end_error_m: f64,
    /// Per terrain: (before, after, drift-free) RMSE, metres.
    pub cases: Vec<(String, [f64; 3])>,
    /// The timed correction: see [`ApplyTiming`].
    pub timing: ApplyTiming,
}

/// A loop closure over a long trajectory, timed.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ApplyTiming {
    /// Trajectory length, metres.
    pub trajectory_m: f64,
    /// Scans in the ledger (10 per metre: 10 Hz at 1 m/s).
    pub scans: usize,
    /// Ledger memory, MiB.
    pub ledger_mb: f64,
    /// Tiles in memory (within the daemon's 30 m radius) and on disk.
    pub tiles_in_memory: usize,
    /// Tiles paged to disk.
    pub tiles_on_disk: usize,
    /// Wall time of each run of the correction, milliseconds (the median is reported).
    pub runs_ms: Vec<f64>,
    /// Median of `runs_ms`.
    pub median_ms: f64,
    /// Pages rewritten.
    pub pages_rewritten: u32,
}

/// Runs the drift evaluation.
pub fn run_drift(opts: &FamilyOptions) -> Result<DriftReport> {
    let names: &[&str] = if opts.quick {
        &["fbm-h05-16deg"]
    } else {
        &["craters", "fbm-h05-8deg", "fbm-h05-16deg", "boulders"]
    };
    let scans = if opts.quick { 30 } else { 100 };
    let preset = ScannerPreset::vlp16();
    let mut report = DriftReport {
        drive_m: (scans - 1) as f64,
        ..DriftReport::default()
    };
    let mut total = [0.0f64; 3];
    let bar = progress::bar((names.len() * scans) as u64, "  drift drives");
    for spec in family().into_iter().filter(|t| names.contains(&t.name.as_str())) {
        let terrain = spec.build(opts.seed, FAMILY_SIZE_M);
        let path = Path::wander(opts.seed ^ 0xd21f, &terrain, scans, 1.0, 0.25);
        let truth: Vec<Isometry3<f64>> = (0..scans)
            .map(|i| path.pose(&terrain, i, preset.mount_height_m))
            .collect();
        let odometry = OdometryDrift::wheels().apply(&truth);
        report.end_error_m += (odometry[scans - 1].translation.vector - truth[scans - 1].translation.vector)
            .norm()
            / names.len() as f64;
        let free = map_drive(&terrain, &preset, &truth, &truth, opts, &bar)?.0;
        let (drifted, mut ledger) = map_drive(&terrain, &preset, &truth, &odometry, opts, &bar)?;
        let closure = Correction::from_request(&CorrectionRequest {
            version: rangegp_proto::PROTOCOL_VERSION,
            corrections: truth
                .iter()
                .enumerate()
                .map(|(i, p)| PoseCorrection::Scan {
                    publisher_id: 1,
                    sequence: i as u64 + 1,
                    pose: rigid(p),
                })
                .collect(),
        })?;
        let corrected = correct_aggregate(&drifted, &mut ledger, None, &closure)?;
        anyhow::ensure!(
            corrected.moved == scans,
            "{} of {scans} scans moved",
            corrected.moved
        );
        let mut rng = Pcg64::seed_from_u64(opts.seed ^ 0xd21f7);
        let (mut sums, mut n) = ([0.0f64; 3], 0usize);
        for _ in 0..4000 {
            let p = truth[rng.random_range(0..scans)].translation.vector;
            let (r, a) = (rng.random_range(1.0f64..9.0), rng.random_range(-3.2f64..3.2));
            let (x, y) = (p.x + r * a.cos(), p.y + r * a.sin());
            let Some(z) = terrain.height(x, y) else { continue };
            let answers = [&drifted, &corrected.world, &free].map(|m| m.elevation(x, y).map(|e| e.z));
            if let [Some(b), Some(c), Some(f)] = answers {
                for (s, v) in sums.iter_mut().zip([b, c, f]) {
                    *s += (v - z).powi(2);
                }
                n += 1;
            }
        }
        let rmse = sums.map(|s| (s / n.max(1) as f64).sqrt());
        report.cases.push((spec.name.clone(), rmse));
        for (t, s) in total.iter_mut().zip(sums) {
            *t += s;
        }
        report.points += n;
    }
    bar.finish_and_clear();
    [report.before, report.after, report.free] = total.map(|s| (s / report.points.max(1) as f64).sqrt());
    report.timing = time_long_correction(opts)?;
    Ok(report)
}

fn rigid(p: &Isometry3<f64>) -> Rigid {
    let q = p.rotation;
    Rigid {
        translation_m: p.translation.vector.into(),
        rotation_xyzw: [q.i, q.j, q.k, q.w],
    }
}

/// Scans simulated from the `truth` poses, sent with the `sent` poses, fused as the daemon does
/// (10 m reach, nothing evicted); returns the aggregate and its ledger.
fn map_drive(
    terrain: &Heightmap,
    preset: &ScannerPreset,
    truth: &[Isometry3<f64>],
    sent: &[Isometry3<f64>],
    opts: &FamilyOptions,
    bar: &indicatif::ProgressBar,
) -> Result<(WorldAggregate, Ledger)> {
    let params = opts.config.map_params();
    let limits = ValidationLimits {
        max_future_ns: u64::MAX,
        ..opts.config.validation_limits()
    };
    let fitted: Vec<_> = truth
        .par_iter()
        .zip(sent)
        .enumerate()
        .map(|(i, (t, s))| -> Result<_> {
            let mut rng = Pcg64::seed_from_u64(opts.seed ^ ((i as u64) << 20) ^ 0xd21f);
            let rays = simulate_scan(terrain, t, preset, &mut rng);
            let (mut header, points) = to_message(preset, s, &rays, 1_000 + i as u64);
            header.sequence = i as u64 + 1;
            header.publisher_id = 1;
            let input = validate(&header, &points, &limits, 0)
                .map_err(|r| anyhow::anyhow!("scan rejected: {}", r.as_str()))?;
            let map = LocalRangeMap::fit(&input, &params)?;
            Ok((input, map))
        })
        .collect::<Result<_>>()?;
    let mut world = WorldAggregate::new(WorldParams::default());
    let mut ledger = Ledger::new(opts.config.aggregate.ledger_mib << 20);
    let mut scales = ScaleLearner::new(&opts.config);
    for (input, map) in fitted {
        let map = Arc::new(map);
        scales.observe(&input, Arc::clone(&map), &mut world);
        let inserted = world.insert_all_and_evict(&[(&input, map.as_ref())], f64::INFINITY, f64::INFINITY)?;
        for raster in inserted.fused {
            ledger.push(raster);
        }
        bar.inc(1);
    }
    Ok((world, ledger))
}

/// Trajectory of the timed correction, metres.
pub const TIMED_TRAJECTORY_M: f64 = 500.0;
/// Scans per metre of it (10 Hz at 1 m/s).
const SCANS_PER_M: usize = 10;
/// Reach each of its scans is fused out to, metres (an OS1-64 at 10 Hz on two cores).
const TIMED_REACH_M: f64 = 6.0;
/// The daemon's eviction radius, metres.
const RADIUS_M: f64 = 30.0;

/// Times a loop closure (every scan moved by 0.5 m and 1°) over a 500 m trajectory's ledger of
/// 5 000 scans, with the tiles beyond 30 m of the robot paged to disk as the daemon keeps them.
/// The scans' cells are the terrain's heights (σ 1 cm): a correction's cost depends on the
/// cells moved, not on how they were predicted, and fitting 5 000 scans would take minutes.
fn time_long_correction(opts: &FamilyOptions) -> Result<ApplyTiming> {
    let terrain = family()
        .into_iter()
        .find(|t| t.name == "fbm-h05-8deg")
        .map(|t| t.build(opts.seed, FAMILY_SIZE_M))
        .ok_or_else(|| anyhow::anyhow!("no fbm-h05-8deg terrain"))?;
    let metres = if opts.quick { 100.0 } else { TIMED_TRAJECTORY_M };
    let steps = (metres / 1.0).round() as usize;
    let path = Path::wander(opts.seed ^ 0x7173, &terrain, steps + 1, 1.0, 0.25);
    let params = WorldParams::default();
    let cell = params.cell_m;
    let mut ledger = Ledger::new(opts.config.aggregate.ledger_mib << 20);
    let mut edits: HashMap<(i32, i32), CellEdit> = HashMap::new();
    let bar = progress::bar((steps * SCANS_PER_M) as u64, "  500 m ledger");
    for k in 0..steps * SCANS_PER_M {
        let f = k as f64 / SCANS_PER_M as f64;
        let (a, b) = (
            path.waypoints[f.floor() as usize],
            path.waypoints[f.floor() as usize + 1],
        );
        let t = f.fract();
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        let pose = Isometry3::from_parts(
            Translation3::new(x, y, terrain.height(x, y).unwrap_or(0.0) + 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, a[2]),
        );
        let reach = (TIMED_REACH_M / cell).ceil() as i32;
        let (ci, cj) = ((x / cell).floor() as i32, (y / cell).floor() as i32);
        let cells: Vec<FusedCell> = (-reach..=reach)
            .flat_map(|di| (-reach..=reach).map(move |dj| (ci + di, cj + dj)))
            .filter_map(|(i, j)| {
                let (cx, cy) = ((i as f64 + 0.5) * cell, (j as f64 + 0.5) * cell);
                ((cx - x).hypot(cy - y) < TIMED_REACH_M)
                    .then(|| terrain.height(cx, cy))
                    .flatten()
                    .map(|z| ((i, j), z as f32, 1e-4f32))
            })
            .collect();
        for &(c, z, var) in &cells {
            edits.entry(c).or_default().add(z as f64, var as f64, 1.0);
        }
        ledger.push(ScanRaster::new((1, k as u64 + 1, k as u64), pose, &cells));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mut world = WorldAggregate::new(params);
    world.apply_edits(edits, &|_| false)?;
    let dir = std::env::temp_dir().join(format!("rangegp-eval-pages-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut store = PageStore::open(&dir, checkpoint::identity("eval", &params))?;
    let last = path.waypoints[steps];
    for page in world.evict_beyond(last[0], last[1], RADIUS_M) {
        store.write(&page)?;
    }
    let mut timing = ApplyTiming {
        trajectory_m: metres,
        scans: ledger.len(),
        ledger_mb: ledger.bytes() as f64 / f64::from(1 << 20),
        tiles_in_memory: world.tiles(),
        tiles_on_disk: store.keys().len(),
        ..ApplyTiming::default()
    };
    anyhow::ensure!(
        ledger.forgotten() == 0,
        "the ledger's budget ({} MiB) does not hold a {metres} m trajectory",
        opts.config.aggregate.ledger_mib
    );
    // A loop closure: every scan moved by 0.5 m and 1° (alternately there and back, so each run
    // moves the same amount).
    for run in 0..3 {
        let sign = if run % 2 == 0 { 1.0 } else { -1.0 };
        let transform = Isometry3::from_parts(
            Translation3::new(0.5 * sign, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, sign * 1f64.to_radians()),
        );
        let closure = Correction::from_request(&CorrectionRequest {
            version: rangegp_proto::PROTOCOL_VERSION,
            corrections: vec![PoseCorrection::Transform {
                publisher_id: None,
                from_stamp_ns: 0,
                until_stamp_ns: u64::MAX,
                transform: rigid(&transform),
            }],
        })?;
        let started = Instant::now();
        let corrected = correct_aggregate(&world, &mut ledger, Some(&mut store), &closure)?;
        timing.runs_ms.push(started.elapsed().as_secs_f64() * 1e3);
        timing.pages_rewritten = corrected.pages_rewritten;
        world = corrected.world;
    }
    let _ = std::fs::remove_dir_all(&dir);
    let mut sorted = timing.runs_ms.clone();
    sorted.sort_by(f64::total_cmp);
    timing.median_ms = sorted[sorted.len() / 2];
    Ok(timing)
}
