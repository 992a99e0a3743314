//! Online against batch hyperparameters on random seed-000 scans (seed 000 §IV protocol: 20 %
//! of each scan's returns train, optimiser started at σ² = 2.5, ℓ = 0.15).

use crate::eval::scores::MeanSd;
use crate::eval::split::{random_pose, split_scan};
use anyhow::Result;
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_service::config::Config;
use rangegp_service::gp::hyper::{fit_hyperparameters, HyperBounds};
use rangegp_service::gp::likelihood::TrainingSet;
use rangegp_service::gp::Kernel;
use rangegp_service::map::local::hyper_sample;
use rangegp_service::scan::ScanInput;
use rangegp_sim::{CraterParams, Heightmap, ScannerPreset};
use serde::Serialize;
use std::path::PathBuf;

/// Options of `rangegp-bench hyper`.
#[derive(Debug, Clone, clap::Args)]
pub struct HyperOptions {
    /// Random scans (seed 000 used 100).
    #[arg(long, default_value_t = 100)]
    pub scans: usize,
    /// World seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output folder for hyper.json.
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
}

/// The comparison `hyper.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct HyperReport {
    /// Scans used.
    pub scans: usize,
    /// Per-scan batch optima of σ².
    pub batch_variance: MeanSd,
    /// Per-scan batch optima of ℓ.
    pub batch_length_scale: MeanSd,
    /// Online estimate of σ² after all scans.
    pub online_variance: f64,
    /// Online estimate of ℓ after all scans.
    pub online_length_scale: f64,
    /// |online − batch mean| ≤ batch sd for both.
    pub online_within_one_sd: bool,
}

/// A seed-000 scan at a random pose with 20 % of its returns, noisy, kept for training.
fn training_scan(terrain: &Heightmap, rng: &mut Pcg64) -> ScanInput {
    let preset = ScannerPreset::seed000();
    let pose = random_pose(terrain, 12.0, preset.mount_height_m, rng);
    split_scan(terrain, pose, &preset, 0.2, 0, rng).train
}

/// Runs the comparison: every scan's own optimum (100 L-BFGS iterations from the paper's start)
/// against the daemon's online learner fed the same scans in order.
pub fn run_hyper(opts: &HyperOptions) -> Result<HyperReport> {
    // Both learners start where seed 000's optimiser started (σ² = 2.5, ℓ = 0.15): the
    // likelihood of these scans has a short- and a long-length-scale mode, and a comparison of
    // optimisers must not hand them different basins.
    let mut config = Config::default();
    config.gp.online.enabled = true;
    config.gp.kernel_variance = 2.5;
    config.gp.length_scale = 0.15;
    let params = config.map_params();
    let terrain = Heightmap::cratered(opts.seed, &CraterParams::default());
    let mut rng = Pcg64::seed_from_u64(opts.seed ^ 0x4e11);
    let start = Kernel::matern32(2.5, 0.15);
    let mut online = config.online_hyperparameters();
    let (mut vars, mut ells) = (Vec::new(), Vec::new());
    for i in 0..opts.scans {
        let mut scan = training_scan(&terrain, &mut rng);
        scan.sequence = i as u64;
        let sample = hyper_sample(&scan, &params, usize::MAX);
        let set = TrainingSet {
            inputs: &sample.inputs,
            targets: &sample.targets,
            noise_var: &sample.noise_var,
        };
        let bounds = HyperBounds {
            variance: (1e-6, 1e1),
            length_scale: (0.05, 50.0),
        };
        let fit = fit_hyperparameters(&start, set, bounds, 100)?;
        vars.push(fit.variance);
        ells.push(fit.length_scale);
        online.update(hyper_sample(&scan, &params, config.gp.online.subset_rays).as_training_set())?;
        if (i + 1) % 10 == 0 {
            eprintln!("      {}/{} scans", i + 1, opts.scans);
        }
    }
    let (bv, bl) = (MeanSd::of(&vars), MeanSd::of(&ells));
    let k = online.kernel();
    let report = HyperReport {
        scans: opts.scans,
        batch_variance: bv,
        batch_length_scale: bl,
        online_variance: k.variance,
        online_length_scale: k.length_scale,
        online_within_one_sd: (k.variance - bv.mean).abs() <= bv.sd
            && (k.length_scale - bl.mean).abs() <= bl.sd,
    };
    std::fs::create_dir_all(&opts.out)?;
    std::fs::write(
        opts.out.join("hyper.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    Ok(report)
}

/// Prints the comparison.
pub fn print_hyper(r: &HyperReport) {
    println!(
        "\nhyperparameters over {} seed-000 scans (20 % of returns each)",
        r.scans
    );
    println!("                     σ² (amplitude-scaled)   ℓ (m of footprint)");
    println!(
        "  batch (per scan)   {:.2e} ± {:.2e}     {:.3} ± {:.3}",
        r.batch_variance.mean, r.batch_variance.sd, r.batch_length_scale.mean, r.batch_length_scale.sd
    );
    println!(
        "  batch median       {:.2e}                {:.3}",
        r.batch_variance.median, r.batch_length_scale.median
    );
    println!(
        "  batch geom. mean   {:.2e}                {:.3}",
        r.batch_variance.geometric_mean, r.batch_length_scale.geometric_mean
    );
    println!(
        "  online (final)     {:.2e}                {:.3}",
        r.online_variance, r.online_length_scale
    );
    println!("  seed 000 Table I   2.302 ± 0.980 (σ², range sphere)   1.206 ± 0.608 (m of chord)");
    println!("  online within one sd of batch: {}", r.online_within_one_sd);
}
