//! Crashes and damaged disks, with real processes killed by SIGKILL:
//!
//! - a publisher killed mid-stream and restarted (same id, sequences from 1) is accepted again;
//! - the daemon killed 20 times under load restores its aggregate from the checkpoint each time,
//!   answering exactly like a replay of the scans the checkpoint names, with the σ scales it
//!   had learnt, losing at most 1 s;
//! - 1 000 random corruptions of a checkpoint are all rejected and the daemon starts anyway.
//!
//! `RANGEGP_KILL_CYCLES` and `RANGEGP_CORRUPTIONS` change the counts (defaults 20 and 1000).

use anyhow::{ensure, Context, Result};
use rand::{Rng, SeedableRng};
use rangegp_client::{Client, ScanPublisher};
use rangegp_lab::scangen::{now_ns, GeneratedScan};
use rangegp_proto::msg::{MapUpdate, Source};
use rangegp_proto::scan::ScanHeader;
use rangegp_service::checkpoint::{self, Store};
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::scales::SigmaScales;
use rangegp_service::map::{calibration, query, LocalRangeMap, MapSnapshot};
use rangegp_tests::child::{self, ChildProcess};
use rangegp_tests::{env_count, ping_pong, unique_id, world, Harness, TempDir, WAIT};
use rangegp_transport::{reserve_loopback_endpoint, ReservedEndpoint};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Child role: a daemon running the configuration file named in its arguments until killed.
#[test]
#[ignore = "child process of the daemon-kill test"]
fn child_daemon() -> Result<()> {
    let Some(path) = child::args() else { return Ok(()) };
    let config = Config::load(Path::new(&path))?;
    let _daemon = Daemon::builder(config.clone()).start()?;
    child::say("ready");
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

/// Child role: a driver publishing seed-000 scans at 20 Hz as `<service> <publisher id>`.
#[test]
#[ignore = "child process of the publisher-kill test"]
fn child_publisher() -> Result<()> {
    let Some(args) = child::args() else { return Ok(()) };
    let (service, id) = args.split_once(' ').context("args: <service> <publisher id>")?;
    let mut publisher = ScanPublisher::new(service, id.parse()?, 4096)?;
    let mut w = world(8, 8);
    let scans: Vec<GeneratedScan> = (0..8).map(|i| w.scan(i, 0)).collect();
    for i in 0.. {
        let scan = &scans[ping_pong(i, scans.len())];
        let sequence = publisher.publish(
            ScanHeader {
                stamp_ns: now_ns(),
                ..scan.header
            },
            &scan.points,
        )?;
        if i == 0 {
            child::say(&format!("first {sequence}"));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

#[test]
fn a_publisher_killed_mid_stream_is_replaced_and_its_successor_accepted_within_2_s() -> Result<()> {
    let h = Harness::start(|_| {})?;
    let updates: Arc<Mutex<Vec<(Instant, MapUpdate)>>> = Arc::default();
    let _sub = {
        let updates = Arc::clone(&updates);
        h.client
            .subscribe_map_updates(move |u| updates.lock().expect("lock").push((Instant::now(), u)))?
    };
    let args = format!("{} 77", h.config.scan_service_name());
    let mut first = ChildProcess::spawn("child_publisher", &args)?;
    first.expect("first", WAIT)?;
    let s = h.wait_status("scans of the first publisher", |s| s.scans_accepted >= 5)?;
    first.kill()?;
    let highest = updates
        .lock()
        .expect("lock")
        .iter()
        .map(|(_, u)| u.sequence)
        .max()
        .unwrap_or(0);
    ensure!(highest >= 5, "first publisher mapped up to {highest}");

    let mut second = ChildProcess::spawn("child_publisher", &args)?;
    second.expect("first", WAIT)?;
    let since = Instant::now();
    // Its sequences start at 1 again: an update below the old highest is the new process's.
    let deadline = since + WAIT;
    let accepted_at = loop {
        let found = updates
            .lock()
            .expect("lock")
            .iter()
            .find(|(at, u)| *at >= since && u.publisher_id == 77 && u.sequence < highest)
            .map(|(at, _)| *at);
        if let Some(at) = found {
            break at;
        }
        ensure!(
            Instant::now() < deadline,
            "the restarted publisher was never accepted"
        );
        std::thread::sleep(Duration::from_millis(2));
    };
    let delay = accepted_at.saturating_duration_since(since);
    let after = h.client.status()?;
    eprintln!(
        "publisher kill: restarted driver's first scan mapped {:.0} ms after it was sent; \
         accepted {} before the kill, {} now, stale rejections {}",
        delay.as_secs_f64() * 1e3,
        s.scans_accepted,
        after.scans_accepted,
        after
            .rejections
            .iter()
            .find(|r| r.reason == "stale_sequence")
            .map_or(0, |r| r.count)
    );
    ensure!(delay <= Duration::from_secs(2), "accepted after {delay:?}");
    Ok(())
}

/// The daemon configuration of one kill cycle: a fresh endpoint (held until the child daemon
/// listens on it), the shared checkpoint directory.
fn cycle_config(base: &Config, dir: &Path) -> Result<(Config, PathBuf, ReservedEndpoint)> {
    let mut config = base.clone();
    let reserved = reserve_loopback_endpoint()?;
    config.zenoh.listen = vec![reserved.endpoint().to_owned()];
    let path = dir.join("rangegpd.toml");
    std::fs::write(&path, toml::to_string(&config)?)?;
    Ok((config, path, reserved))
}

/// The reference: the scans a checkpoint names, replayed in order through validation, the fit
/// and the aggregate exactly as the daemon does it.
struct Replay {
    world: WorldAggregate,
    scans: Vec<GeneratedScan>,
    config: Config,
}

impl Replay {
    fn extend(
        &mut self,
        from: usize,
        history: &[rangegp_service::map::aggregate::world::ScanRef],
    ) -> Result<()> {
        let limits = ValidationLimits {
            max_future_ns: u64::MAX,
            ..self.config.validation_limits()
        };
        // The daemon fuses the scans that waited together, each insert at its own reach: replay
        // insert by insert, as the history records them.
        let mut inserts: Vec<Vec<&rangegp_service::map::aggregate::world::ScanRef>> = Vec::new();
        for r in &history[from..] {
            match inserts.last_mut() {
                Some(group) if group[0].insert == r.insert => group.push(r),
                _ => inserts.push(vec![r]),
            }
        }
        for group in inserts {
            let mut fitted = Vec::new();
            for r in &group {
                let scan = &self.scans[ping_pong(r.sequence as usize - 1, self.scans.len())];
                let header = ScanHeader {
                    publisher_id: r.publisher_id,
                    sequence: r.sequence,
                    stamp_ns: r.stamp_ns,
                    point_count: scan.points.len() as u32,
                    ..scan.header
                };
                let input =
                    validate(&header, &scan.points, &limits, 0).map_err(|e| anyhow::anyhow!("{e:?}"))?;
                let map = LocalRangeMap::fit(&input, &self.config.map_params())?;
                fitted.push((input, map));
            }
            let batch: Vec<_> = fitted.iter().map(|(s, m)| (s, m)).collect();
            // With the window's departure weights the daemon had learnt when it fused them.
            self.world.set_window_scales(&SigmaScales {
                departure: group[0].departure_weights,
                ..SigmaScales::default()
            });
            self.world
                .insert_all_and_evict(&batch, self.config.aggregate.radius_m, group[0].reach_m)?;
        }
        Ok(())
    }
}

#[test]
fn the_daemon_killed_under_load_restores_its_aggregate_each_time() -> Result<()> {
    let cycles = env_count("RANGEGP_KILL_CYCLES", 20);
    let tmp = TempDir::new("kill")?;
    let dir = tmp.path().to_path_buf();
    let mut base = Config {
        map_id: unique_id("kill"),
        ..Config::default()
    };
    base.ingest.service_name = format!("rangegp/{}/scans", unique_id("svc"));
    base.metrics.listen = String::new();
    base.checkpoint.dir = Some(dir.join("checkpoints"));
    base.checkpoint.interval_ms = 250;
    // Nothing leaves the radius on this 40 m path: the replay below models fusion and eviction,
    // not the site map's paging (tests/tests/site_map.rs covers that).
    base.aggregate.radius_m = 1000.0;
    let params = WorldParams::default();
    let identity = checkpoint::identity(&base.map_id, &params);

    let mut w = world(8, 40);
    let scans: Vec<GeneratedScan> = (0..40).map(|i| w.scan(i, 0)).collect();
    let mut publisher = ScanPublisher::new(&base.scan_service_name(), 5, 4096)?;
    let mut replay = Replay {
        world: WorldAggregate::new(params),
        scans: scans.clone(),
        config: base.clone(),
    };
    let (mut restored_len, mut lost_max, mut compared, mut answers) = (0usize, 0f64, 0usize, 0u64);
    let mut answered = 0usize;
    let mut last_published_stamp = 0u64;
    for cycle in 0..cycles {
        // What the killed daemon left on disk (nothing before the first start).
        let store = Store::open(&dir.join("checkpoints"), 2)?;
        let (restored, rejected) = store.restore(identity, &params)?;
        ensure!(
            rejected.is_empty(),
            "cycle {cycle}: a checkpoint was damaged: {rejected:?}"
        );
        if let Some(r) = &restored {
            let history = &r.checkpoint.world.history;
            ensure!(
                history.len() >= restored_len,
                "cycle {cycle}: restored history shrank"
            );
            ensure!(
                history[..restored_len] == replay.world.state().history[..],
                "cycle {cycle}: scans restored before were lost"
            );
            replay.extend(restored_len, history)?;
            restored_len = history.len();
            ensure!(
                replay.world.state() == r.checkpoint.world,
                "cycle {cycle}: the checkpoint differs from a replay of the scans it names"
            );
            let newest = history.last().map_or(0, |s| s.stamp_ns);
            let lost = last_published_stamp.saturating_sub(newest) as f64 * 1e-9;
            lost_max = lost_max.max(lost);
        } else {
            ensure!(cycle == 0, "cycle {cycle}: nothing to restore");
        }

        let (config, path, reserved) = cycle_config(&base, &dir)?;
        let mut daemon = ChildProcess::spawn("child_daemon", &path.to_string_lossy())?;
        daemon.expect("ready", WAIT)?;
        drop(reserved);
        let client = Client::builder(&config.map_id)
            .connect(config.zenoh.listen.clone())
            .timeout(WAIT)
            .open()?;
        client.wait_for_daemon(WAIT)?;

        // Before any new scan: the restored aggregate answers exactly as the replay does, with
        // the σ scales the killed daemon had learnt (none before the first checkpoint).
        let scales = restored
            .as_ref()
            .and_then(|r| r.checkpoint.scales)
            .map_or_else(SigmaScales::default, |s| {
                calibration::under_settings(s, config.gp.unseen_relief, config.gp.view_disagreement)
            });
        ensure!(
            restored.is_none() || scales.learnt.aggregate.iter().flatten().flatten().any(|&l| l),
            "cycle {cycle}: the checkpoint kept no learnt σ scales"
        );
        let reference = MapSnapshot::new(
            Vec::new(),
            Some(Arc::new(WorldAggregate::from_state(replay.world.state())?)),
        )
        .with_scales(scales)
        .with_max_sigma(config.query.max_sigma_m);
        let probes: Vec<[f64; 2]> = replay
            .world
            .cells()
            .keys()
            .step_by(97)
            .map(|&(i, j)| [(i as f64 + 0.3) * params.cell_m, (j as f64 + 0.6) * params.cell_m])
            .collect();
        if !probes.is_empty() {
            let got = client.elevation(&probes)?;
            for (p, item) in probes.iter().zip(&got) {
                let want = query::elevation(&reference, p[0], p[1]);
                ensure!(
                    *item == want,
                    "cycle {cycle}: at {p:?} the daemon says {item:?}, the replay {want:?}"
                );
                answered += usize::from(item.source == Source::Aggregate && item.z_m.is_some());
            }
            compared += probes.len();
        }

        // Load: scans at 10 Hz and a planner querying, then SIGKILL at an uneven moment.
        let stop = Arc::new(AtomicBool::new(false));
        let planner_answers = Arc::new(AtomicU64::new(0));
        let planner = {
            let (stop, n) = (Arc::clone(&stop), Arc::clone(&planner_answers));
            let client = Client::builder(&config.map_id)
                .connect(config.zenoh.listen.clone())
                .timeout(Duration::from_secs(2))
                .open()?;
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    if client.elevation(&[[3.0, 0.5], [6.0, 2.0]]).is_ok() {
                        n.fetch_add(1, Ordering::Relaxed);
                    }
                    std::thread::sleep(Duration::from_millis(5));
                }
            })
        };
        let run = Duration::from_millis(1200 + 37 * (cycle as u64 % 7));
        let started = Instant::now();
        while started.elapsed() < run {
            let next = publisher.next_sequence();
            let scan = &scans[ping_pong(next as usize - 1, scans.len())];
            let stamp = now_ns();
            publisher.publish(
                ScanHeader {
                    stamp_ns: stamp,
                    ..scan.header
                },
                &scan.points,
            )?;
            last_published_stamp = stamp;
            std::thread::sleep(Duration::from_millis(100));
        }
        daemon.kill()?;
        stop.store(true, Ordering::Relaxed);
        planner.join().map_err(|_| anyhow::anyhow!("planner panicked"))?;
        answers += planner_answers.load(Ordering::Relaxed);
        eprintln!("kill cycle {}/{cycles}: restored {restored_len} scans", cycle + 1);
    }
    eprintln!(
        "daemon kills: {cycles} cycles; restored aggregate equal to the replay every time \
         ({compared} elevation answers compared, {answered} answered by the aggregate with the \
         checkpoint's σ scales); scans lost per kill at most {lost_max:.2} s; planner answers \
         under load {answers}"
    );
    ensure!(restored_len > 0, "no checkpoint ever restored");
    ensure!(answered > 0, "no restored answer was compared");
    let largest = std::fs::read_dir(dir.join("checkpoints"))?
        .filter_map(|e| e.ok()?.metadata().ok())
        .map(|m| m.len())
        .max()
        .unwrap_or(0);
    eprintln!(
        "largest checkpoint file {largest} bytes; the last restored aggregate held {} cells",
        replay.world.cells().len()
    );
    ensure!(lost_max <= 1.0, "lost {lost_max:.2} s of scans in one kill");
    Ok(())
}

/// One random way to damage a file; never returns the bytes unchanged.
fn corrupt(valid: &[u8], rng: &mut impl Rng) -> Vec<u8> {
    loop {
        let mut b = valid.to_vec();
        let len = b.len();
        match rng.random_range(0..8) {
            0 => {
                let i = rng.random_range(0..len);
                b[i] ^= 1 << rng.random_range(0..8);
            }
            1 => {
                for _ in 0..rng.random_range(2..32) {
                    let i = rng.random_range(0..len);
                    b[i] = rng.random();
                }
            }
            2 => b.truncate(rng.random_range(0..len)),
            3 => b.extend((0..rng.random_range(1..64)).map(|_| rng.random::<u8>())),
            4 => {
                let at = rng.random_range(0..len);
                let end = (at + rng.random_range(1..256)).min(len);
                b[at..end].fill(0);
            }
            5 => {
                let (i, j) = (rng.random_range(0..len), rng.random_range(0..len));
                b.swap(i, j);
            }
            6 => b = (0..rng.random_range(0..len * 2)).map(|_| rng.random()).collect(),
            _ => {
                // A sector of another file: a page of garbage in the middle.
                let at = rng.random_range(0..len);
                for v in b.iter_mut().skip(at).take(512) {
                    *v = rng.random();
                }
            }
        }
        if b != valid {
            return b;
        }
    }
}

#[test]
fn every_corrupted_checkpoint_is_rejected_and_the_daemon_starts() -> Result<()> {
    let corruptions = env_count("RANGEGP_CORRUPTIONS", 1000);
    let tmp = TempDir::new("corrupt")?;
    let dir = tmp.path().to_path_buf();
    let ckpt = dir.join("checkpoints");
    // A real checkpoint: a daemon maps a few scans and shuts down (the final write).
    let h = Harness::start(|c| {
        c.aggregate.queue_len = 8;
        c.checkpoint.dir = Some(ckpt.clone());
    })?;
    let mut publisher = h.publisher(3)?;
    let mut w = world(8, 3);
    for i in 0..3 {
        let scan = w.scan(i, now_ns());
        publisher.publish(scan.header, &scan.points)?;
        h.wait_status("the scan aggregated", |s| s.aggregate.inserts == i as u64 + 1)?;
    }
    let config = h.config.clone();
    h.daemon.shutdown();
    let store = Store::open(&ckpt, 2)?;
    let params = WorldParams::default();
    let identity = checkpoint::identity(&config.map_id, &params);
    let (newest, _) = store.restore(identity, &params)?;
    let newest = newest.context("the shutdown checkpoint")?;
    ensure!(
        newest.world.inserts() == 3,
        "checkpoint of {} inserts",
        newest.world.inserts()
    );
    let &(i, j) = newest.world.cells().keys().min().context("cells")?;
    let probe = [[(i as f64 + 0.5) * params.cell_m, (j as f64 + 0.5) * params.cell_m]];
    let valid = std::fs::read(&store.generations()?[0].1)?;

    let mut rng = rand_pcg::Pcg64::seed_from_u64(6);
    let trial = dir.join("trial");
    let mut loaded = 0;
    for _ in 0..corruptions {
        let _ = std::fs::remove_dir_all(&trial);
        let store = Store::open(&trial, 2)?;
        store.write(&corrupt(&valid, &mut rng))?;
        let (restored, rejected) = store.restore(identity, &params)?;
        loaded += usize::from(restored.is_some());
        ensure!(rejected.len() == 1, "one file, one rejection");
    }
    eprintln!("checkpoint corruption: {corruptions} corrupted files, {loaded} loaded");
    ensure!(loaded == 0, "{loaded} corrupted checkpoints were loaded");

    // The daemon on a damaged newest generation: logs it, restores the previous one, answers.
    let store = Store::open(&ckpt, 3)?;
    store.write(&corrupt(&valid, &mut rng))?;
    let restart = |dir: PathBuf| -> Result<Harness> {
        let map_id = config.map_id.clone();
        Harness::start(move |c| {
            c.map_id = map_id;
            c.checkpoint.dir = Some(dir);
        })
    };
    let h = restart(ckpt.clone())?;
    let s = h.client.status()?;
    ensure!(s.aggregate.cells > 0, "previous generation restored");
    ensure!(h.daemon.metrics().checkpoints_rejected.load(Ordering::Relaxed) == 1);
    ensure!(h.client.elevation(&probe)?[0].source == Source::Aggregate);
    h.daemon.shutdown();
    // Only damaged files: the daemon starts with an empty aggregate.
    let only_bad = dir.join("only-bad");
    let store = Store::open(&only_bad, 2)?;
    store.write(&corrupt(&valid, &mut rng))?;
    store.write(&corrupt(&valid, &mut rng))?;
    let h = restart(only_bad)?;
    ensure!(h.client.status()?.aggregate.cells == 0, "nothing restored");
    ensure!(h.daemon.metrics().checkpoints_rejected.load(Ordering::Relaxed) == 2);
    drop(h);
    Ok(())
}
