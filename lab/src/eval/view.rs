//! `rangegp-eval view`: rays from poses no scan was taken at, over ground that only scans long
//! gone from the window saw, against the simulator's exact ray caster (issue 16).
//!
//! On each terrain and sensor, a drive of `scans` poses is mapped as the daemon maps it (window,
//! aggregate, prequential σ calibration). Then views are cast from poses beside the early path
//! (its maps left the window: the aggregate answers) and beside the late path (the window
//! answers): range RMSE and 95 % coverage of each, and the share of rays towards ground the
//! drive saw that get a range at all.

use super::calibration::Coverage;
use super::drive::{map_drive, Drive, MappedDrive};
use super::FamilyOptions;
use anyhow::Result;
use nalgebra::{UnitQuaternion, Vector3};
use rangegp_proto::msg::{Provenance, Ray, Source};
use rangegp_service::map::query;
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, Heightmap, ScannerPreset};
use serde::Serialize;
use std::collections::BTreeMap;

/// What `view.json` holds.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ViewReport {
    /// Quick (CI) or full sizes.
    pub quick: bool,
    /// Range RMSE of rays over ground only evicted scans saw, metres.
    pub evicted_ray_rmse: f64,
    /// Their share within 1.96 σ of the true range.
    pub evicted_ray_cov95: f64,
    /// Range RMSE of rays over ground the window sees, metres.
    pub window_ray_rmse: f64,
    /// Their share within 1.96 σ.
    pub window_ray_cov95: f64,
    /// Rays towards ground the drive saw that got a range.
    pub answered_fraction: f64,
    /// Rays scored (evicted, window).
    pub rays: [usize; 2],
    /// Answers of the evicted area by source (`window`, `aggregate`).
    pub evicted_sources: BTreeMap<String, usize>,
    /// Answers by provenance, both areas.
    pub provenance: BTreeMap<String, usize>,
    /// Per terrain and sensor: (evicted RMSE, evicted cov95, window RMSE, window cov95, answered).
    pub cases: Vec<(String, String, [f64; 5])>,
    /// Bars missed.
    pub failures: Vec<String>,
}

/// Accumulated errors of one area.
#[derive(Debug, Default)]
struct Area {
    sq: f64,
    within: usize,
    n: usize,
}

impl Area {
    fn push(&mut self, err: f64, sd: f64) {
        self.sq += err * err;
        self.within += usize::from(err.abs() <= 1.96 * sd);
        self.n += 1;
    }

    fn rmse(&self) -> f64 {
        (self.sq / self.n.max(1) as f64).sqrt()
    }

    fn cov95(&self) -> f64 {
        self.within as f64 / self.n.max(1) as f64
    }
}

/// Runs the evaluation.
pub fn run_view(opts: &FamilyOptions) -> Result<ViewReport> {
    let terrains: Vec<_> = family()
        .into_iter()
        .filter(|t| !opts.quick || ["craters", "fbm-h05-16deg"].contains(&t.name.as_str()))
        .collect();
    let sensors = [ScannerPreset::seed000(), ScannerPreset::vlp16()];
    let (mut evicted, mut window) = (Area::default(), Area::default());
    let (mut seen, mut answered) = (0usize, 0usize);
    let mut report = ViewReport {
        quick: opts.quick,
        ..ViewReport::default()
    };
    for spec in &terrains {
        let terrain = spec.build(opts.seed, FAMILY_SIZE_M);
        for preset in &sensors {
            eprintln!("view: terrain {}, {} …", spec.name, preset.name);
            let case = run_case(&terrain, preset, opts)?;
            let (mut ev, mut wi) = (Area::default(), Area::default());
            for ray in &case.rays {
                let Some(truth) = ray.truth else { continue };
                if !ray.seen {
                    continue;
                }
                seen += 1;
                let Some((range, sd, source, provenance)) = ray.answer else {
                    continue;
                };
                answered += 1;
                let err = range - truth;
                *report
                    .provenance
                    .entry(format!("{provenance:?}").to_lowercase())
                    .or_default() += 1;
                if ray.evicted_area {
                    ev.push(err, sd);
                    evicted.push(err, sd);
                    *report
                        .evicted_sources
                        .entry(format!("{source:?}").to_lowercase())
                        .or_default() += 1;
                } else {
                    wi.push(err, sd);
                    window.push(err, sd);
                }
            }
            let answered_here = case.rays.iter().filter(|r| r.truth.is_some() && r.seen).count();
            let got = case
                .rays
                .iter()
                .filter(|r| r.truth.is_some() && r.seen && r.answer.is_some())
                .count();
            report.cases.push((
                spec.name.clone(),
                preset.name.to_owned(),
                [
                    ev.rmse(),
                    ev.cov95(),
                    wi.rmse(),
                    wi.cov95(),
                    got as f64 / answered_here.max(1) as f64,
                ],
            ));
        }
    }
    report.evicted_ray_rmse = evicted.rmse();
    report.evicted_ray_cov95 = evicted.cov95();
    report.window_ray_rmse = window.rmse();
    report.window_ray_cov95 = window.cov95();
    report.answered_fraction = answered as f64 / seen.max(1) as f64;
    report.rays = [evicted.n, window.n];
    report.failures = bars(&report);
    Ok(report)
}

/// The acceptance bars of issue 16 (the same in the quick form, which runs fewer scenes).
pub fn bars(r: &ViewReport) -> Vec<String> {
    let mut failures = Vec::new();
    if r.evicted_ray_rmse > 2.0 * r.window_ray_rmse {
        failures.push(format!(
            "evicted-area ray RMSE {:.4} m above 2 × the window's {:.4} m",
            r.evicted_ray_rmse, r.window_ray_rmse
        ));
    }
    if !(0.90..=0.98).contains(&r.evicted_ray_cov95) {
        failures.push(format!(
            "evicted-area ray cov95 {:.3} outside [0.90, 0.98]",
            r.evicted_ray_cov95
        ));
    }
    if r.answered_fraction < 0.9 {
        failures.push(format!(
            "answered fraction {:.3} below 0.9 over ground the drive saw",
            r.answered_fraction
        ));
    }
    failures
}

/// The CI guard of the quick form (docs/EVALUATION.md "Views"), so a regression fails the build.
/// The evicted-area cov95 bound lies between the quick run with the local leave-one-out σ (0.895)
/// and without it (0.870); the full run meets the bar (0.924). The other limits sit just
/// below what the quick run measured on 2026-11-24.
pub fn quick_regressions(r: &ViewReport) -> Vec<String> {
    let mut failures = Vec::new();
    let mut check = |ok: bool, what: String| {
        if !ok {
            failures.push(what);
        }
    };
    check(
        r.evicted_ray_rmse <= 2.0 * r.window_ray_rmse,
        format!(
            "evicted RMSE {:.4} > 2 × window {:.4}",
            r.evicted_ray_rmse, r.window_ray_rmse
        ),
    );
    check(
        r.evicted_ray_cov95 >= 0.88,
        format!("evicted cov95 {:.3} < 0.88", r.evicted_ray_cov95),
    );
    check(
        r.window_ray_cov95 >= 0.82,
        format!("window cov95 {:.3} < 0.82", r.window_ray_cov95),
    );
    check(
        r.answered_fraction >= 0.95,
        format!("answered {:.3} < 0.95", r.answered_fraction),
    );
    check(
        r.rays[0] >= 300 && r.rays[1] >= 300,
        format!("too few rays scored: {:?}", r.rays),
    );
    failures
}

/// One scored ray.
struct ScoredRay {
    /// Whether it was cast beside the early path (maps evicted from the window).
    evicted_area: bool,
    /// True range, if the ray meets the terrain.
    truth: Option<f64>,
    /// Whether a scan of the drive saw the true hit point.
    seen: bool,
    /// Range, σ, source and provenance of the answer.
    answer: Option<(f64, f64, Source, Provenance)>,
}

struct Case {
    rays: Vec<ScoredRay>,
}

fn run_case(terrain: &Heightmap, preset: &ScannerPreset, opts: &FamilyOptions) -> Result<Case> {
    let capacity = opts.config.window.capacity;
    let scans = capacity + if opts.quick { 12 } else { 24 };
    let seed = opts.seed;
    // No eviction from the aggregate here: the drive stays within the daemon's radius.
    let MappedDrive {
        path,
        poses,
        snapshot,
        ..
    } = map_drive(
        terrain,
        preset,
        &Drive {
            config: &opts.config,
            scans,
            step_m: 1.0,
            chassis_m: None,
            stop_scans: 0,
            path_seed: seed ^ 0x71e,
            scan_seed: &|i| seed ^ ((i as u64) << 24) ^ 0x71e,
            stamp_base: 2_000,
            evict: false,
            progress: false,
            keep_after: &[],
        },
    )?;
    let coverage = Coverage::of(preset);
    // Beside poses 2 … (evicted − 2) and beside the last few: never visited, 0.7 m aside.
    let evicted_until = scans - capacity;
    let probes: Vec<(bool, usize)> = (2..evicted_until.saturating_sub(2))
        .step_by(2)
        .map(|i| (true, i))
        .chain((scans - 6..scans - 1).map(|i| (false, i)))
        .collect();
    let mut rays = Vec::new();
    for (evicted_area, i) in probes {
        let pose = poses[i];
        let heading = path.waypoints[i][2];
        let side = if i % 4 < 2 { 0.7 } else { -0.7 };
        let origin = pose.translation.vector + side * Vector3::new(-heading.sin(), heading.cos(), 0.0);
        let yaw = UnitQuaternion::from_euler_angles(0.0, 0.0, heading);
        for elevation_deg in [-6.0f64, -10.0, -15.0, -22.0] {
            for azimuth_deg in (-5..=5).map(|k| 10.0 * f64::from(k)) {
                let (e, a) = (elevation_deg.to_radians(), azimuth_deg.to_radians());
                let dir = yaw * Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
                let max_range = 12.0f64.min(preset.max_range_m);
                let truth = terrain.cast(origin, dir, max_range);
                let seen = truth.is_some_and(|t| {
                    let p = origin + dir * t;
                    poses.iter().any(|q| coverage.sees(terrain, q, [p.x, p.y, p.z]))
                });
                let item = query::ray(
                    &snapshot,
                    &Ray {
                        origin_m: origin.into(),
                        direction: dir.into(),
                        max_range_m: max_range,
                    },
                );
                let answer = item
                    .range_m
                    .zip(item.range_var_m2)
                    .map(|(r, v)| (r, v.max(1e-18).sqrt(), item.source, item.provenance));
                rays.push(ScoredRay {
                    evicted_area,
                    truth,
                    seen,
                    answer,
                });
            }
        }
    }
    Ok(Case { rays })
}

/// Prints the report.
pub fn print_view(r: &ViewReport) {
    println!(
        "\nrangegp-eval view ({} form)",
        if r.quick { "quick" } else { "full" }
    );
    println!("  terrain            sensor    evicted RMSE  cov95   window RMSE  cov95   answered");
    for (t, s, v) in &r.cases {
        println!(
            "  {t:<18} {s:<8} {:>10.4} m {:>6.3} {:>10.4} m {:>6.3} {:>9.3}",
            v[0], v[1], v[2], v[3], v[4]
        );
    }
    println!(
        "  pooled                      {:>10.4} m {:>6.3} {:>10.4} m {:>6.3} {:>9.3}   (rays {} / {})",
        r.evicted_ray_rmse,
        r.evicted_ray_cov95,
        r.window_ray_rmse,
        r.window_ray_cov95,
        r.answered_fraction,
        r.rays[0],
        r.rays[1]
    );
    println!(
        "  evicted area answered by {:?}; provenance {:?}",
        r.evicted_sources, r.provenance
    );
}
