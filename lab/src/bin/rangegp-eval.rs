//! `rangegp-eval`: the seed-000 experiments (Table I, the aggregate, overhangs) with one command.

use anyhow::Result;
use clap::Parser;
use rangegp_lab::eval::{run, EvalOptions, Experiment};

/// Counted, for the site map's memory bar (`rangegp_lab::heap`).
#[global_allocator]
static HEAP: rangegp_lab::heap::Counting = rangegp_lab::heap::counting();

fn main() -> Result<()> {
    rangegp_lab::heap::register(&HEAP);
    let opts = EvalOptions::parse();
    let summary = run(&opts)?;
    // The experiments outside `all` write (and name) their own report instead.
    if !matches!(
        opts.experiment,
        Experiment::Calibration
            | Experiment::View
            | Experiment::Sitemap
            | Experiment::World
            | Experiment::Layers
    ) {
        println!("\n  written: {}", opts.out.join("summary.json").display());
    }
    match summary.failures.len() {
        0 => Ok(()),
        n => anyhow::bail!("{n} evaluation bar(s) missed"),
    }
}
