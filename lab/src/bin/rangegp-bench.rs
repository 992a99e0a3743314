//! `rangegp-bench`: performance measurements of rangegp on this machine.

use anyhow::Result;
use clap::{Parser, Subcommand};
use rangegp_lab::bench::fleet::{print_fleet, run_fleet, FleetBenchOptions};
use rangegp_lab::bench::gp::{print_gp, run_gp, GpBenchOptions};
use rangegp_lab::bench::hyper::{print_hyper, run_hyper, HyperOptions};
use rangegp_lab::bench::query::{print_query, run_query, QueryBenchOptions};

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
    /// CPU time per answered item of each query kind against a full window.
    Query(QueryBenchOptions),
    /// A site daemon's single-point latency against a robot's, behind one router with storage.
    Fleet(FleetBenchOptions),
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Gp(opts) => {
            let report = run_gp(&opts)?;
            print_gp(&report);
            println!("  written: {}", opts.out.join("gp.json").display());
        }
        Command::Query(opts) => {
            let report = run_query(&opts)?;
            print_query(&report);
            println!("  written: {}", opts.out.join("query.json").display());
        }
        Command::Fleet(opts) => {
            let report = run_fleet(&opts)?;
            print_fleet(&report);
            println!("  written: {}", opts.out.join("fleet.json").display());
        }
        Command::Hyper(opts) => {
            let report = run_hyper(&opts)?;
            print_hyper(&report);
            println!("  written: {}", opts.out.join("hyper.json").display());
        }
    }
    Ok(())
}
