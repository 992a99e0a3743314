//! `rangegpd`: the rangegp daemon (`run`), its self-contained demo (`demo`), and its defaults.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_service::demo::{self, DemoOptions};
use std::path::PathBuf;
use tracing_subscriber::EnvFilter;

#[derive(Parser)]
#[command(
    version,
    about = "Range-based Gaussian-process terrain maps from LiDAR scans, served over Zenoh"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the daemon until SIGINT or SIGTERM.
    Run {
        /// TOML configuration (defaults for anything missing).
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Daemon + simulated rover (iceoryx2) + simulated planner (Zenoh), all on loopback.
    Demo(DemoOptions),
    /// Print the default configuration as TOML.
    DefaultConfig,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let default_level = if matches!(cli.command, Command::Demo(_)) {
        "warn"
    } else {
        "info"
    };
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default_level)))
        .with_writer(std::io::stderr)
        .init();
    match cli.command {
        Command::Run { config } => {
            let config = match config {
                Some(path) => Config::load(&path)?,
                None => Config::default(),
            };
            let mut signals = signal_hook::iterator::Signals::new([
                signal_hook::consts::SIGINT,
                signal_hook::consts::SIGTERM,
            ])
            .context("installing signal handlers")?;
            let daemon = Daemon::start(&config)?;
            notify_systemd(&[sd_notify::NotifyState::Ready]);
            if let Some(sig) = signals.forever().next() {
                tracing::info!(signal = sig, "shutting down");
            }
            notify_systemd(&[sd_notify::NotifyState::Stopping]);
            daemon.shutdown();
        }
        Command::Demo(opts) => {
            let summary = demo::run(&opts)?;
            demo::print_table(&summary, &opts.out);
        }
        Command::DefaultConfig => print!("{}", toml::to_string_pretty(&Config::default())?),
    }
    Ok(())
}

/// Tells systemd (`Type=notify`) where the daemon is; a no-op outside systemd.
fn notify_systemd(state: &[sd_notify::NotifyState]) {
    if let Err(e) = sd_notify::notify(false, state) {
        tracing::warn!(error = %e, "cannot notify systemd");
    }
}
