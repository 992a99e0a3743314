//! The seed-000 evaluation (`rangegp-eval`): Table I, the aggregate experiment and the overhang
//! scene, scored with [`scores`] and printed beside the paper's numbers.

pub mod local;
pub mod progress;
pub mod scores;
pub mod split;

use anyhow::Result;
use local::{print_local, run_local, LocalOptions, LocalReport};
use rangegp_sim::{CraterParams, Heightmap};
use serde::Serialize;
use std::path::PathBuf;

/// Which experiments to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Experiment {
    /// Table I: one scan at a time.
    Local,
    /// Five A* trajectories folded into the aggregates.
    Aggregate,
    /// The tunnel scene with the constant-range prior.
    Overhang,
    /// All three.
    All,
}

/// Command line of `rangegp-eval`.
#[derive(Debug, Clone, clap::Parser)]
#[command(version, about = "Reproduce seed 000 (Table I, the aggregate, overhangs) and score rangegp's maps")]
pub struct EvalOptions {
    /// Experiment to run.
    #[arg(value_enum)]
    pub experiment: Experiment,
    /// Reduced sizes for CI (a few minutes); the bars checked are the quick ones.
    #[arg(long)]
    pub quick: bool,
    /// World seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output folder for summary.json and the pictures.
    #[arg(long, default_value = "eval-out")]
    pub out: PathBuf,
}

/// What `summary.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// Quick (CI) or full sizes.
    pub quick: bool,
    /// World seed.
    pub seed: u64,
    /// Table I.
    pub local: Option<LocalSummary>,
    /// Bars missed, one line each (empty: all met).
    pub failures: Vec<String>,
}

/// The local experiment's headline numbers and its full report.
#[derive(Debug, Clone, Serialize)]
pub struct LocalSummary {
    /// Range GP mean per-scan RMSE in z, metres.
    pub range_rmse_z: f64,
    /// Elevation GP mean per-scan RMSE in z, metres.
    pub elev_rmse_z: f64,
    /// Range GP 95 % coverage of z.
    pub coverage95: f64,
    /// Range GP NLPD of z.
    pub nlpd: f64,
    /// Range GP AUSE of z, metres.
    pub ause: f64,
    /// Everything measured.
    pub report: LocalReport,
}

/// Runs the selected experiments, prints their tables, writes summary.json.
pub fn run(opts: &EvalOptions) -> Result<Summary> {
    let want = |e: Experiment| opts.experiment == e || opts.experiment == Experiment::All;
    eprintln!("terrain: 100 m × 100 m at 5 cm, seed {} …", opts.seed);
    let terrain = Heightmap::cratered(opts.seed, &CraterParams::default());
    let mut summary = Summary {
        quick: opts.quick,
        seed: opts.seed,
        local: None,
        failures: Vec::new(),
    };
    if want(Experiment::Local) {
        let n = if opts.quick { 20 } else { 100 };
        let report = run_local(
            &terrain,
            &LocalOptions {
                tune_scans: n,
                test_scans: n,
                seed: opts.seed,
            },
        )?;
        print_local(&report);
        summary.local = Some(LocalSummary {
            range_rmse_z: report.range.rmse_z_per_scan.mean,
            elev_rmse_z: report.elevation.rmse_z_per_scan.mean,
            coverage95: report.range.z.coverage95,
            nlpd: report.range.z.nlpd,
            ause: report.range.z.ause,
            report,
        });
    }
    std::fs::create_dir_all(&opts.out)?;
    std::fs::write(opts.out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    Ok(summary)
}
