//! Input hardening over the real transports: a storm of malformed scans interleaved with valid
//! ones. Nothing malformed gets in, every rejection is counted under its reason, every valid
//! scan is taken, and the daemon answers queries throughout.
//!
//! `RANGEGP_STORM=<n>` sets how many of each (default 10 000, as the acceptance asks).

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::MapUpdate;
use rangegp_proto::scan::{ScanHeader, ScanPoint, FLAG_NO_RETURN};
use rangegp_tests::{env_count, ping_pong, world, Harness, WAIT};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One way to break a valid scan, named by the reason the daemon must give.
fn malform(
    kind: usize,
    good: &ScanHeader,
    points: &[ScanPoint],
    last_valid: u64,
) -> (&'static str, ScanHeader, Vec<ScanPoint>) {
    let next = last_valid + 1;
    let h = ScanHeader {
        sequence: next,
        // Odd stamps mark malformed scans: a map update carrying one would be a leak.
        stamp_ns: good.stamp_ns | 1,
        ..*good
    };
    let mut p = points.to_vec();
    let (reason, header) = match kind {
        0 => (
            "unsupported_version",
            ScanHeader {
                protocol_version: 1,
                ..h
            },
        ),
        1 => {
            p.clear();
            ("empty_scan", ScanHeader { point_count: 0, ..h })
        }
        2 => {
            p = points.iter().cycle().take(2100).copied().collect();
            (
                "too_many_points",
                ScanHeader {
                    point_count: 2100,
                    ..h
                },
            )
        }
        3 => (
            "truncated",
            ScanHeader {
                point_count: h.point_count + 1,
                ..h
            },
        ),
        4 => {
            p[kind * 7 % points.len()].range_m = f32::NAN;
            ("invalid_range", h)
        }
        5 => {
            p[11].range_m = -2.0;
            ("invalid_range", h)
        }
        6 => {
            p[3].inclination_rad = 7.0;
            ("invalid_angle", h)
        }
        7 => {
            p[5].flags = 0x40;
            ("invalid_flags", h)
        }
        8 => (
            "invalid_pose",
            ScanHeader {
                pz_m: f64::INFINITY,
                ..h
            },
        ),
        9 => ("non_unit_quaternion", ScanHeader { qw: 0.5, ..h }),
        10 => (
            "invalid_sensor_model",
            ScanHeader {
                range_noise_per_m: 5.0,
                ..h
            },
        ),
        11 => (
            "stale_sequence",
            ScanHeader {
                sequence: last_valid - 1,
                ..h
            },
        ),
        12 => (
            "duplicate_sequence",
            ScanHeader {
                sequence: last_valid,
                ..h
            },
        ),
        13 => (
            "future_timestamp",
            ScanHeader {
                stamp_ns: (now_ns() + 60_000_000_000) | 1,
                ..h
            },
        ),
        _ => {
            for q in &mut p {
                q.flags = FLAG_NO_RETURN;
            }
            ("no_returns", h)
        }
    };
    (reason, header, p)
}

const KINDS: usize = 15;

#[test]
fn a_storm_of_malformed_scans_changes_nothing_and_every_valid_scan_is_taken() -> anyhow::Result<()> {
    let n = env_count("RANGEGP_STORM", 10_000) as u64;
    let h = Harness::start(|c| {
        c.ingest.max_points = 2000;
        // A burst of valid scans is skipped (newest wins), not queued behind the fitter.
        c.ingest.queue_len = 1;
    })?;
    let leaked: Arc<Mutex<Vec<MapUpdate>>> = Arc::default();
    let _sub = {
        let leaked = Arc::clone(&leaked);
        h.client.subscribe_map_updates(move |u| {
            if u.stamp_ns & 1 == 1 {
                leaked.lock().expect("lock").push(u);
            }
        })?
    };
    // A planner queries all along; every answer must come back.
    let stop = Arc::new(AtomicBool::new(false));
    let answered = Arc::new(AtomicU64::new(0));
    let planner = {
        let (stop, answered) = (Arc::clone(&stop), Arc::clone(&answered));
        let client = rangegp_client::Client::builder(&h.config.map_id)
            .connect([h.endpoint.clone()])
            .timeout(WAIT)
            .open()?;
        std::thread::spawn(move || -> anyhow::Result<()> {
            // From the first mapped scan on (before it, "no map" is the right answer).
            let deadline = Instant::now() + WAIT;
            while client.status()?.scans_accepted == 0 {
                anyhow::ensure!(Instant::now() < deadline, "no scan mapped");
                std::thread::sleep(Duration::from_millis(2));
            }
            while !stop.load(Ordering::Relaxed) {
                client.elevation(&[[3.0, 0.5], [5.0, -1.0]])?;
                answered.fetch_add(1, Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(2));
            }
            Ok(())
        })
    };

    let mut w = world(8, 12);
    let valid: Vec<_> = (0..12).map(|i| w.scan(i, 0)).collect();
    let mut publisher = h.publisher(21)?;
    let mut injected: BTreeMap<&str, u64> = BTreeMap::new();
    let mut sent = 0u64;
    let started = Instant::now();
    for i in 0..n {
        let scan = &valid[ping_pong(i as usize, valid.len())];
        let stamp = now_ns() & !1;
        let header = ScanHeader {
            stamp_ns: stamp,
            ..scan.header
        };
        let last_valid = publisher.publish(header, &scan.points)?;
        // The first valid scan has nothing below it to be stale against.
        let kind = if last_valid < 2 {
            (i as usize) % 11
        } else {
            (i as usize) % KINDS
        };
        let good = ScanHeader {
            publisher_id: 21,
            point_count: scan.points.len() as u32,
            ..header
        };
        let (reason, bad, points) = malform(kind, &good, &scan.points, last_valid);
        publisher.publish_raw(bad, &points)?;
        *injected.entry(reason).or_default() += 1;
        sent += 2;
        // Stay inside the subscriber's buffer (8): iceoryx2 would overwrite the oldest sample.
        if sent.is_multiple_of(6) || i + 1 == n {
            h.wait_status("the daemon to take the batch", |s| s.scans_received == sent)?;
        }
        if i % 2000 == 1999 {
            eprintln!(
                "storm: {} of {n} pairs in {:.1} s",
                i + 1,
                started.elapsed().as_secs_f64()
            );
        }
    }
    let status = h.wait_status("the last valid scan fitted or skipped", |s| {
        s.scans_accepted + s.scans_skipped + s.scans_rejected == 2 * n
    })?;
    stop.store(true, Ordering::Relaxed);
    planner
        .join()
        .map_err(|_| anyhow::anyhow!("planner panicked"))??;

    let leaked = leaked.lock().expect("lock").clone();
    assert!(leaked.is_empty(), "malformed scans reached the map: {leaked:?}");
    assert_eq!(status.scans_rejected, n, "exactly the malformed ones rejected");
    assert_eq!(
        status.scans_accepted + status.scans_skipped,
        n,
        "every valid scan taken"
    );
    for r in &status.rejections {
        let want = injected.get(r.reason.as_str()).copied().unwrap_or(0);
        assert_eq!(r.count, want, "rejections for {}", r.reason);
    }
    assert_eq!(
        status.sequence_gaps, 0,
        "malformed scans do not advance sequences"
    );
    assert!(status.scans_accepted > 0 && answered.load(Ordering::Relaxed) > 0);
    eprintln!(
        "storm: {n} valid + {n} malformed in {:.1} s; accepted {} fitted + {} skipped, rejected {}, \
         malformed accepted 0, planner answers {}",
        started.elapsed().as_secs_f64(),
        status.scans_accepted,
        status.scans_skipped,
        status.scans_rejected,
        answered.load(Ordering::Relaxed)
    );
    Ok(())
}
