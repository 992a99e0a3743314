//! `rangegp-bench fleet`: a site daemon's query latency against a robot's, both behind one Zenoh
//! router with a memory storage of the site's tiles, on loopback. The robot gets seed-000 scans,
//! its tiles reach the site through the router, and a planner (a client of the router) asks both
//! for single points over the mapped ground, interleaved so that both share the machine's noise.

use crate::fleet::{daemon_config, StorageRouter};
use crate::scangen::{now_ns, to_message};
use anyhow::{ensure, Result};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_client::{Client, ScanPublisher};
use rangegp_proto::fleet::FleetRole;
use rangegp_proto::keys::MapKeys;
use rangegp_proto::msg::StatusReply;
use rangegp_service::daemon::Daemon;
use rangegp_sim::{simulate_scan, CraterParams, Heightmap, Path, ScannerPreset};
use serde::Serialize;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Options of `rangegp-bench fleet`.
#[derive(Debug, Clone, clap::Args)]
pub struct FleetBenchOptions {
    /// Scans the robot maps before the timing.
    #[arg(long, default_value_t = 16)]
    pub scans: usize,
    /// Single-point queries to each of the robot and the site.
    #[arg(long, default_value_t = 1000)]
    pub queries: usize,
    /// Output folder for fleet.json.
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
}

/// What `rangegp-bench fleet` measured.
#[derive(Debug, Clone, Serialize)]
pub struct FleetReport {
    /// Scans the robot mapped.
    pub scans: usize,
    /// Tiles the site assembled from the robot.
    pub site_tiles: u64,
    /// Single-point elevation round trip to the robot (through the router), median, µs.
    pub robot_elevation_p50_us: f64,
    /// The same to the site daemon, median, µs.
    pub site_elevation_p50_us: f64,
    /// `site / robot` (the fleet bar: at most 2).
    pub site_over_robot: f64,
    /// One fleet query (`rangegp/*`, robot and site, 100 ms deadline), median, µs.
    pub fleet_elevation_p50_us: f64,
    /// Share of the site's answers with a height (the points lie on mapped ground).
    pub site_answered: f64,
}

/// Longest wait for any step of the setup.
const WAIT: Duration = Duration::from_secs(60);

/// Polls `client`'s status until `done` (bounded).
fn wait(client: &Client, what: &str, done: impl Fn(&StatusReply) -> bool) -> Result<StatusReply> {
    let deadline = Instant::now() + WAIT;
    loop {
        let s = client.status()?;
        if done(&s) {
            return Ok(s);
        }
        ensure!(Instant::now() < deadline, "no {what} in time");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Runs the fleet benchmark and writes `fleet.json`.
pub fn run_fleet(opts: &FleetBenchOptions) -> Result<FleetReport> {
    std::fs::create_dir_all(&opts.out)?;
    let reserved = rangegp_transport::reserve_loopback_endpoint()?;
    let endpoint = reserved.endpoint().to_owned();
    let tag = std::process::id();
    let (site_id, robot_id) = (format!("benchsite{tag}"), format!("benchrobot{tag}"));
    let _router = StorageRouter::start(&endpoint, &MapKeys::new(&site_id)?, WAIT)?;
    drop(reserved);
    let mut site_config = daemon_config(&site_id, &endpoint);
    site_config.fleet.role = FleetRole::Site;
    let _site_daemon = Daemon::builder(site_config).start()?;
    let mut robot_config = daemon_config(&robot_id, &endpoint);
    robot_config.fleet.site = site_id.clone();
    robot_config.fleet.tile_period_ms = 100;
    robot_config.ingest.service_name = format!("rangegp/{robot_id}/scans");
    let _robot_daemon = Daemon::builder(robot_config.clone()).start()?;
    let open = |id: &str| -> Result<Client> {
        let c = Client::builder(id)
            .connect([endpoint.clone()])
            .timeout(WAIT)
            .open()?;
        c.wait_for_daemon(WAIT)?;
        Ok(c)
    };
    let (robot, site) = (open(&robot_id)?, open(&site_id)?);

    let terrain = Heightmap::cratered(0, &CraterParams::default());
    let preset = ScannerPreset::seed000();
    let path = Path::wander(7, &terrain, opts.scans, 1.0, 0.3);
    let mut publisher = ScanPublisher::new(&robot_config.scan_service_name(), 1, preset.ray_count())?;
    let mut rng = Pcg64::seed_from_u64(7);
    let t0 = now_ns().saturating_sub(60_000_000_000);
    for i in 0..opts.scans {
        let pose = path.pose(&terrain, i, preset.mount_height_m);
        let rays = simulate_scan(&terrain, &pose, &preset, &mut rng);
        let (header, points) = to_message(&preset, &pose, &rays, t0 + i as u64 * 1_000_000_000);
        let before = robot.status()?.aggregate.inserts;
        publisher.publish(header, &points)?;
        wait(&robot, "fused scan", |s| s.aggregate.inserts > before)?;
    }
    let cells = wait(&robot, "tiles sent", |s| {
        s.fleet.tiles_pending == 0 && s.fleet.tiles_published > 0
    })?
    .aggregate
    .cells;
    let site_status = wait(&site, "site assembled", |s| s.aggregate.cells >= cells)?;

    // Points ahead of the poses (inside the seed-000 scanner's forward field of view).
    let points: Vec<[f64; 2]> = (0..opts.queries)
        .map(|_| {
            let [x, y, heading] = path.waypoints[rng.random_range(0..path.waypoints.len())];
            let (r, a) = (rng.random_range(2.0..6.0), heading + rng.random_range(-1.0..1.0));
            [x + r * f64::cos(a), y + r * f64::sin(a)]
        })
        .collect();
    let (mut robot_us, mut site_us, mut fleet_us) = (Vec::new(), Vec::new(), Vec::new());
    let mut answered = 0usize;
    let time = |f: &mut dyn FnMut() -> Result<()>| -> Result<f64> {
        let t = Instant::now();
        f()?;
        Ok(t.elapsed().as_secs_f64() * 1e6)
    };
    for p in &points {
        robot_us.push(time(&mut || {
            robot.elevation(&[*p]).map(|_| ()).map_err(Into::into)
        })?);
        site_us.push(time(&mut || {
            answered += usize::from(site.elevation(&[*p])?[0].z_m.is_some());
            Ok(())
        })?);
    }
    for p in points.iter().take(opts.queries / 10) {
        fleet_us.push(time(&mut || {
            site.fleet_elevation(&[*p], Duration::from_millis(100), &[])
                .map(|_| ())
                .map_err(Into::into)
        })?);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    let (r, s) = (median(&mut robot_us), median(&mut site_us));
    let report = FleetReport {
        scans: opts.scans,
        site_tiles: site_status.aggregate.tiles,
        robot_elevation_p50_us: r,
        site_elevation_p50_us: s,
        site_over_robot: if r > 0.0 { s / r } else { 0.0 },
        fleet_elevation_p50_us: median(&mut fleet_us),
        site_answered: answered as f64 / points.len().max(1) as f64,
    };
    std::fs::write(
        opts.out.join("fleet.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    Ok(report)
}

/// Prints the report.
pub fn print_fleet(r: &FleetReport) {
    println!(
        "rangegp-bench fleet: one robot ({} seed-000 scans) and a site behind one router",
        r.scans
    );
    println!("  site tiles assembled           {}", r.site_tiles);
    println!(
        "  elevation p50, robot / site    {:.0} / {:.0} µs  (site ×{:.2}; {:.0} % answered)",
        r.robot_elevation_p50_us,
        r.site_elevation_p50_us,
        r.site_over_robot,
        r.site_answered * 100.0
    );
    println!(
        "  fleet query p50 (robot + site) {:.0} µs",
        r.fleet_elevation_p50_us
    );
}
