//! `rangegp-eval`: the seed-000 experiments (Table I, the aggregate, overhangs) with one command.

use anyhow::Result;
use clap::Parser;
use rangegp_service::eval::{run, EvalOptions};

fn main() -> Result<()> {
    let opts = EvalOptions::parse();
    let summary = run(&opts)?;
    println!("\n  written: {}", opts.out.join("summary.json").display());
    if !summary.failures.is_empty() {
        for f in &summary.failures {
            eprintln!("  FAILED: {f}");
        }
        anyhow::bail!("{} evaluation bar(s) missed", summary.failures.len());
    }
    Ok(())
}
