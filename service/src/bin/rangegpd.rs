//! `rangegpd`: the rangegp daemon (`run`), its defaults, a check of a configuration, and the
//! deliberate reset of its checkpoints. The demo is the lab's (`rangegp demo`).

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use rangegp_service::checkpoint::{PageStore, Store};
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
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
    /// Print the default configuration as TOML.
    DefaultConfig,
    /// Parse and validate a configuration without starting anything; the first bad field is named.
    CheckConfig {
        /// TOML configuration to check.
        config: PathBuf,
    },
    /// Delete every checkpoint generation of the configured directory (stop the daemon first):
    /// the one deliberate way to replace a mapped area with an empty map.
    ResetCheckpoints {
        /// TOML configuration naming `[checkpoint] dir`.
        #[arg(long)]
        config: PathBuf,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")))
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
            let daemon = Daemon::builder(config.clone()).start()?;
            notify_systemd(&[sd_notify::NotifyState::Ready]);
            if let Some(sig) = signals.forever().next() {
                tracing::info!(signal = sig, "shutting down");
            }
            notify_systemd(&[sd_notify::NotifyState::Stopping]);
            daemon.shutdown();
        }
        Command::DefaultConfig => print!("{}", toml::to_string_pretty(&Config::default())?),
        Command::CheckConfig { config } => {
            let checked = Config::load(&config)?;
            checked.validate()?;
            println!("{}: valid", config.display());
        }
        Command::ResetCheckpoints { config } => {
            let config = Config::load(&config)?;
            let dir = config
                .checkpoint_dir()
                .context("checkpoints are off (checkpoint.enabled = false) or no state directory is known")?;
            let removed = Store::open(&dir, config.checkpoint.keep)?.reset()?;
            let pages = PageStore::reset(&dir)?;
            println!(
                "removed {removed} checkpoint generation(s) and {pages} paged tile(s) from {}",
                dir.display()
            );
        }
    }
    Ok(())
}

/// Tells systemd (`Type=notify`) where the daemon is; a no-op outside systemd.
fn notify_systemd(state: &[sd_notify::NotifyState]) {
    if let Err(e) = sd_notify::notify(false, state) {
        tracing::warn!(error = %e, "cannot notify systemd");
    }
}
