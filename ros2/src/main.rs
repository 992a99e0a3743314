//! `rangegp-ros2`: runs the bridge until SIGINT or SIGTERM, saying what it has done every
//! `--report-s` seconds.

use anyhow::Context;
use clap::Parser;
use rangegp_ros2::{Bridge, BridgeConfig};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The rangegp ROS 2 bridge: PointCloud2 + Odometry in, GridMap + OccupancyGrid out.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    /// Configuration (TOML); without it, the defaults (`--print-config` shows them).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print the configuration in effect as TOML and exit.
    #[arg(long)]
    print_config: bool,
    /// Seconds between progress reports.
    #[arg(long, default_value_t = 10.0)]
    report_s: f64,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,rustdds=warn,ros2_client=warn")),
        )
        .init();
    let cli = Cli::parse();
    let config = match &cli.config {
        Some(path) => BridgeConfig::load(path).with_context(|| format!("loading {}", path.display()))?,
        None => BridgeConfig::default(),
    };
    if cli.print_config {
        print!("{}", toml::to_string_pretty(&config)?);
        return Ok(());
    }
    anyhow::ensure!(
        cli.report_s.is_finite() && cli.report_s > 0.0,
        "--report-s must be positive"
    );
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone()).context("installing signal handlers")?;
    }
    let bridge = Bridge::start(config).context("starting the bridge")?;
    tracing::info!("bridge running; Ctrl-C stops it");
    let report = Duration::from_secs_f64(cli.report_s);
    let mut last = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(100));
        if last.elapsed() >= report {
            last = Instant::now();
            tracing::info!(stats = %serde_json::to_string(&bridge.stats())?, "progress");
        }
    }
    let stats = bridge.stats();
    bridge.stop();
    println!("{}", serde_json::to_string_pretty(&stats)?);
    Ok(())
}
