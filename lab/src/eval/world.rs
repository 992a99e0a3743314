//! `rangegp-eval world` (issue 17): a map that follows the world. Pose corrections are scored in
//! [`super::drift`]; motion deskew here.
//!
//! A rotating lidar's columns fire over 100 ms while the robot drives 1 m/s and turns 30°/s. Each
//! scan is mapped three ways through the daemon's own validation and fit: deskewed (the header
//! carries the twist, each point its firing time), not deskewed (the same sweep with the twist
//! zeroed: the daemon takes every ray as fired at the stamp), and a static scan from the
//! stamp's pose (every ray at one instant: the bound deskew can reach). Elevations at the same
//! points, answered by all three, are scored against the terrain.

use super::change::{run_change, ChangeReport};
use super::drift::{run_drift, DriftReport, TIMED_TRAJECTORY_M};
use super::{progress, FamilyOptions};
use crate::scangen::{to_message, with_motion};
use anyhow::Result;
use nalgebra::{Isometry3, Vector3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::LocalRangeMap;
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, simulate_scan, simulate_sweep, Heightmap, Path, ScannerPreset, SweepMotion};
use serde::Serialize;

/// What `world.json` holds (the parts of issue 17 built so far).
#[derive(Debug, Clone, Default, Serialize)]
pub struct WorldReport {
    /// Quick (CI) or full sizes.
    pub quick: bool,
    /// Aggregate elevation RMSE of a drive mapped with drifting odometry, metres.
    pub drift_rmse_before_correction: f64,
    /// The same map after a loop closure corrected every scan's pose, metres.
    pub drift_rmse_after_correction: f64,
    /// The same drive mapped with the true poses, metres.
    pub drift_free_rmse: f64,
    /// Median time of a loop closure over a 500 m trajectory (100 m in the quick form), ms.
    pub correction_apply_ms: f64,
    /// The drift drives and the timed correction in detail.
    pub drift: DriftReport,
    /// Cells reported changed that truly changed, over all reported (an object appearing and
    /// leaving).
    pub change_cells_precision: f64,
    /// Truly changed cells reported, over those seen.
    pub change_cells_recall: f64,
    /// Scans that saw its ground before a removed object left the map (`None`: never).
    pub scans_to_clear_removed_object: Option<usize>,
    /// The moving-object drive in detail.
    pub change: ChangeReport,
    /// Elevation RMSE of deskewed sweeps, metres.
    pub deskew_rmse: f64,
    /// Elevation RMSE of the same sweeps taken as if fired at the stamp, metres.
    pub no_deskew_rmse: f64,
    /// Elevation RMSE of static scans from the stamps' poses, metres.
    pub static_rmse: f64,
    /// Points scored (answered by all three maps).
    pub points: usize,
    /// The same three RMSEs over the points within 15° of the seam behind the sensor, where the
    /// sweep's last columns meet its first (deskewed, not deskewed, static), metres.
    pub seam_rmse: [f64; 3],
    /// Points scored at the seam.
    pub seam_points: usize,
    /// Per terrain: (deskew, no deskew, static) RMSE, metres.
    pub cases: Vec<(String, [f64; 3])>,
    /// Bars missed.
    pub failures: Vec<String>,
}

/// The sweep of the issue: 100 ms, 1 m/s forward, 30°/s to the left.
pub fn issue_motion() -> SweepMotion {
    SweepMotion {
        sweep_s: 0.1,
        linear_mps: Vector3::new(1.0, 0.0, 0.0),
        angular_radps: Vector3::new(0.0, 0.0, 30f64.to_radians()),
    }
}

/// Points whose bearing in the sensor frame is beyond this (radians, 165°) lie at the seam.
const SEAM_FROM_RAD: f64 = 165.0 * std::f64::consts::PI / 180.0;

/// `deskew_rmse` may exceed `static_rmse` by this factor at most (the issue's bar).
pub const DESKEW_OVER_STATIC_MAX: f64 = 1.1;
/// `drift_rmse_after_correction` may exceed `drift_free_rmse` by this factor at most (the
/// issue's bar).
pub const CORRECTED_OVER_FREE_MAX: f64 = 1.1;
/// Change precision and recall are at least this (the issue's bar).
pub const CHANGE_MIN: f64 = 0.9;
/// A removed object leaves the map within this many scans that see its ground (the issue's bar).
pub const CLEAR_WITHIN_SCANS: usize = 3;
/// Changes reported on the static first pass, as a fraction of the cells it fused, at most:
/// about fifteen times the full run's rate (4 of 66 352 on 2026-11-25; seeds 1 and 2: 6 of
/// 67 036 and of 66 622), so that the quick form's 21 376 cells may show a few.
pub const STATIC_CHANGE_MAX_FRACTION: f64 = 1e-3;
/// A loop closure over a 500 m trajectory applies within this, milliseconds (the issue's bar;
/// checked by the full run only: CI machines are shared, timings are not asserted there).
pub const CORRECTION_APPLY_MAX_MS: f64 = 1000.0;

/// Runs the deskew evaluation.
pub fn run_world(opts: &FamilyOptions) -> Result<WorldReport> {
    let names: &[&str] = if opts.quick {
        &["craters", "fbm-h05-16deg"]
    } else {
        &[
            "craters",
            "fbm-h05-8deg",
            "fbm-h05-16deg",
            "fbm-h08-30deg",
            "boulders",
            "terraces",
        ]
    };
    let preset = ScannerPreset::os1_64(if opts.quick { 512 } else { 1024 });
    let scans = if opts.quick { 3 } else { 8 };
    let motion = issue_motion();
    let params = opts.config.map_params();
    let limits = ValidationLimits {
        max_future_ns: u64::MAX,
        ..opts.config.validation_limits()
    };
    let mut report = WorldReport {
        quick: opts.quick,
        ..WorldReport::default()
    };
    let mut total = [0.0f64; 3];
    let (mut seam, mut seam_n) = ([0.0f64; 3], 0usize);
    let bar = progress::bar((names.len() * scans) as u64, "  deskew scans");
    for spec in family().into_iter().filter(|t| names.contains(&t.name.as_str())) {
        let terrain = spec.build(opts.seed, FAMILY_SIZE_M);
        let path = Path::wander(opts.seed ^ 0xd35, &terrain, scans, 3.0, 0.25);
        let mut sums = [0.0f64; 3];
        let mut n = 0usize;
        for i in 0..scans {
            let pose = path.pose(&terrain, i, preset.mount_height_m);
            let seed = opts.seed ^ ((i as u64) << 24) ^ 0xde5;
            let maps = three_maps(&terrain, &pose, &preset, &motion, seed, &limits, &params)?;
            let mut rng = Pcg64::seed_from_u64(seed ^ 0x9e57);
            for _ in 0..400 {
                let r = rng.random_range(2.0f64..20.0);
                let a = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                let (x, y) = (pose.translation.x + r * a.cos(), pose.translation.y + r * a.sin());
                let local = pose.inverse_transform_vector(&Vector3::new(
                    x - pose.translation.x,
                    y - pose.translation.y,
                    0.0,
                ));
                let at_seam = local.y.atan2(local.x).abs() > SEAM_FROM_RAD;
                let Some(truth) = terrain.height(x, y) else {
                    continue;
                };
                let z: Vec<Option<f64>> = maps.iter().map(|m| m.elevation(x, y).map(|e| e.z)).collect();
                if let [Some(a), Some(b), Some(c)] = z[..] {
                    for (s, v) in sums.iter_mut().zip([a, b, c]) {
                        *s += (v - truth).powi(2);
                    }
                    n += 1;
                    if at_seam {
                        for (s, v) in seam.iter_mut().zip([a, b, c]) {
                            *s += (v - truth).powi(2);
                        }
                        seam_n += 1;
                    }
                }
            }
            bar.inc(1);
        }
        let rmse = sums.map(|s| (s / n.max(1) as f64).sqrt());
        report.cases.push((spec.name.clone(), rmse));
        for (t, s) in total.iter_mut().zip(sums) {
            *t += s;
        }
        report.points += n;
    }
    bar.finish_and_clear();
    let drift = run_drift(opts)?;
    report.drift_rmse_before_correction = drift.before;
    report.drift_rmse_after_correction = drift.after;
    report.drift_free_rmse = drift.free;
    report.correction_apply_ms = drift.timing.median_ms;
    if drift.points == 0 {
        report
            .failures
            .push("no point was answered by all three drift maps".into());
    } else if drift.after > CORRECTED_OVER_FREE_MAX * drift.free {
        report.failures.push(format!(
            "corrected RMSE {:.4} m > {CORRECTED_OVER_FREE_MAX} × drift-free {:.4} m",
            drift.after, drift.free
        ));
    }
    if !opts.quick
        && drift.timing.trajectory_m >= TIMED_TRAJECTORY_M
        && drift.timing.median_ms > CORRECTION_APPLY_MAX_MS
    {
        report.failures.push(format!(
            "a loop closure over {} m took {:.0} ms > {CORRECTION_APPLY_MAX_MS} ms",
            drift.timing.trajectory_m, drift.timing.median_ms
        ));
    }
    report.drift = drift;
    let change = run_change(opts)?;
    report.change_cells_precision = change.precision;
    report.change_cells_recall = change.recall;
    report.scans_to_clear_removed_object = change.scans_to_clear;
    for (what, value) in [("precision", change.precision), ("recall", change.recall)] {
        if value < CHANGE_MIN {
            report
                .failures
                .push(format!("change {what} {value:.3} < {CHANGE_MIN}"));
        }
    }
    let static_fraction = change.static_changes as f64 / change.static_cells.max(1) as f64;
    if static_fraction > STATIC_CHANGE_MAX_FRACTION {
        report.failures.push(format!(
            "{} changes reported on the static pass ({static_fraction:.5} of its cells > {STATIC_CHANGE_MAX_FRACTION})",
            change.static_changes
        ));
    }
    match change.scans_to_clear {
        Some(n) if n <= CLEAR_WITHIN_SCANS => {}
        other => report.failures.push(format!(
            "a removed object left the map after {other:?} scans that saw its ground (bar: {CLEAR_WITHIN_SCANS})"
        )),
    }
    report.change = change;
    let pooled = total.map(|s| (s / report.points.max(1) as f64).sqrt());
    report.seam_rmse = seam.map(|s| (s / seam_n.max(1) as f64).sqrt());
    report.seam_points = seam_n;
    [report.deskew_rmse, report.no_deskew_rmse, report.static_rmse] = pooled;
    if report.points == 0 {
        report
            .failures
            .push("no point was answered by all three maps".into());
    } else if report.deskew_rmse > DESKEW_OVER_STATIC_MAX * report.static_rmse {
        report.failures.push(format!(
            "deskew RMSE {:.4} m > {DESKEW_OVER_STATIC_MAX} × static {:.4} m",
            report.deskew_rmse, report.static_rmse
        ));
    }
    Ok(report)
}

/// The deskewed, the not-deskewed and the static map of one pose.
fn three_maps(
    terrain: &Heightmap,
    pose: &Isometry3<f64>,
    preset: &ScannerPreset,
    motion: &SweepMotion,
    seed: u64,
    limits: &ValidationLimits,
    params: &rangegp_service::map::local::MapParams,
) -> Result<[LocalRangeMap; 3]> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let sweep = simulate_sweep(terrain, pose, preset, motion, &mut rng);
    let still = simulate_scan(terrain, pose, preset, &mut rng);
    let (unaware, points) = to_message(preset, pose, &sweep, 1_000);
    let moving = with_motion(unaware, motion);
    let (static_header, static_points) = to_message(preset, pose, &still, 1_000);
    let fit = |h: &rangegp_proto::scan::ScanHeader,
               p: &[rangegp_proto::scan::ScanPoint]|
     -> Result<LocalRangeMap> {
        let input =
            validate(h, p, limits, 0).map_err(|r| anyhow::anyhow!("scan rejected: {}", r.as_str()))?;
        Ok(LocalRangeMap::fit(&input, params)?)
    };
    Ok([
        fit(&moving, &points)?,
        fit(&unaware, &points)?,
        fit(&static_header, &static_points)?,
    ])
}

/// Prints the report.
pub fn print_world(r: &WorldReport) {
    let d = &r.drift;
    println!(
        "\nPose corrections: {:.0} m drives with wheel odometry (1 % of distance, 2°/100 m; {:.2} m off at the end), then a loop closure ({} points)",
        d.drive_m, d.end_error_m, d.points
    );
    println!(
        "  {:16} {:>12} {:>12} {:>12}",
        "terrain", "drifted", "corrected", "true poses"
    );
    for (name, [b, a, f]) in &d.cases {
        println!("  {name:16} {b:>10.4} m {a:>10.4} m {f:>10.4} m");
    }
    println!(
        "  {:16} {:>10.4} m {:>10.4} m {:>10.4} m",
        "pooled", d.before, d.after, d.free
    );
    let c = &r.change;
    println!(
        "\nMoving objects: three passes by each (absent, present, gone), VLP-16\n  \
         reported {:?} cells (appeared, left): true {:?}, false {:?}, on its boundary {:?}, missed {:?}; precision {:.3}, recall {:.3}\n  \
         left the map after {:?} scans that saw its ground; {} cells reported changed on the static pass (of {} fused)",
        c.reported, c.true_positives, c.false_positives, c.boundary, c.missed, c.precision, c.recall, c.scans_to_clear, c.static_changes, c.static_cells
    );
    for case in &c.cases {
        println!("    {case}");
    }
    let t = &d.timing;
    println!(
        "  loop closure over {:.0} m ({} scans, ledger {:.1} MiB, {} tiles in memory, {} on disk): median {:.0} ms of {:?}, {} pages rewritten",
        t.trajectory_m, t.scans, t.ledger_mb, t.tiles_in_memory, t.tiles_on_disk, t.median_ms, t.runs_ms.iter().map(|v| v.round()).collect::<Vec<_>>(), t.pages_rewritten
    );
    println!(
        "\nMotion deskew: OS1-64 sweeping over 100 ms at 1 m/s and 30°/s ({} points)",
        r.points
    );
    println!(
        "  {:16} {:>12} {:>14} {:>10}",
        "terrain", "deskewed", "not deskewed", "static"
    );
    for (name, [d, n, s]) in &r.cases {
        println!("  {name:16} {d:>10.4} m {n:>12.4} m {s:>8.4} m");
    }
    println!(
        "  {:16} {:>10.4} m {:>12.4} m {:>8.4} m",
        "pooled", r.deskew_rmse, r.no_deskew_rmse, r.static_rmse
    );
    let [d, n, s] = r.seam_rmse;
    println!(
        "  {:16} {d:>10.4} m {n:>12.4} m {s:>8.4} m  ({} points within 15° of the sweep's seam)",
        "seam", r.seam_points
    );
}
