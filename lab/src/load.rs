//! `rangegp load`: drives a running daemon with the scan generator at a sensor's rate while a
//! pool of simulated planners queries it, and measures the daemon's bare Zenoh echo queryable
//! (`rangegp/<map>/echo`: same process, session and transport, no map work) in the same run,
//! interleaved with the elevation queries, as the transport baseline. This is the CLI's driver (errors are `anyhow`, as at a binary
//! edge); the numbers it writes are the issue-5 acceptance figures.
//!
//! Scan-to-queryable latency is measured end to end on one clock: from the publisher's send to
//! the daemon's [`MapUpdate`] for that sequence arriving here (iceoryx2 delivery, validation,
//! fit, publication and the event's Zenoh hop all included).

use crate::scangen::{now_ns, GeneratedScan, ScanGenerator};
use anyhow::{bail, Context, Result};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_client::{Client, ScanPublisher};
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::msg::{ElevationRequest, MapUpdate, Ray, StatusReply};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_service::metrics::latency::percentile;
use rangegp_sim::ScannerPreset;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// What to run.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    /// Daemon endpoint.
    pub connect: String,
    /// Map id.
    pub map_id: String,
    /// iceoryx2 scan service.
    pub service: String,
    /// Sensor preset.
    pub preset: ScannerPreset,
    /// Scans per second.
    pub rate_hz: f64,
    /// Length of the timed run, seconds.
    pub seconds: f64,
    /// Simulated planners querying concurrently (each its own Zenoh session).
    pub planners: usize,
    /// Query rounds per second per planner.
    pub planner_hz: f64,
    /// World seed.
    pub seed: u64,
    /// Metres between poses on the path (driven back and forth).
    pub step_m: f64,
    /// Publisher id in the scan headers.
    pub publisher_id: u64,
    /// Where summary.json goes.
    pub out: PathBuf,
    /// Per-query timeout.
    pub timeout: Duration,
}

/// Round-trip figures of one query kind, microseconds.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RttSummary {
    /// Answered queries.
    pub count: usize,
    /// Queries that failed (timeout, error reply).
    pub errors: usize,
    /// Median, µs.
    pub p50_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
    /// Median over the echo's median.
    pub p50_over_echo: f64,
}

/// What a load run measured (`load-out/summary.json`).
#[derive(Debug, Clone, Serialize)]
pub struct LoadSummary {
    /// Sensor preset.
    pub preset: String,
    /// Rays per scan.
    pub rays_per_scan: usize,
    /// Scans per second asked for.
    pub rate_hz: f64,
    /// Timed run length, seconds.
    pub seconds: f64,
    /// Simulated planners.
    pub planners: usize,
    /// Scans published in the timed run.
    pub scans_sent: u64,
    /// Publishes that started later than their slot by more than one period (generator behind).
    pub scans_late: u64,
    /// Scans the daemon accepted during the run (status delta).
    pub scans_accepted: u64,
    /// Scans the daemon skipped because fitting fell behind (status delta).
    pub scans_skipped: u64,
    /// Scans the daemon rejected (status delta).
    pub scans_rejected: u64,
    /// Accepted scans the aggregate did not fuse: displaced from its queue or in a failed insert
    /// (status delta).
    pub scans_not_fused: u64,
    /// The daemon's aggregate insert (all scans waiting at once) p50 / p99, milliseconds.
    pub daemon_aggregate_insert_ms: [f64; 2],
    /// Reach each scan was fused out to at the end, metres.
    pub daemon_aggregate_reach_m: f64,
    /// Scans sent whose map update never arrived here.
    pub scans_without_update: u64,
    /// Publish to map-update received, median, milliseconds.
    pub scan_to_queryable_p50_ms: f64,
    /// Publish to map-update received, 99th percentile, milliseconds.
    pub scan_to_queryable_p99_ms: f64,
    /// Largest publish to map-update, milliseconds.
    pub scan_to_queryable_max_ms: f64,
    /// The daemon's own receive-to-queryable p99 (status, recent scans), milliseconds.
    pub daemon_scan_to_queryable_p99_ms: f64,
    /// The daemon's fit time p50 / p99 (status, recent scans), milliseconds.
    pub daemon_fit_ms: [f64; 2],
    /// Single-point elevation round trip, median, µs.
    pub elevation_rtt_p50_us: f64,
    /// Bare Zenoh echo round trip (the daemon's echo queryable, the same request bytes, the same
    /// client session, interleaved with the elevation queries), median, µs.
    pub echo_rtt_p50_us: f64,
    /// `elevation_rtt_p50_us / echo_rtt_p50_us`.
    pub elevation_over_echo: f64,
    /// Per kind: elevation (1 point), variance (64 points), ray (1 ray from an unvisited pose),
    /// grid (8 × 8 m at 0.25 m), echo.
    pub rtt: HashMap<String, RttSummary>,
    /// Daemon RSS before the first scan, MiB.
    pub rss_start_mb: f64,
    /// Daemon RSS once a fifth of the run (at most 60 s) has passed, MiB.
    pub rss_warm_mb: f64,
    /// Daemon RSS at the end, MiB.
    pub rss_end_mb: f64,
    /// `rss_end_mb / rss_warm_mb − 1`.
    pub rss_growth_after_warmup: f64,
    /// (seconds into the run, RSS MiB) every 5 s.
    pub rss_series_mb: Vec<(f64, f64)>,
    /// Aggregate cells / tiles at the end.
    pub aggregate_cells_tiles: [u64; 2],
    /// Tile messages the daemon published into its site's key space per second over the run
    /// (0 without `[fleet] site`).
    pub tiles_per_s: f64,
    /// Their bytes per second, KiB (the fleet bar: at most 1 MB/s per robot).
    pub tile_kib_per_s: f64,
}

/// [`percentile`], 0 when nothing was measured (a figure of the summary).
fn pct(v: &mut [f64], q: f64) -> f64 {
    percentile(v, q).unwrap_or(0.0)
}

/// Distinct scans held in memory and replayed (the path is driven forth and back).
fn distinct_scans(preset: &ScannerPreset, total: usize) -> usize {
    const POINT_BUDGET: usize = 4 << 20;
    total.clamp(2, (POINT_BUDGET / preset.ray_count().max(1)).clamp(2, 240))
}

/// Index into `n` path poses for the `i`-th scan, driving forth then back.
fn ping_pong(i: usize, n: usize) -> usize {
    let period = 2 * n - 2;
    let k = i % period;
    if k < n {
        k
    } else {
        period - k
    }
}

/// Latencies recorded by the planners, per kind, µs; errors counted.
#[derive(Debug, Default)]
struct Rtts(HashMap<&'static str, (Vec<f64>, usize)>);

impl Rtts {
    fn record<T, E>(&mut self, kind: &'static str, started: Instant, result: Result<T, E>) {
        let entry = self.0.entry(kind).or_default();
        match result {
            Ok(_) => entry.0.push(started.elapsed().as_secs_f64() * 1e6),
            Err(_) => entry.1 += 1,
        }
    }

    fn merge(&mut self, other: Rtts) {
        for (k, (v, e)) in other.0 {
            let entry = self.0.entry(k).or_default();
            entry.0.extend(v);
            entry.1 += e;
        }
    }
}

/// The robot's newest sensor position, for planners to query around.
type Robot = Arc<Mutex<[f64; 3]>>;

/// One simulated planner: elevation and echo (alternating first), variance, a ray from a pose
/// the robot never had, and every tenth round a grid, all around the robot, at `hz`.
fn planner(client: &Client, robot: &Robot, hz: f64, seed: u64, stop: &AtomicBool) -> Rtts {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut rtts = Rtts::default();
    let period = Duration::from_secs_f64(1.0 / hz);
    let mut round = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let tick = Instant::now();
        let [x, y, z] = *robot.lock().unwrap_or_else(PoisonError::into_inner);
        let mut near = |r: f64| [x + rng.random_range(-r..r), y + rng.random_range(-r..r)];
        let point = near(6.0);
        let request = ElevationRequest {
            version: PROTOCOL_VERSION,
            points: vec![point],
        };
        let bytes = codec::encode(Encoding::Bincode, &request).unwrap_or_default();
        let elevation = |rtts: &mut Rtts| {
            let t = Instant::now();
            rtts.record("elevation", t, client.elevation(&[point]));
        };
        let echo = |rtts: &mut Rtts| {
            let t = Instant::now();
            rtts.record("echo", t, client.echo(bytes.clone()));
        };
        if round.is_multiple_of(2) {
            elevation(&mut rtts);
            echo(&mut rtts);
        } else {
            echo(&mut rtts);
            elevation(&mut rtts);
        }
        let points: Vec<[f64; 2]> = (0..64).map(|_| near(6.0)).collect();
        let t = Instant::now();
        rtts.record("variance", t, client.variance(&points));
        let origin = near(4.0);
        let azimuth: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let ray = Ray {
            origin_m: [origin[0], origin[1], z + 0.3],
            direction: [azimuth.cos(), azimuth.sin(), -0.25],
            max_range_m: 15.0,
        };
        let t = Instant::now();
        rtts.record("ray", t, client.ray(&[ray]));
        if round % 10 == 9 {
            let t = Instant::now();
            rtts.record(
                "grid",
                t,
                client.grid([x - 4.0, y - 4.0], [x + 4.0, y + 4.0], 0.25),
            );
        }
        round += 1;
        std::thread::sleep(period.saturating_sub(tick.elapsed()));
    }
    rtts
}

/// Runs the load test; `log` receives progress lines.
pub fn run(opts: &LoadOptions, log: impl Fn(&str)) -> Result<LoadSummary> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !positive(opts.rate_hz)
        || !positive(opts.seconds)
        || !positive(opts.planner_hz)
        || !positive(opts.step_m)
    {
        bail!("rate, seconds, planner rate and step must be positive");
    }
    let total = (opts.rate_hz * opts.seconds).ceil() as usize;
    let distinct = distinct_scans(&opts.preset, total + 1);
    log(&format!(
        "generating {distinct} distinct {} scans ({} rays each), replayed forth and back",
        opts.preset.name,
        opts.preset.ray_count()
    ));
    let world = ScanGenerator::new(opts.seed, 200.0, opts.preset.clone(), distinct, opts.step_m);
    let scans: Vec<GeneratedScan> = (0..distinct)
        .into_par_iter()
        .map(|i| world.scan_independent(i, 0))
        .collect();

    let open = || {
        Client::builder(&opts.map_id)
            .connect([opts.connect.clone()])
            .timeout(opts.timeout)
            .open()
    };
    let client = open()?;
    client
        .wait_for_daemon(opts.timeout)
        .with_context(|| format!("no daemon for map {:?} at {}", opts.map_id, opts.connect))?;
    let arrivals: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    let _updates = {
        let (arrivals, publisher) = (Arc::clone(&arrivals), opts.publisher_id);
        client.subscribe_map_updates(move |u: MapUpdate| {
            if u.publisher_id == publisher {
                arrivals
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .insert(u.sequence, Instant::now());
            }
        })?
    };
    let mut publisher = ScanPublisher::new(&opts.service, opts.publisher_id, opts.preset.ray_count())?;
    let start_status = client.status()?;
    let robot: Robot = Arc::new(Mutex::new([0.0; 3]));

    // Warm-up: one scan, and wait until it is queryable, so planners start against a map.
    let warm = publish(&mut publisher, &scans[0], &robot)?;
    let deadline = Instant::now() + opts.timeout;
    while !arrivals
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .contains_key(&warm.0)
    {
        if Instant::now() > deadline {
            bail!(
                "the daemon did not map the warm-up scan within {:?}",
                opts.timeout
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    log(&format!(
        "daemon answering; {} planners at {} Hz, scans at {} Hz for {} s",
        opts.planners, opts.planner_hz, opts.rate_hz, opts.seconds
    ));

    let stop = Arc::new(AtomicBool::new(false));
    let mut planners = Vec::new();
    for p in 0..opts.planners {
        let (client, robot, stop) = (open()?, Arc::clone(&robot), Arc::clone(&stop));
        client.wait_for_daemon(opts.timeout)?;
        let (hz, seed) = (opts.planner_hz, opts.seed ^ (p as u64 + 1));
        planners.push(std::thread::spawn(move || {
            planner(&client, &robot, hz, seed, &stop)
        }));
    }
    let rss_client = open()?;
    let sampler = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || rss_samples(&rss_client, &stop))
    };

    let period = Duration::from_secs_f64(1.0 / opts.rate_hz);
    let started = Instant::now();
    let mut sent: Vec<(u64, Instant)> = Vec::with_capacity(total);
    let mut late = 0u64;
    for i in 0..total {
        let slot = started + period.mul_f64(i as f64);
        let now = Instant::now();
        if now < slot {
            std::thread::sleep(slot - now);
        } else if now - slot > period {
            late += 1;
        }
        let scan = &scans[ping_pong(i + 1, distinct)];
        sent.push(publish(&mut publisher, scan, &robot)?);
        if (i + 1) % (opts.rate_hz.ceil() as usize * 10).max(1) == 0 {
            log(&format!(
                "{:>5.0} s: {} scans sent",
                started.elapsed().as_secs_f64(),
                i + 1
            ));
        }
    }
    // Let the last scans land (bounded), then stop the planners.
    let settle = Instant::now() + Duration::from_secs(2);
    while Instant::now() < settle {
        let got = arrivals.lock().unwrap_or_else(PoisonError::into_inner);
        if sent.iter().all(|(s, _)| got.contains_key(s)) {
            break;
        }
        drop(got);
        std::thread::sleep(Duration::from_millis(10));
    }
    stop.store(true, Ordering::Relaxed);
    let mut rtts = Rtts::default();
    for p in planners {
        match p.join() {
            Ok(r) => rtts.merge(r),
            Err(_) => bail!("a planner thread panicked"),
        }
    }
    let series = sampler.join().unwrap_or_default();
    let end_status = client.status()?;

    let got = arrivals.lock().unwrap_or_else(PoisonError::into_inner).clone();
    let mut latencies: Vec<f64> = sent
        .iter()
        .filter_map(|(s, t)| {
            got.get(s)
                .map(|r| r.saturating_duration_since(*t).as_secs_f64() * 1e3)
        })
        .collect();
    let without = (sent.len() - latencies.len()) as u64;
    let mut summaries: HashMap<String, RttSummary> = HashMap::new();
    for (kind, (mut v, errors)) in rtts.0 {
        summaries.insert(
            kind.to_owned(),
            RttSummary {
                count: v.len(),
                errors,
                p50_us: pct(&mut v, 0.5),
                p99_us: pct(&mut v, 0.99),
                p50_over_echo: 0.0,
            },
        );
    }
    let echo_p50 = summaries.get("echo").map_or(0.0, |s| s.p50_us);
    for s in summaries.values_mut() {
        s.p50_over_echo = if echo_p50 > 0.0 { s.p50_us / echo_p50 } else { 0.0 };
    }
    let elevation_p50 = summaries.get("elevation").map_or(0.0, |s| s.p50_us);
    let warm_at = (opts.seconds / 5.0).min(60.0);
    let rss = |s: &StatusReply| s.rss_mb.unwrap_or(0.0);
    let rss_warm = series
        .iter()
        .find(|(t, _)| *t >= warm_at)
        .or(series.last())
        .map_or(rss(&start_status), |p| p.1);
    let delta = |f: fn(&StatusReply) -> u64| f(&end_status).saturating_sub(f(&start_status));
    let summary = LoadSummary {
        preset: opts.preset.name.to_owned(),
        rays_per_scan: opts.preset.ray_count(),
        rate_hz: opts.rate_hz,
        seconds: opts.seconds,
        planners: opts.planners,
        scans_sent: sent.len() as u64,
        scans_late: late,
        // The warm-up scan is in the delta; the timed run is what is reported.
        scans_accepted: delta(|s| s.scans_accepted).saturating_sub(1),
        scans_skipped: delta(|s| s.scans_skipped),
        scans_rejected: delta(|s| s.scans_rejected),
        scans_not_fused: delta(|s| s.aggregate.skipped + s.aggregate.failed),
        daemon_aggregate_insert_ms: [
            end_status.aggregate_insert_ms.p50_ms,
            end_status.aggregate_insert_ms.p99_ms,
        ],
        daemon_aggregate_reach_m: end_status.aggregate.reach_m,
        scans_without_update: without,
        scan_to_queryable_p50_ms: pct(&mut latencies, 0.5),
        scan_to_queryable_p99_ms: pct(&mut latencies, 0.99),
        scan_to_queryable_max_ms: latencies.iter().copied().fold(0.0, f64::max),
        daemon_scan_to_queryable_p99_ms: end_status.scan_to_queryable_ms.p99_ms,
        daemon_fit_ms: [end_status.fit_ms.p50_ms, end_status.fit_ms.p99_ms],
        elevation_rtt_p50_us: elevation_p50,
        echo_rtt_p50_us: echo_p50,
        elevation_over_echo: if echo_p50 > 0.0 {
            elevation_p50 / echo_p50
        } else {
            0.0
        },
        rtt: summaries,
        rss_start_mb: rss(&start_status),
        rss_warm_mb: rss_warm,
        rss_end_mb: rss(&end_status),
        rss_growth_after_warmup: if rss_warm > 0.0 {
            rss(&end_status) / rss_warm - 1.0
        } else {
            0.0
        },
        rss_series_mb: series,
        aggregate_cells_tiles: [end_status.aggregate.cells, end_status.aggregate.tiles],
        tiles_per_s: delta(|s| s.fleet.tiles_published) as f64 / opts.seconds,
        tile_kib_per_s: delta(|s| s.fleet.tile_bytes_published) as f64 / opts.seconds / 1024.0,
    };
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let file = opts.out.join("summary.json");
    std::fs::write(&file, serde_json::to_string_pretty(&summary)?)
        .with_context(|| format!("writing {}", file.display()))?;
    Ok(summary)
}

/// Publishes `scan` stamped now, moves the robot there; returns (sequence, send instant).
fn publish(publisher: &mut ScanPublisher, scan: &GeneratedScan, robot: &Robot) -> Result<(u64, Instant)> {
    let header = rangegp_proto::scan::ScanHeader {
        stamp_ns: now_ns(),
        ..scan.header
    };
    let t = Instant::now();
    let sequence = publisher.publish(header, &scan.points)?;
    let p = scan.pose.translation.vector;
    *robot.lock().unwrap_or_else(PoisonError::into_inner) = [p.x, p.y, p.z];
    Ok((sequence, t))
}

/// The daemon's RSS every 5 s until `stop` (seconds since start, MiB).
fn rss_samples(client: &Client, stop: &AtomicBool) -> Vec<(f64, f64)> {
    let started = Instant::now();
    let mut series = Vec::new();
    let mut next = started;
    while !stop.load(Ordering::Relaxed) {
        if Instant::now() >= next {
            if let Ok(Some(mb)) = client.status().map(|s| s.rss_mb) {
                series.push((started.elapsed().as_secs_f64(), mb));
            }
            next += Duration::from_secs(5);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    series
}

/// Prints the summary as a table.
pub fn print(s: &LoadSummary, out: &std::path::Path) {
    println!(
        "rangegp load: {} ({} rays) at {} Hz for {} s, {} planners",
        s.preset, s.rays_per_scan, s.rate_hz, s.seconds, s.planners
    );
    println!(
        "  scans sent / accepted / skipped / rejected   {} / {} / {} / {}  (late {}, no update {})",
        s.scans_sent,
        s.scans_accepted,
        s.scans_skipped,
        s.scans_rejected,
        s.scans_late,
        s.scans_without_update
    );
    println!(
        "  scan to queryable p50 / p99 / max           {:.1} / {:.1} / {:.1} ms  (daemon p99 {:.1} ms, fit p50 {:.1} ms)",
        s.scan_to_queryable_p50_ms,
        s.scan_to_queryable_p99_ms,
        s.scan_to_queryable_max_ms,
        s.daemon_scan_to_queryable_p99_ms,
        s.daemon_fit_ms[0]
    );
    println!(
        "  aggregate: not fused / insert p50 / p99     {} / {:.1} / {:.1} ms  (reach {:.1} m)",
        s.scans_not_fused,
        s.daemon_aggregate_insert_ms[0],
        s.daemon_aggregate_insert_ms[1],
        s.daemon_aggregate_reach_m
    );
    println!(
        "  fleet tiles published                       {:.1} tiles/s, {:.1} KiB/s",
        s.tiles_per_s, s.tile_kib_per_s
    );
    let mut kinds: Vec<_> = s.rtt.iter().collect();
    kinds.sort_by_key(|(k, _)| k.as_str());
    for (kind, r) in kinds {
        println!(
            "  rtt {kind:<10} p50 / p99 {:>8.0} / {:>8.0} µs   ×{:.2} echo   ({} ok, {} errors)",
            r.p50_us, r.p99_us, r.p50_over_echo, r.count, r.errors
        );
    }
    println!(
        "  daemon RSS start / warm / end               {:.1} / {:.1} / {:.1} MiB ({:+.1} % after warm-up)",
        s.rss_start_mb,
        s.rss_warm_mb,
        s.rss_end_mb,
        100.0 * s.rss_growth_after_warmup
    );
    println!(
        "  summary                                     {}",
        out.join("summary.json").display()
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_path_is_driven_forth_and_back() {
        let seq: Vec<usize> = (0..9).map(|i| ping_pong(i, 4)).collect();
        assert_eq!(seq, [0, 1, 2, 3, 2, 1, 0, 1, 2]);
    }

    #[test]
    fn distinct_scans_fit_the_memory_budget() {
        let os1 = ScannerPreset::by_name("os1-64").expect("preset");
        assert!(distinct_scans(&os1, 600) * os1.ray_count() <= 4 << 20);
        assert_eq!(distinct_scans(&ScannerPreset::seed000(), 20), 20);
        assert_eq!(distinct_scans(&ScannerPreset::seed000(), 1), 2);
    }
}
