//! `rangegp-bench`: performance measurements of rangegp on this machine.

use anyhow::Result;
use clap::{Parser, Subcommand};
use rangegp_service::bench::gp::{print_gp, run_gp, GpBenchOptions};
use rangegp_service::bench::hyper::{print_hyper, run_hyper, HyperOptions};

#[derive(Parser)]
#[command(
    version,
    about = "Benchmarks of rangegp (medians; peers measured in the same run)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// GP engine: Cholesky GFLOP/s, full-scan fits, prediction, numpy / scikit-learn peers.
    Gp(GpBenchOptions),
    /// Online against batch (per-scan) hyperparameters on random seed-000 scans.
    Hyper(HyperOptions),
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Gp(opts) => {
            let report = run_gp(&opts)?;
            print_gp(&report);
            println!("  written: {}", opts.out.join("gp.json").display());
        }
        Command::Hyper(opts) => {
            let report = run_hyper(&opts)?;
            print_hyper(&report);
            println!("  written: {}", opts.out.join("hyper.json").display());
        }
    }
    Ok(())
}
