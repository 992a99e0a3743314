//! Overhangs (seed 000 §V-C): a VLP-16 inside a tunnel (walls and a roof over the floor) with
//! the constant-range prior. The range GP answers held-out rays, once modelling range (seed 000)
//! and once inverse range (the project's choice for such scenes: every plane is linear in 1/r);
//! the elevation GP, one height per (x, y), cannot hold a roof over a floor, and its error on the
//! same rays shows it.

use super::local::{self, NUGGET_M2};
use super::progress;
use super::scores::{Sample, Scores};
use super::split::{split_scan, SplitScan};
use crate::plot::{Heatmap, Limits, Raster};
use anyhow::{Context, Result};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_service::config::Config;
use rangegp_service::gp::hyper::{fit_hyperparameters, HyperBounds};
use rangegp_service::gp::{JitterPolicy, Kernel};
use rangegp_service::map::elevation_gp::ElevationGp;
use rangegp_service::map::local::{hyper_sample, LocalRangeMap, MapParams, PriorKind, RangeTarget};
use rangegp_service::map::root;
use rangegp_sim::{ScannerPreset, Surface, Tunnel};
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;

/// Size of the overhang experiment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OverhangOptions {
    /// Scans the hyperparameters are tuned on (seed 000: 50).
    pub tune_scans: usize,
    /// Scans scored.
    pub test_scans: usize,
    /// Seed.
    pub seed: u64,
}

/// The range GP under one target: its tuned kernel and its scores.
#[derive(Debug, Clone, Serialize)]
pub struct RangeGpRow {
    /// What the GP modelled.
    pub target: RangeTarget,
    /// Hyperparameters used (σ², ℓ): geometric mean of the per-scan optima.
    pub kernel: [f64; 2],
    /// Range along the held-out rays, metres.
    pub ray: Scores,
}

/// The overhang experiment's report.
#[derive(Debug, Clone, Serialize)]
pub struct OverhangReport {
    /// Held-out rays scored per model.
    pub test_rays: usize,
    /// Range GP modelling range (seed 000's form).
    pub range: RangeGpRow,
    /// Range GP modelling inverse range (the project's form for overhang scenes).
    pub inverse_range: RangeGpRow,
    /// Elevation GP: range along every fifth held-out ray, cast against its surface (a ray that
    /// never meets it counts as reaching the max range).
    pub elevation_gp_ray: Scores,
    /// Elevation GP: z at those rays' true (x, y).
    pub elevation_gp_z: Scores,
}

/// Range of the scanner and of the constant-range prior, metres (seed 000 §V-C: R = 10).
const RANGE_M: f64 = 10.0;
/// Training points the elevation-GP baseline is fitted to at most (an even stride).
const ELEVATION_POINTS: usize = 2000;
/// Rays in each hyperparameter-learning patch.
const HYPER_RAYS: usize = 400;

/// The scanner of seed 000 §V-C: a VLP-16, its returns kept to 10 m.
pub fn overhang_scanner() -> ScannerPreset {
    ScannerPreset {
        max_range_m: RANGE_M,
        ..ScannerPreset::vlp16()
    }
}

fn scan_at(tunnel: &Tunnel, seed: u64, stream: u64, i: usize) -> SplitScan {
    let mut rng = Pcg64::seed_from_u64(seed ^ 0x7e77 ^ (stream << 40) ^ (i as u64).wrapping_mul(0x9E37_79B9));
    let pose = Isometry3::from_parts(
        Translation3::new(
            rng.random_range(-8.0..8.0),
            rng.random_range(-1.2..1.2),
            rng.random_range(0.6..1.4),
        ),
        UnitQuaternion::from_euler_angles(
            0.0,
            0.0,
            rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
        ),
    );
    split_scan(tunnel, pose, &overhang_scanner(), 0.2, i as u64, &mut rng)
}

fn params(kernel: Kernel, target: RangeTarget) -> MapParams {
    MapParams {
        kernel,
        prior: PriorKind::ConstantRange { range_m: RANGE_M },
        sphere_radius_m: Some(RANGE_M),
        nugget_m2: NUGGET_M2,
        target,
        ..Config::default().map_params()
    }
}

/// Range where the ray first meets the elevation GP's surface (sampled every 0.1 m, refined by
/// the maps' root finder), or `max_range` when it never does. The ray may start above or below
/// the surface (under a roof the baseline's surface lies between floor and roof).
fn cast_on_heights(gp: &ElevationGp, origin: Vector3<f64>, dir: Vector3<f64>, max_range: f64) -> f64 {
    let side = |t: f64| {
        let p = origin + dir * t;
        p.z - gp.height(p.x, p.y)
    };
    let start = side(0.0).signum();
    let samples = (max_range / 0.1).ceil() as usize;
    root::first_crossing(|t| Some(-start * side(t)), 0.0, max_range, samples).map_or(max_range, |r| r.t)
}

/// Per-scan optimum (σ², ℓ) of the range GP under `target` on a compact patch of rays.
fn tune(scan: &SplitScan, target: RangeTarget) -> Result<(f64, f64)> {
    let start = local::start_kernel();
    let sample = hyper_sample(&scan.train, &params(start, target), HYPER_RAYS);
    let bounds = HyperBounds {
        variance: (1e-6, 1e3),
        length_scale: (1e-2, 50.0),
    };
    let f = fit_hyperparameters(&start, sample.as_training_set(), bounds, 100)?;
    Ok((f.variance, f.length_scale))
}

/// Held-out range samples of the range GP fitted to `scan`.
fn score_range(scan: &SplitScan, kernel: Kernel, target: RangeTarget) -> Result<Vec<Sample>> {
    let map = LocalRangeMap::fit(&scan.train, &params(kernel, target))?;
    let angles: Vec<(f64, f64)> = scan.test.iter().map(|t| (t.inclination, t.azimuth)).collect();
    Ok(map
        .predict_ranges(&angles)
        .into_iter()
        .zip(&scan.test)
        .map(|((r, v), t)| Sample {
            mean: r,
            sd: v.sqrt().max(1e-12),
            truth: t.range,
        })
        .collect())
}

/// The elevation GP's samples on every fifth held-out ray: (range along the ray, z at its hit).
fn score_elevation(scan: &SplitScan) -> Result<(Vec<Sample>, Vec<Sample>)> {
    let tr = &scan.train;
    let s = tr.pose.translation.vector;
    let (all_points, all_noise) = local::world_points(scan);
    let every = |n: usize| all_points.len().div_ceil(n).max(1);
    let stride = every(ELEVATION_POINTS);
    let points: Vec<[f64; 3]> = all_points.iter().step_by(stride).copied().collect();
    let noise: Vec<f64> = all_noise.iter().step_by(stride).copied().collect();
    // The baseline gets its own per-scan optimum (the most favourable setting for it), learnt on
    // an even stride of the scan's points.
    let hyper = every(HYPER_RAYS);
    let hyper_points: Vec<[f64; 3]> = all_points.iter().step_by(hyper).copied().collect();
    let hyper_noise: Vec<f64> = all_noise.iter().step_by(hyper).copied().collect();
    let ek = local::elevation_optimum(&hyper_points, &hyper_noise, 50)?;
    let egp = ElevationGp::fit(
        &points,
        &noise,
        Kernel::matern32(ek.variance, ek.length_scale),
        JitterPolicy::default(),
    )?;
    let some: Vec<_> = scan.test.iter().step_by(5).collect();
    let ray = some
        .iter()
        .map(|t| Sample {
            mean: cast_on_heights(&egp, s, Vector3::from(t.dir), tr.max_range_m),
            sd: 1.0,
            truth: t.range,
        })
        .collect();
    let z = some
        .iter()
        .map(|t| {
            let (z, v) = egp.predict(t.point[0], t.point[1]);
            Sample {
                mean: z,
                sd: v.sqrt().max(1e-12),
                truth: t.point[2],
            }
        })
        .collect();
    Ok((ray, z))
}

/// The samples of one test scan.
struct Scored {
    range: Vec<Sample>,
    inverse: Vec<Sample>,
    elev_ray: Vec<Sample>,
    elev_z: Vec<Sample>,
}

/// Runs the experiment; panoramas of the first test scan go to `out`.
pub fn run_overhang(opts: &OverhangOptions, out: &Path) -> Result<OverhangReport> {
    let tunnel = Tunnel::default();
    let bar = progress::bar(opts.tune_scans as u64, "overhang: tuning");
    let fits: Vec<[(f64, f64); 2]> = (0..opts.tune_scans)
        .into_par_iter()
        .map(|i| {
            let scan = scan_at(&tunnel, opts.seed, 0, i);
            let r = Ok([
                tune(&scan, RangeTarget::Range)?,
                tune(&scan, RangeTarget::InverseRange)?,
            ]);
            bar.inc(1);
            r
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let range_kernel = local::geometric_kernel(fits.iter().map(|f| f[0]));
    let inverse_kernel = local::geometric_kernel(fits.iter().map(|f| f[1]));
    let bar = progress::bar(opts.test_scans as u64, "overhang: scoring");
    let scored: Vec<Scored> = (0..opts.test_scans)
        .into_par_iter()
        .map(|i| {
            let scan = scan_at(&tunnel, opts.seed, 1, i);
            let (elev_ray, elev_z) = score_elevation(&scan)?;
            let r = Ok(Scored {
                range: score_range(&scan, range_kernel, RangeTarget::Range)?,
                inverse: score_range(&scan, inverse_kernel, RangeTarget::InverseRange)?,
                elev_ray,
                elev_z,
            });
            bar.inc(1);
            r
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    draw(&scan_at(&tunnel, opts.seed, 1, 0), inverse_kernel, out)?;
    let pool = |f: fn(&Scored) -> &Vec<Sample>| {
        let all: Vec<Sample> = scored.iter().flat_map(|s| f(s).iter().copied()).collect();
        Scores::of(&all).context("no held-out rays")
    };
    let row = |target, kernel: Kernel, ray| RangeGpRow {
        target,
        kernel: [kernel.variance, kernel.length_scale],
        ray,
    };
    Ok(OverhangReport {
        test_rays: scored.iter().map(|s| s.range.len()).sum(),
        range: row(RangeTarget::Range, range_kernel, pool(|s| &s.range)?),
        inverse_range: row(RangeTarget::InverseRange, inverse_kernel, pool(|s| &s.inverse)?),
        elevation_gp_ray: pool(|s| &s.elev_ray)?,
        elevation_gp_z: pool(|s| &s.elev_z)?,
    })
}

/// Panoramas (azimuth across, elevation up, 0.5° pixels) of the true range, the fitted
/// inverse-range GP and its absolute error, for one scan inside the tunnel.
fn draw(scan: &SplitScan, kernel: Kernel, out: &Path) -> Result<()> {
    let map = LocalRangeMap::fit(&scan.train, &params(kernel, RangeTarget::InverseRange))?;
    let tunnel = Tunnel::default();
    let pose = scan.train.pose;
    let truth = |az: f64, el: f64| {
        let inc = (90.0 - el).to_radians();
        let dir = pose.rotation * rangegp_sim::sensor::direction(inc, az.to_radians());
        tunnel.cast(pose.translation.vector, dir, RANGE_M)
    };
    let fitted = |az: f64, el: f64| Some(map.predict_range((90.0 - el).to_radians(), az.to_radians()).0);
    let (lo, hi) = ((-180.0, -15.0), (180.0, 15.0));
    let t = Raster::from_fn(lo, hi, 0.5, truth);
    let f = Raster::from_fn(lo, hi, 0.5, |a, e| truth(a, e).and(fitted(a, e)));
    let e = Raster::from_fn(lo, hi, 0.5, |a, e| Some((fitted(a, e)? - truth(a, e)?).abs()));
    let range = Limits::Fixed(0.0, RANGE_M);
    let pictures = [
        (
            "overhang_true_range.png",
            "True range",
            "range (m)",
            &t,
            range,
            colorous::VIRIDIS,
        ),
        (
            "overhang_fitted_range.png",
            "Fitted range",
            "range (m)",
            &f,
            range,
            colorous::VIRIDIS,
        ),
        (
            "overhang_abs_error.png",
            "Absolute range error",
            "|error| (m)",
            &e,
            Limits::Fixed(0.0, 0.05),
            colorous::INFERNO,
        ),
    ];
    for (name, title, unit, raster, limits, gradient) in pictures {
        Heatmap::new(title, unit)
            .axes("azimuth (°)", "elevation (°)")
            .limits(limits)
            .gradient(gradient)
            .save(&out.join(name), raster)?;
    }
    Ok(())
}

/// Prints the table.
pub fn print_overhang(r: &OverhangReport) {
    println!(
        "\nOverhangs (seed 000 §V-C): VLP-16 inside a tunnel, constant-range prior (R = {RANGE_M} m), {} held-out rays",
        r.test_rays
    );
    println!("                                  RMSE     median |err|      L∞     cov95   kernel σ², ℓ");
    let row = |name: &str, s: &Scores, cov: bool, kernel: Option<[f64; 2]>| {
        let c = if cov {
            format!("{:.3}", s.coverage95)
        } else {
            "  —  ".into()
        };
        let k = kernel.map_or(String::new(), |k| format!("{:.3e}, {:.3}", k[0], k[1]));
        println!(
            "  {name:<30} {:>8.4}   {:>10.4}   {:>8.4}   {c}   {k}",
            s.rmse, s.median_abs, s.max_abs
        );
    };
    row("range GP (range), ray", &r.range.ray, true, Some(r.range.kernel));
    row(
        "range GP (1/range), ray",
        &r.inverse_range.ray,
        true,
        Some(r.inverse_range.kernel),
    );
    row("elevation GP, ray", &r.elevation_gp_ray, false, None);
    row("elevation GP, z at hit", &r.elevation_gp_z, true, None);
    println!("  paper (real VLP-16 data, no score given): σ = 5.16, κ = 0.177; bar: ray RMSE ≤ 0.02 m");
}
