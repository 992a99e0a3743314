//! The local mapping experiment of seed 000 (Table I): hyperparameters optimised on random
//! tuning scans and averaged, then the range GP and the elevation-GP baseline scored on other
//! random scans over their held-out rays.

use super::progress;
use super::scores::{MeanSd, Sample, Scores};
use super::split::{random_pose, split_scan, SplitScan};
use anyhow::{Context, Result};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_service::gp::hyper::{fit_hyperparameters, HyperBounds, HyperFit};
use rangegp_service::gp::likelihood::TrainingSet;
use rangegp_service::gp::{JitterPolicy, Kernel};
use rangegp_service::map::elevation_gp::ElevationGp;
use rangegp_service::map::local::{hyper_sample, LocalRangeMap, MapParams, PriorKind, RangeTarget};
use rangegp_service::map::tiles::Tiling;
use rangegp_sim::{Heightmap, ScannerPreset};
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// Size of the local experiment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalOptions {
    /// Scans whose per-scan optima are averaged into the hyperparameters (seed 000: 100).
    pub tune_scans: usize,
    /// Scans scored with them (seed 000: 100).
    pub test_scans: usize,
    /// World seed.
    pub seed: u64,
}

/// Where every optimiser starts (seed 000: σ = 2.5, κ = 0.15).
pub fn start_kernel() -> Kernel {
    Kernel::matern32(2.5, 0.15)
}
/// Known noise on top of the sensor model for both models, m² (see docs/EVALUATION.md).
pub const NUGGET_M2: f64 = 1e-6;

/// One model's row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct ModelRow {
    /// Per-tuning-scan optimal σ².
    pub variance: MeanSd,
    /// Per-tuning-scan optimal ℓ (range GP: metres of chord on the range sphere; elevation GP:
    /// metres on the ground).
    pub length_scale: MeanSd,
    /// Coefficient of variation of ℓ over the tuning scans.
    pub length_scale_cv: f64,
    /// Per-test-scan RMSE in z (the paper's "Local RMSE" with its standard deviation).
    pub rmse_z_per_scan: MeanSd,
    /// Pooled scores of z over every held-out ray of every test scan.
    pub z: Scores,
    /// Mean predicted standard deviation in x, y, z (Table I "Local GP uncertainty").
    pub mean_sigma_xyz: [f64; 3],
    /// Median fit time per scan, ms.
    pub fit_ms: f64,
}

/// The Table I reproduction.
#[derive(Debug, Clone, Serialize)]
pub struct LocalReport {
    /// Tuning scans.
    pub tune_scans: usize,
    /// Test scans.
    pub test_scans: usize,
    /// Range-based GP (exact, flat-ground prior, Matérn-3/2 on the range sphere).
    pub range: ModelRow,
    /// Elevation-based GP (Matérn-3/2 on (x, y)).
    pub elevation: ModelRow,
}

fn sphere_params(kernel: Kernel) -> MapParams {
    MapParams {
        kernel,
        sphere_radius_m: Some(10.0),
        nugget_m2: NUGGET_M2,
        max_training_rays: usize::MAX,
        // One exact GP per scan: the paper's model (a scan keeps ~200 training rays).
        tiling: Tiling {
            max_rays_per_tile: 1 << 20,
            overlap: 0.0,
        },
        prior: PriorKind::FlatGround {
            sensor_height_m: ScannerPreset::seed000().mount_height_m,
        },
        target: RangeTarget::Range,
        jitter: JitterPolicy::default(),
        variance_calibration: rangegp_service::map::tiles::VarianceCalibration::None,
        index_data: false,
        view_ceiling: false,
    }
}

/// Training points of a scan in the map frame with their noise variances (isotropic: the range
/// noise of the ray), for the elevation GP.
pub fn world_points(scan: &SplitScan) -> (Vec<[f64; 3]>, Vec<f64>) {
    let t = &scan.train;
    let s = t.pose.translation.vector;
    t.rays
        .iter()
        .map(|r| {
            let w = t.pose.rotation * rangegp_sim::sensor::direction(r.inclination, r.azimuth);
            let p = s + w * r.range;
            (
                [p.x, p.y, p.z],
                (t.range_noise_per_m * r.range).powi(2) + NUGGET_M2,
            )
        })
        .unzip()
}

/// The hyperparameter box every seed-000 optimiser searches.
pub fn bounds() -> HyperBounds {
    HyperBounds {
        variance: (1e-4, 1e2),
        length_scale: (1e-2, 50.0),
    }
}

/// The elevation GP's optimum on map-frame `points` (z about its mean over (x, y)) with their
/// noise variances, from seed 000's start, at most `iterations` L-BFGS steps.
pub fn elevation_optimum(points: &[[f64; 3]], noise: &[f64], iterations: u64) -> Result<HyperFit> {
    let mean_z = points.iter().map(|p| p[2]).sum::<f64>() / points.len().max(1) as f64;
    let inputs: Vec<[f64; 3]> = points.iter().map(|p| [p[0], p[1], 0.0]).collect();
    let targets: Vec<f64> = points.iter().map(|p| p[2] - mean_z).collect();
    let set = TrainingSet {
        inputs: &inputs,
        targets: &targets,
        noise_var: noise,
    };
    Ok(fit_hyperparameters(&start_kernel(), set, bounds(), iterations)?)
}

/// Matérn-3/2 with the geometric means of per-scan optima (σ², ℓ): seed 000 averaged its
/// optima; a few scans run to a bound, so the average is taken in log space.
pub fn geometric_kernel(fits: impl Iterator<Item = (f64, f64)>) -> Kernel {
    let (v, l): (Vec<f64>, Vec<f64>) = fits.unzip();
    Kernel::matern32(MeanSd::of(&v).geometric_mean, MeanSd::of(&l).geometric_mean)
}

/// Per-scan optima of both models (range GP, elevation GP) on one tuning scan.
pub fn tune(scan: &SplitScan) -> Result<(HyperFit, HyperFit)> {
    let start = start_kernel();
    let sample = hyper_sample(&scan.train, &sphere_params(start), usize::MAX);
    let range = fit_hyperparameters(&start, sample.as_training_set(), bounds(), 100)?;
    let (points, noise) = world_points(scan);
    Ok((range, elevation_optimum(&points, &noise, 100)?))
}

/// Samples and timing of one test scan: (range z samples, range σxyz, elevation samples, fit ms ×2).
struct Scored {
    range: Vec<Sample>,
    range_sigma: Vec<[f64; 3]>,
    elevation: Vec<Sample>,
    fit_ms: [f64; 2],
}

fn score(scan: &SplitScan, range_kernel: Kernel, elev_kernel: Kernel) -> Result<Scored> {
    let t0 = Instant::now();
    let map = LocalRangeMap::fit(&scan.train, &sphere_params(range_kernel))?;
    let range_ms = t0.elapsed().as_secs_f64() * 1e3;
    let s = scan.train.pose.translation.vector;
    let mut range = Vec::with_capacity(scan.test.len());
    let mut range_sigma = Vec::with_capacity(scan.test.len());
    for t in &scan.test {
        let (r, var) = map.predict_range(t.inclination, t.azimuth);
        let sd = var.sqrt();
        range.push(Sample {
            mean: s.z + r * t.dir[2],
            sd: (sd * t.dir[2].abs()).max(1e-12),
            truth: t.point[2],
        });
        range_sigma.push([sd * t.dir[0].abs(), sd * t.dir[1].abs(), sd * t.dir[2].abs()]);
    }
    let (points, noise) = world_points(scan);
    let t0 = Instant::now();
    let egp = ElevationGp::fit(&points, &noise, elev_kernel, JitterPolicy::default())?;
    let elev_ms = t0.elapsed().as_secs_f64() * 1e3;
    let elevation = scan
        .test
        .iter()
        .map(|t| {
            let (z, var) = egp.predict(t.point[0], t.point[1]);
            Sample {
                mean: z,
                sd: var.sqrt().max(1e-12),
                truth: t.point[2],
            }
        })
        .collect();
    Ok(Scored {
        range,
        range_sigma,
        elevation,
        fit_ms: [range_ms, elev_ms],
    })
}

/// The `i`-th random scan of stream `stream` (tuning 0, test 1): reproducible and independent of
/// the order scans are processed in.
pub fn scan_at(terrain: &Heightmap, seed: u64, stream: u64, i: usize) -> SplitScan {
    let preset = ScannerPreset::seed000();
    let mut rng = Pcg64::seed_from_u64(seed ^ (stream << 40) ^ (i as u64).wrapping_mul(0x9E37_79B9));
    let pose = random_pose(terrain, 12.0, preset.mount_height_m, &mut rng);
    split_scan(terrain, pose, &preset, 0.2, i as u64, &mut rng)
}

/// Runs the experiment on `terrain`.
pub fn run_local(terrain: &Heightmap, opts: &LocalOptions) -> Result<LocalReport> {
    let bar = progress::bar(opts.tune_scans as u64, "local: tuning");
    let fits: Vec<(HyperFit, HyperFit)> = (0..opts.tune_scans)
        .into_par_iter()
        .map(|i| {
            let r = tune(&scan_at(terrain, opts.seed, 0, i));
            bar.inc(1);
            r
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let summarise = |pick: fn(&(HyperFit, HyperFit)) -> &HyperFit| {
        let v: Vec<f64> = fits.iter().map(|f| pick(f).variance).collect();
        let l: Vec<f64> = fits.iter().map(|f| pick(f).length_scale).collect();
        (MeanSd::of(&v), MeanSd::of(&l))
    };
    let (rv, rl) = summarise(|f| &f.0);
    let (ev, el) = summarise(|f| &f.1);
    // Seed 000 averaged the per-scan optima; a few scans run to a bound, so the average here is
    // taken in log space (the geometric mean), as the online learner smooths.
    let range_kernel = Kernel::matern32(rv.geometric_mean, rl.geometric_mean);
    let elev_kernel = Kernel::matern32(ev.geometric_mean, el.geometric_mean);
    let bar = progress::bar(opts.test_scans as u64, "local: scoring");
    let scored: Vec<Scored> = (0..opts.test_scans)
        .into_par_iter()
        .map(|i| {
            let r = score(&scan_at(terrain, opts.seed, 1, i), range_kernel, elev_kernel);
            bar.inc(1);
            r
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let row = |variance: MeanSd,
               length_scale: MeanSd,
               pick: fn(&Scored) -> &[Sample],
               k: usize|
     -> Result<ModelRow> {
        let per_scan: Vec<f64> = scored
            .iter()
            .filter_map(|s| Scores::of(pick(s)).map(|sc| sc.rmse))
            .collect();
        let all: Vec<Sample> = scored.iter().flat_map(|s| pick(s).iter().copied()).collect();
        let sigmas: Vec<[f64; 3]> = scored
            .iter()
            .flat_map(|s| s.range_sigma.iter().copied())
            .collect();
        let mean_axis = |a: usize| sigmas.iter().map(|s| s[a]).sum::<f64>() / sigmas.len().max(1) as f64;
        let z = Scores::of(&all).context("no held-out rays")?;
        let fit_ms: Vec<f64> = scored.iter().map(|s| s.fit_ms[k]).collect();
        Ok(ModelRow {
            length_scale_cv: length_scale.cv(),
            variance,
            length_scale,
            rmse_z_per_scan: MeanSd::of(&per_scan),
            mean_sigma_xyz: if k == 0 {
                [mean_axis(0), mean_axis(1), z.mean_sd]
            } else {
                [f64::NAN, f64::NAN, z.mean_sd]
            },
            z,
            fit_ms: MeanSd::of(&fit_ms).median,
        })
    };
    Ok(LocalReport {
        tune_scans: opts.tune_scans,
        test_scans: opts.test_scans,
        range: row(rv, rl, |s| &s.range, 0)?,
        elevation: row(ev, el, |s| &s.elevation, 1)?,
    })
}

/// Prints the table beside seed 000's Table I.
pub fn print_local(r: &LocalReport) {
    println!(
        "\nLocal mapping (seed 000 Table I): {} tuning scans, {} test scans, 20 % of returns train",
        r.tune_scans, r.test_scans
    );
    println!("                            range GP              elevation GP          | paper: range GP    elevation GP");
    let pair = |m: &MeanSd| format!("{:.4} ({:.4})", m.mean, m.sd);
    let line = |name: &str, a: String, b: String, pa: &str, pb: &str| {
        println!("  {name:<24}  {a:<20}  {b:<20}  | {pa:<17}  {pb}");
    };
    line(
        "kernel scalar σ²",
        pair(&r.range.variance),
        pair(&r.elevation.variance),
        "2.302 (0.980)",
        "0.0842 (0.0497)",
    );
    line(
        "length scale ℓ",
        pair(&r.range.length_scale),
        pair(&r.elevation.length_scale),
        "1.206 (0.608)",
        "18.102 (12.682)",
    );
    let geo = |m: &MeanSd| format!("{:.4}", m.geometric_mean);
    line(
        "σ² used (geom. mean)",
        geo(&r.range.variance),
        geo(&r.elevation.variance),
        "",
        "",
    );
    line(
        "ℓ used (geom. mean)",
        geo(&r.range.length_scale),
        geo(&r.elevation.length_scale),
        "",
        "",
    );
    line(
        "ℓ coeff. of variation",
        format!("{:.3}", r.range.length_scale_cv),
        format!("{:.3}", r.elevation.length_scale_cv),
        "0.504",
        "0.701",
    );
    line(
        "RMSE z per scan",
        pair(&r.range.rmse_z_per_scan),
        pair(&r.elevation.rmse_z_per_scan),
        "0.0121 (0.0048)",
        "0.0085 (0.0021)",
    );
    line(
        "mean σx",
        format!("{:.4}", r.range.mean_sigma_xyz[0]),
        "—".into(),
        "0.0603",
        "—",
    );
    line(
        "mean σy",
        format!("{:.4}", r.range.mean_sigma_xyz[1]),
        "—".into(),
        "0.0620",
        "—",
    );
    line(
        "mean σz",
        format!("{:.4}", r.range.mean_sigma_xyz[2]),
        format!("{:.4}", r.elevation.mean_sigma_xyz[2]),
        "0.0169",
        "0.0890",
    );
    let s = |name: &str, f: fn(&Scores) -> f64| {
        line(
            name,
            format!("{:.4}", f(&r.range.z)),
            format!("{:.4}", f(&r.elevation.z)),
            "",
            "",
        )
    };
    s("pooled RMSE z", |z| z.rmse);
    s("median |err| z", |z| z.median_abs);
    s("L∞ z", |z| z.max_abs);
    s("NLPD", |z| z.nlpd);
    s("coverage 68 %", |z| z.coverage68);
    s("coverage 95 %", |z| z.coverage95);
    s("AUSE (MAE, m)", |z| z.ause);
    line(
        "fit per scan, ms",
        format!("{:.2}", r.range.fit_ms),
        format!("{:.2}", r.elevation.fit_ms),
        "",
        "",
    );
}
