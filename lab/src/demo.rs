//! `rangegp demo`: the daemon on embedded defaults, a simulated rover publishing scans through
//! the real iceoryx2 publisher, and a simulated planner querying over real Zenoh (loopback,
//! scouting off). Ends with a table, `summary.json` and pictures.

use crate::plot::{Heatmap, Limits, Raster};
use crate::scangen::{now_ns, ScanGenerator};
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_client::{Client, ScanPublisher};
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_service::metrics::latency::percentile;
use rangegp_sim::ScannerPreset;
use rangegp_transport::reserve_loopback_endpoint;
use serde::Serialize;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Demo settings (CLI flags of `rangegp demo`).
#[derive(Debug, Clone, clap::Args)]
pub struct DemoOptions {
    /// Scans the rover publishes.
    #[arg(long, default_value_t = 40)]
    pub scans: usize,
    /// World seed (terrain, path, noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Metres between scans.
    #[arg(long, default_value_t = 1.0)]
    pub step_m: f64,
    /// Scans per second the rover publishes at most.
    #[arg(long, default_value_t = 10.0)]
    pub rate_hz: f64,
    /// Single-point elevation queries the planner makes after each scan.
    #[arg(long, default_value_t = 25)]
    pub queries_per_scan: usize,
    /// Cell size of the pictures, metres.
    #[arg(long, default_value_t = 0.5)]
    pub grid_resolution_m: f64,
    /// Output folder.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// No progress bar (for logs and tests).
    #[arg(long)]
    pub quiet: bool,
}

/// What the demo measured (written to `summary.json`).
#[derive(Debug, Clone, Serialize)]
pub struct DemoSummary {
    /// Scans the daemon fitted.
    pub scans_accepted: u64,
    /// Scans the daemon rejected.
    pub scans_rejected: u64,
    /// Planner queries answered with an observed elevation.
    pub points_observed: usize,
    /// Planner queries with no map covering them.
    pub points_unobserved: usize,
    /// RMSE of observed elevations against ground truth, metres.
    pub elevation_rmse_m: f64,
    /// Median absolute elevation error of observed points, metres.
    pub elevation_median_abs_m: f64,
    /// Mean predicted σ of observed elevations, metres.
    pub mean_sigma_m: f64,
    /// Fraction of observed points whose truth lies within ±1.96 σ.
    pub coverage95: f64,
    /// Single-point elevation round trip, median, microseconds.
    pub query_p50_us: f64,
    /// Single-point elevation round trip, 99th percentile, microseconds.
    pub query_p99_us: f64,
    /// Median fit time per scan, milliseconds.
    pub fit_ms_p50: f64,
    /// Scan taken from shared memory to queryable, 99th percentile, milliseconds.
    pub scan_to_queryable_p99_ms: f64,
    /// Grid cells answered in the pictures / total.
    pub grid_observed_fraction: f64,
}

/// A directory under the system's temporary directory, removed when dropped.
pub(crate) struct TempDir(pub(crate) std::path::PathBuf);

impl TempDir {
    pub(crate) fn new(name: &str) -> Result<Self> {
        let dir = std::env::temp_dir().join(format!("rangegp-{name}"));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        Ok(Self(dir))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs the demo end to end.
pub fn run(opts: &DemoOptions) -> Result<DemoSummary> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if opts.scans == 0 || !positive(opts.rate_hz) || !positive(opts.grid_resolution_m) {
        bail!("--scans, --rate-hz and --grid-resolution-m must be positive");
    }
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let reserved = reserve_loopback_endpoint().context("reserving a loopback port")?;
    let endpoint = reserved.endpoint().to_owned();
    let map_id = format!("demo-{}-{}", std::process::id(), now_ns() % 1_000_000_007);
    let mut config = Config {
        map_id: map_id.clone(),
        ..Config::default()
    };
    config.zenoh.listen = vec![endpoint.clone()];
    config.window.capacity = opts.scans;
    config.metrics.listen = "127.0.0.1:0".into();
    // Checkpoints and the site map as in production, in a directory of the demo's own that is
    // removed at the end (not the user's state directory).
    let state = TempDir::new(&map_id)?;
    config.checkpoint.dir = Some(state.0.clone());
    let daemon = Daemon::builder(config.clone())
        .start()
        .context("starting the daemon")?;
    drop(reserved);

    let client = Client::builder(&map_id)
        .connect([endpoint])
        .timeout(Duration::from_secs(10))
        .open()?;
    client
        .wait_for_daemon(Duration::from_secs(10))
        .context("daemon not reachable over zenoh")?;
    let mut rover = ScanPublisher::new(&config.scan_service_name(), 1, 4096)?;
    let mut world = ScanGenerator::new(
        opts.seed,
        100.0,
        ScannerPreset::seed000(),
        opts.scans,
        opts.step_m,
    );
    let mut planner_rng = Pcg64::seed_from_u64(opts.seed ^ 0x91a2);

    let bar = if opts.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(opts.scans as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} rover {pos}/{len} scans [{bar:30}] {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let (mut errors, mut sigmas, mut rtts) = (Vec::new(), Vec::new(), Vec::new());
    let mut unobserved = 0usize;
    let period = Duration::from_secs_f64(1.0 / opts.rate_hz);
    for i in 0..opts.scans {
        let tick = Instant::now();
        let scan = world.scan(i, now_ns());
        rover.publish(scan.header, &scan.points)?;
        wait_until_processed(&client, i as u64 + 1)?;
        let heading = world.path.waypoints[i][2];
        let s = scan.pose.translation.vector;
        for _ in 0..opts.queries_per_scan {
            let az = heading + planner_rng.random_range(-80f64..80.0).to_radians();
            let rho = planner_rng.random_range(3.0..9.0);
            let (x, y) = (s.x + rho * az.cos(), s.y + rho * az.sin());
            let Some(truth) = world.terrain.height(x, y) else {
                continue;
            };
            let sent = Instant::now();
            let item = client.elevation(&[[x, y]])?.remove(0);
            rtts.push(sent.elapsed().as_secs_f64() * 1e6);
            match (item.z_m, item.z_var_m2) {
                (Some(z), Some(v)) => {
                    errors.push(z - truth);
                    sigmas.push(v.sqrt());
                }
                _ => unobserved += 1,
            }
        }
        bar.set_message(format!("elevation RMSE {:.4} m", rms(&errors)));
        bar.inc(1);
        std::thread::sleep(period.saturating_sub(tick.elapsed()));
    }
    bar.finish();

    let status = client.status()?;
    let grid_observed_fraction = draw_pictures(&client, &world, opts)?;
    let covered = errors
        .iter()
        .zip(&sigmas)
        .filter(|(e, s)| e.abs() <= 1.96 * **s)
        .count();
    let summary = DemoSummary {
        scans_accepted: status.scans_accepted,
        scans_rejected: status.scans_rejected,
        points_observed: errors.len(),
        points_unobserved: unobserved,
        elevation_rmse_m: rms(&errors),
        elevation_median_abs_m: pct(&mut errors.iter().map(|e| e.abs()).collect::<Vec<_>>(), 0.5),
        mean_sigma_m: sigmas.iter().sum::<f64>() / sigmas.len().max(1) as f64,
        coverage95: covered as f64 / errors.len().max(1) as f64,
        query_p50_us: pct(&mut rtts, 0.50),
        query_p99_us: pct(&mut rtts, 0.99),
        fit_ms_p50: status.fit_ms.p50_ms,
        scan_to_queryable_p99_ms: status.scan_to_queryable_ms.p99_ms,
        grid_observed_fraction,
    };
    std::fs::write(
        opts.out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    drop(rover);
    daemon.shutdown();
    Ok(summary)
}

/// Waits (bounded) until the daemon has accepted or rejected `count` scans.
fn wait_until_processed(client: &Client, count: u64) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let s = client.status()?;
        if s.scans_accepted + s.scans_rejected >= count {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("daemon did not process scan {count} within 10 s");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Elevation, σ and |error| pictures over the area the rover saw, queried in batches.
fn draw_pictures(client: &Client, world: &ScanGenerator, opts: &DemoOptions) -> Result<f64> {
    let xs: Vec<f64> = world.path.waypoints.iter().map(|w| w[0]).collect();
    let ys: Vec<f64> = world.path.waypoints.iter().map(|w| w[1]).collect();
    let lim = world.terrain.half_extent();
    let fold = |v: &[f64], f: fn(f64, f64) -> f64, init: f64| v.iter().copied().fold(init, f);
    let (x0, x1) = (
        (fold(&xs, f64::min, f64::INFINITY) - 10.0).max(-lim),
        (fold(&xs, f64::max, f64::NEG_INFINITY) + 10.0).min(lim),
    );
    let (y0, y1) = (
        (fold(&ys, f64::min, f64::INFINITY) - 10.0).max(-lim),
        (fold(&ys, f64::max, f64::NEG_INFINITY) + 10.0).min(lim),
    );
    let res = opts.grid_resolution_m;
    let (nx, ny) = (((x1 - x0) / res) as usize + 1, ((y1 - y0) / res) as usize + 1);
    let cells: Vec<[f64; 2]> = (0..ny)
        .flat_map(|r| (0..nx).map(move |c| [x0 + c as f64 * res, y0 + r as f64 * res]))
        .collect();
    let mut items = Vec::with_capacity(cells.len());
    for chunk in cells.chunks(4096) {
        items.extend(client.elevation(chunk)?);
    }
    let raster = |values: Vec<Option<f64>>| Raster {
        nx,
        ny,
        x0,
        y0,
        resolution: res,
        values,
    };
    let z = raster(items.iter().map(|i| i.z_m).collect());
    let sigma = raster(items.iter().map(|i| i.z_var_m2.map(f64::sqrt)).collect());
    let error = raster(
        items
            .iter()
            .zip(&cells)
            .map(|(i, c)| Some((i.z_m? - world.terrain.height(c[0], c[1])?).abs()))
            .collect(),
    );
    let truth = raster(cells.iter().map(|c| world.terrain.height(c[0], c[1])).collect());
    let path: Vec<[f64; 2]> = world.path.waypoints.iter().map(|w| [w[0], w[1]]).collect();
    let zrange = truth
        .range()
        .map_or(Limits::Robust, |(lo, hi)| Limits::Fixed(lo, hi));
    let pictures = [
        (
            "elevation.png",
            "Predicted elevation",
            "elevation (m)",
            &z,
            zrange,
            colorous::VIRIDIS,
        ),
        (
            "truth.png",
            "Ground truth",
            "elevation (m)",
            &truth,
            zrange,
            colorous::VIRIDIS,
        ),
        (
            "sigma.png",
            "Calibrated σ of the elevation",
            "σ (m)",
            &sigma,
            Limits::Robust,
            colorous::MAGMA,
        ),
        (
            "abs_error.png",
            "Absolute elevation error",
            "|error| (m)",
            &error,
            Limits::Fixed(0.0, 0.1),
            colorous::INFERNO,
        ),
    ];
    for (file, title, unit, raster, limits, gradient) in pictures {
        Heatmap::new(title, unit)
            .limits(limits)
            .gradient(gradient)
            .path(&path)
            .save(&opts.out.join(file), raster)?;
    }
    Ok(items.iter().filter(|i| i.z_m.is_some()).count() as f64 / items.len().max(1) as f64)
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|e| e * e).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// [`percentile`], NaN when nothing was measured.
fn pct(v: &mut [f64], q: f64) -> f64 {
    percentile(v, q).unwrap_or(f64::NAN)
}

/// Prints the end-of-demo table.
pub fn print_table(s: &DemoSummary, out: &std::path::Path) {
    println!("\nrangegp demo — seed-000 scanner on cratered terrain");
    println!(
        "  scans accepted / rejected     {:>10} / {}",
        s.scans_accepted, s.scans_rejected
    );
    println!(
        "  planner points observed       {:>10} (unobserved {})",
        s.points_observed, s.points_unobserved
    );
    println!("  elevation RMSE vs truth       {:>10.4} m", s.elevation_rmse_m);
    println!(
        "  median |error|                {:>10.4} m",
        s.elevation_median_abs_m
    );
    println!("  mean predicted σ_z            {:>10.4} m", s.mean_sigma_m);
    println!("  95 % coverage                 {:>10.3}", s.coverage95);
    println!(
        "  query round trip p50 / p99    {:>10.0} / {:.0} µs",
        s.query_p50_us, s.query_p99_us
    );
    println!("  fit time per scan (p50)       {:>10.1} ms", s.fit_ms_p50);
    println!(
        "  scan to queryable (p99)       {:>10.1} ms",
        s.scan_to_queryable_p99_ms
    );
    println!("  output                        {}/{{summary.json, elevation.png, sigma.png, abs_error.png, truth.png}}", out.display());
}
