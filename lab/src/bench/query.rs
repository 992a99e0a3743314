//! `rangegp-bench query`: CPU time per answered point of each query kind against a full window
//! of seed-000 maps (and the world aggregate), on one thread — the cost behind a round trip.

use super::gp::scans;
use crate::scangen::{now_ns, to_message};
use anyhow::Result;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_client::{Client, ScanPublisher};
use rangegp_proto::msg::{GridRequest, Layer, Ray, StatusReply};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::aggregate::Aggregate;
use rangegp_service::map::grid::{self, GridBox};
use rangegp_service::map::layers::LayerModel;
use rangegp_service::map::{query, LocalRangeMap, MapSnapshot, Window};
use rangegp_sim::{simulate_scan, CraterParams, Heightmap, Path, ScannerPreset};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options of `rangegp-bench query`.
#[derive(Debug, Clone, clap::Args)]
pub struct QueryBenchOptions {
    /// Points (or rays) per timed pass.
    #[arg(long, default_value_t = 2000)]
    pub points: usize,
    /// Timed passes (medians are reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Scanner preset of the window's scans: seed000, vlp16 or os1-64.
    #[arg(long, default_value = "seed000")]
    pub preset: String,
    /// Output folder for query.json.
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
}

/// Microseconds of one thread per answered item, medians over the passes.
#[derive(Debug, Clone, Serialize)]
pub struct QueryReport {
    /// Scanner preset of the window's scans.
    pub preset: String,
    /// Window maps queried.
    pub window_maps: usize,
    /// Elevation (window first, aggregate otherwise).
    pub elevation_us: f64,
    /// Variance only.
    pub variance_us: f64,
    /// Ray from a pose near the robot's, never visited.
    pub ray_us: f64,
    /// Elevation from the aggregate alone.
    pub aggregate_elevation_us: f64,
    /// Ray over the aggregate alone (the same rays).
    pub aggregate_ray_us: f64,
    /// One scan fused into the aggregate on one thread, as the daemon's aggregate thread does
    /// (median over the window's scans), milliseconds.
    pub aggregate_insert_ms: f64,
    /// One elevation after the caches were flushed (median): a lone planner query, which finds
    /// none of the map in cache because fitting and batches ran in between.
    pub elevation_cold_us: f64,
    /// Fraction of elevation points answered.
    pub answered: f64,
    /// A 100 × 100 grid at 0.1 m around the robot with elevation and σ only, on the daemon's
    /// `query.threads`, milliseconds (median of the passes).
    pub grid_ms: f64,
    /// The same grid with every planner layer (the footprint's margin included), milliseconds.
    pub grid_all_layers_ms: f64,
    /// The grid of every layer asked of a running daemon over loopback Zenoh (bincode) by a
    /// `Client`, the scans fitted by the daemon's own threads: what a planner waits, milliseconds.
    pub daemon_grid_all_layers_ms: f64,
    /// Of that round trip, the daemon's own time (request decoded, grid evaluated, reply
    /// encoded: its `query_ms.grid` median), milliseconds; the rest is the transport's.
    pub daemon_grid_handler_ms: f64,
}

fn per_item_us(repeats: usize, items: usize, mut pass: impl FnMut()) -> f64 {
    let mut v: Vec<f64> = (0..repeats.max(1))
        .map(|_| {
            let t = Instant::now();
            pass();
            t.elapsed().as_secs_f64() * 1e6 / items.max(1) as f64
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median µs of `query` on each of (at most 200) `points`, each after streaming through a
/// buffer larger than the last-level cache.
fn cold_us(points: &[[f64; 2]], query: impl Fn(&[f64; 2])) -> f64 {
    let mut flush = vec![1u64; 64 << 17];
    let mut v: Vec<f64> = points
        .iter()
        .take(200)
        .map(|p| {
            flush.iter_mut().for_each(|w| *w = w.wrapping_mul(3));
            std::hint::black_box(&flush);
            let t = Instant::now();
            query(p);
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Median milliseconds of a 100 × 100 grid at 0.1 m centred on `centre` with `layers`, on the
/// daemon's query threads, as its grid handler computes it.
fn grid_ms(
    snapshot: &MapSnapshot,
    config: &Config,
    centre: Vector3<f64>,
    layers: &[Layer],
    repeats: usize,
) -> f64 {
    let grid_box = GridBox {
        origin_m: [centre.x - 4.95, centre.y - 4.95],
        resolution_m: 0.1,
        cols: 100,
        rows: 100,
    };
    let model = LayerModel::new(config.layers.robot(), snapshot);
    let mut v: Vec<f64> = (0..repeats.max(1))
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(grid::grid(
                snapshot,
                &grid_box,
                layers,
                &model,
                config.query.threads,
            ));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Longest wait for the benchmark's daemon (start, each scan, the fusing).
const DAEMON_WAIT: Duration = Duration::from_secs(60);

/// The grid of every layer as a planner gets it: a daemon on a loopback endpoint of its own is
/// sent `count` scans of `preset` over iceoryx2 (one at a time, each after the last was taken),
/// then a `Client` asks for the 100 × 100 grid at 0.1 m around the last pose `repeats` times;
/// the median round trip and the daemon's own median time per grid, milliseconds.
fn daemon_grid_ms(
    terrain: &Heightmap,
    preset: &ScannerPreset,
    count: usize,
    repeats: usize,
) -> Result<(f64, f64)> {
    let reserved = rangegp_transport::reserve_loopback_endpoint()?;
    let endpoint = reserved.endpoint().to_owned();
    let id = format!("bench{}", std::process::id());
    let mut config = Config {
        map_id: id.clone(),
        ..Config::default()
    };
    config.zenoh.listen = vec![endpoint.clone()];
    config.ingest.service_name = format!("rangegp/{id}/scans");
    config.metrics.listen = "127.0.0.1:0".into();
    config.checkpoint.enabled = false;
    let _daemon = Daemon::builder(config.clone()).start()?;
    drop(reserved);
    let client = Client::builder(&config.map_id)
        .connect([endpoint])
        .timeout(DAEMON_WAIT)
        .open()?;
    client.wait_for_daemon(DAEMON_WAIT)?;
    let mut publisher = ScanPublisher::new(&config.scan_service_name(), 1, preset.ray_count())?;
    let wait = |what: &str, done: &dyn Fn(&StatusReply) -> bool| -> Result<()> {
        let deadline = Instant::now() + DAEMON_WAIT;
        loop {
            let s = client.status()?;
            if done(&s) {
                return Ok(());
            }
            anyhow::ensure!(
                Instant::now() < deadline,
                "the benchmark's daemon: no {what} in time"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    };
    // The same path as the in-process window, a second apart (4 m steps: within the daemon's
    // speed check), ending a minute ago.
    let path = Path::wander(7, terrain, count, 4.0, 0.3);
    let mut rng = Pcg64::seed_from_u64(7);
    let t0 = now_ns().saturating_sub(60_000_000_000);
    let mut last = None;
    for i in 0..count {
        let pose = path.pose(terrain, i, preset.mount_height_m);
        let rays = simulate_scan(terrain, &pose, preset, &mut rng);
        let (header, points) = to_message(preset, &pose, &rays, t0 + i as u64 * 1_000_000_000);
        let before = client.status()?.scans_accepted;
        publisher.publish(header, &points)?;
        wait("accepted scan", &|s| s.scans_accepted > before)?;
        last = Some(pose.translation.vector);
    }
    wait("fused window", &|s| s.aggregate.inserts >= count as u64)?;
    let c = last.ok_or_else(|| anyhow::anyhow!("no scans"))?;
    let req = GridRequest {
        version: PROTOCOL_VERSION,
        min_m: [c.x - 5.0, c.y - 5.0],
        max_m: [c.x + 5.0, c.y + 5.0],
        resolution_m: 0.1,
        layers: Layer::ALL.to_vec(),
        robot: None,
    };
    let mut v: Vec<f64> = (0..repeats.max(1))
        .map(|_| -> Result<f64> {
            let t = Instant::now();
            std::hint::black_box(client.grid_request(&req)?);
            Ok(t.elapsed().as_secs_f64() * 1e3)
        })
        .collect::<Result<_>>()?;
    v.sort_by(f64::total_cmp);
    Ok((v[v.len() / 2], client.status()?.query_ms.grid.p50_ms))
}

/// Runs the query benchmark and writes `query.json`.
pub fn run_query(opts: &QueryBenchOptions) -> Result<QueryReport> {
    std::fs::create_dir_all(&opts.out)?;
    let config = Config::default();
    let params = config.map_params();
    let terrain = Heightmap::cratered(0, &CraterParams::default());
    let preset = ScannerPreset::by_name(&opts.preset)
        .ok_or_else(|| anyhow::anyhow!("unknown preset {:?} (seed000, vlp16, os1-64)", opts.preset))?;
    let inputs = scans(&terrain, &preset, config.window.capacity, 7)?;
    let mut window = Window::new(config.window.capacity);
    let mut world = WorldAggregate::new(WorldParams::default());
    // The daemon fuses on a one-thread pool of its own: time the inserts the same way.
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let mut insert_ms = Vec::new();
    for scan in &inputs {
        let map = LocalRangeMap::fit(scan, &params)?;
        let t = Instant::now();
        one_thread.install(|| world.insert(scan, &map))?;
        insert_ms.push(t.elapsed().as_secs_f64() * 1e3);
        window.push(Arc::new(map));
    }
    insert_ms.sort_by(f64::total_cmp);
    let world = Arc::new(world);
    let snapshot = window.snapshot().with_aggregate(Some(Arc::clone(&world)));
    let mut rng = Pcg64::seed_from_u64(11);
    let centre = inputs[inputs.len() - 1].pose.translation.vector;
    let points: Vec<[f64; 2]> = (0..opts.points)
        .map(|_| {
            [
                centre.x + rng.random_range(-6.0..6.0),
                centre.y + rng.random_range(-6.0..6.0),
            ]
        })
        .collect();
    let rays: Vec<Ray> = points
        .iter()
        .map(|p| {
            let a: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            Ray {
                origin_m: [p[0], p[1], centre.z + 0.3],
                direction: [a.cos(), a.sin(), -0.25],
                max_range_m: 15.0,
            }
        })
        .collect();
    let answered = points
        .iter()
        .filter(|p| query::elevation(&snapshot, p[0], p[1]).z_m.is_some())
        .count() as f64
        / points.len().max(1) as f64;
    let n = points.len();
    let (daemon_grid_all_layers_ms, daemon_grid_handler_ms) =
        daemon_grid_ms(&terrain, &preset, config.window.capacity, opts.repeats)?;
    let report = QueryReport {
        preset: opts.preset.clone(),
        window_maps: snapshot.maps().len(),
        elevation_us: per_item_us(opts.repeats, n, || {
            points.iter().for_each(|p| {
                std::hint::black_box(query::elevation(&snapshot, p[0], p[1]));
            })
        }),
        variance_us: per_item_us(opts.repeats, n, || {
            points.iter().for_each(|p| {
                std::hint::black_box(query::variance(&snapshot, p[0], p[1]));
            })
        }),
        ray_us: per_item_us(opts.repeats, n, || {
            rays.iter().for_each(|r| {
                std::hint::black_box(query::ray(&snapshot, r));
            })
        }),
        aggregate_elevation_us: per_item_us(opts.repeats, n, || {
            points.iter().for_each(|p| {
                std::hint::black_box(world.elevation(p[0], p[1]));
            })
        }),
        aggregate_ray_us: per_item_us(opts.repeats, n, || {
            rays.iter().for_each(|r| {
                let (o, d) = (Vector3::from(r.origin_m), Vector3::from(r.direction).normalize());
                std::hint::black_box(world.cast(o, d, r.max_range_m, &|_| 1.0));
            })
        }),
        aggregate_insert_ms: insert_ms[insert_ms.len() / 2],
        elevation_cold_us: cold_us(&points, |p| {
            std::hint::black_box(query::elevation(&snapshot, p[0], p[1]));
        }),
        answered,
        grid_ms: grid_ms(&snapshot, &config, centre, &[], opts.repeats),
        grid_all_layers_ms: grid_ms(&snapshot, &config, centre, &Layer::ALL, opts.repeats),
        daemon_grid_all_layers_ms,
        daemon_grid_handler_ms,
    };
    std::fs::write(
        opts.out.join("query.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    Ok(report)
}

/// Prints the report.
pub fn print_query(r: &QueryReport) {
    println!(
        "rangegp-bench query: µs of one thread per item, window of {} {} maps",
        r.window_maps, r.preset
    );
    println!(
        "  elevation            {:>8.1} µs  ({:.0} % answered)",
        r.elevation_us,
        100.0 * r.answered
    );
    println!("  variance             {:>8.1} µs", r.variance_us);
    println!("  ray (unvisited pose) {:>8.1} µs", r.ray_us);
    println!("  aggregate elevation  {:>8.1} µs", r.aggregate_elevation_us);
    println!("  aggregate ray        {:>8.1} µs", r.aggregate_ray_us);
    println!(
        "  aggregate insert     {:>8.1} ms per scan (one thread)",
        r.aggregate_insert_ms
    );
    println!("  elevation, cold cache {:>7.1} µs", r.elevation_cold_us);
    println!(
        "  grid 100 × 100, elevation and σ {:>6.1} ms; every layer {:.1} ms (×{:.2}; daemon's query threads)",
        r.grid_ms,
        r.grid_all_layers_ms,
        r.grid_all_layers_ms / r.grid_ms
    );
    println!(
        "  grid 100 × 100, every layer, from a running daemon over Zenoh {:>6.1} ms ({:.1} ms in the daemon)",
        r.daemon_grid_all_layers_ms, r.daemon_grid_handler_ms
    );
}
