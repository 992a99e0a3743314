//! The streaming daemon's observability over the real transports: map-update events, status
//! latencies / aggregate / RSS, the Prometheus endpoint, the echo baseline, a bounded aggregate,
//! and `rangegp load` in a reduced form.

use rangegp_lab::load::{self, LoadOptions};
use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{MapUpdate, Source};
use rangegp_sim::ScannerPreset;
use rangegp_tests::{world, Harness, TempDir, WAIT};
use std::io::{Read, Write};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// `GET /metrics` over loopback TCP, the body.
fn scrape(addr: std::net::SocketAddr) -> anyhow::Result<String> {
    let mut stream = std::net::TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(WAIT))?;
    write!(
        stream,
        "GET /metrics HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    anyhow::ensure!(response.starts_with("HTTP/1.1 200"), "{response}");
    Ok(response)
}

#[test]
fn every_scan_is_announced_and_counted_in_status_and_prometheus() -> anyhow::Result<()> {
    let h = Harness::start(|c| {
        c.aggregate.queue_len = 8;
    })?;
    let updates: Arc<Mutex<Vec<MapUpdate>>> = Arc::default();
    let _sub = {
        let updates = Arc::clone(&updates);
        h.client
            .subscribe_map_updates(move |u| updates.lock().expect("lock").push(u))?
    };
    let mut publisher = h.publisher(4)?;
    let mut w = world(8, 4);
    for i in 0..4 {
        let scan = w.scan(i, now_ns());
        publisher.publish(scan.header, &scan.points)?;
        h.wait_status("the scan accepted", |s| s.scans_accepted == i as u64 + 1)?;
    }
    let deadline = Instant::now() + WAIT;
    while updates.lock().expect("lock").len() < 4 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    let got = updates.lock().expect("lock").clone();
    let sequences: Vec<u64> = got.iter().map(|u| u.sequence).collect();
    assert_eq!(sequences, [1, 2, 3, 4], "one event per scan, in order");
    assert!(got.iter().all(|u| u.publisher_id == 4 && u.latency_ms > 0.0));
    assert_eq!(got[3].window_len, 4);

    h.client.elevation(&[[3.0, 0.5]])?;
    let s = h.wait_status("every scan in the aggregate", |s| s.aggregate.inserts == 4)?;
    assert_eq!((s.fit_ms.count, s.scan_to_queryable_ms.count), (4, 4));
    // Receive-to-queryable contains each scan's fit, so it dominates it rank by rank.
    assert!(s.scan_to_queryable_ms.p50_ms >= s.fit_ms.p50_ms && s.fit_ms.p50_ms > 0.0);
    assert!(s.fit_ms.p99_ms >= s.fit_ms.p50_ms && s.fit_ms.max_ms >= s.fit_ms.p99_ms);
    assert_eq!(s.query_ms.elevation.count, 1);
    assert!(s.aggregate.enabled && s.aggregate.cells > 0 && s.aggregate.tiles > 0);
    assert!(s.rss_mb.is_some_and(|mb| mb > 1.0), "{:?}", s.rss_mb);

    let addr = h.daemon.metrics_addr().expect("metrics served");
    let body = scrape(addr)?;
    for line in [
        "rangegp_scans_accepted_total 4",
        "rangegp_scans_skipped_total 0",
        "rangegp_scans_rejected_total{reason=\"invalid_pose\"} 0",
        "rangegp_fit_seconds_count 4",
        "rangegp_scan_to_queryable_seconds_count 4",
        "rangegp_aggregate_inserts_total 4",
        "rangegp_window_maps 4",
    ] {
        assert!(body.contains(line), "{line:?} missing from\n{body}");
    }
    assert!(
        body.contains("rangegp_query_seconds_count{kind=\"elevation\"} 1"),
        "{body}"
    );
    assert!(body.contains("rangegp_resident_memory_bytes"), "{body}");
    assert_eq!(h.client.echo(b"ping".to_vec())?, b"ping");
    Ok(())
}

#[test]
fn every_accepted_scan_is_fused_even_when_the_aggregate_lags() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(7)?;
    let mut w = world(21, 12);
    // Fitting takes milliseconds, an aggregate insert tens: it falls behind and must catch up
    // by fusing the waiting scans together, not by dropping them.
    for i in 0..12 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    let s = h.wait_status("every scan fused", |s| s.aggregate.inserts == 12)?;
    assert_eq!((s.aggregate.skipped, s.aggregate.failed), (0, 0));
    assert_eq!(s.scans_accepted, 12);
    Ok(())
}

#[test]
fn the_aggregate_forgets_what_lies_beyond_its_radius() -> anyhow::Result<()> {
    let h = Harness::start(|c| {
        c.window.capacity = 2;
        c.aggregate.queue_len = 16;
        c.aggregate.radius_m = 12.0;
    })?;
    let mut publisher = h.publisher(6)?;
    // Scans 3 m apart: the path leaves the first scans' tiles more than 12 m behind.
    let mut w = rangegp_lab::scangen::ScanGenerator::new(2, 60.0, ScannerPreset::seed000(), 10, 3.0);
    let [x0, y0, heading0] = w.path.waypoints[0];
    let ahead = [x0 + 3.0 * heading0.cos(), y0 + 3.0 * heading0.sin()];
    let mut seen_early = None;
    // Stamped 0.2 s apart (15 m/s): as fast as a robot may plausibly move.
    let t0 = now_ns() - 2_000_000_000;
    for i in 0..10 {
        let scan = w.scan(i, t0 + i as u64 * 200_000_000);
        publisher.publish(scan.header, &scan.points)?;
        h.wait_status("the scan in the aggregate", |s| {
            s.aggregate.inserts == i as u64 + 1
        })?;
        if i == 3 {
            // Out of the 2-map window already, still in the aggregate.
            seen_early = Some(h.client.elevation(&[ahead])?[0].source);
        }
    }
    assert_eq!(seen_early, Some(Source::Aggregate));
    let [x, y, _] = w.path.waypoints[9];
    let behind = (ahead[0] - x).hypot(ahead[1] - y);
    assert!(behind > 16.0, "the path must leave the radius: {behind} m");
    let s = h.client.status()?;
    assert!(s.aggregate.evicted_tiles > 0, "{:?}", s.aggregate);
    assert_eq!(h.client.elevation(&[ahead])?[0].source, Source::None, "forgotten");
    Ok(())
}

#[test]
fn a_reduced_load_run_reports_every_figure() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let tmp = TempDir::new("load-out")?;
    let out = tmp.path();
    let opts = LoadOptions {
        connect: h.endpoint.clone(),
        map_id: h.config.map_id.clone(),
        service: h.config.scan_service_name(),
        preset: ScannerPreset::seed000(),
        rate_hz: 10.0,
        seconds: 3.0,
        planners: 1,
        planner_hz: 10.0,
        seed: 1,
        step_m: 0.5,
        publisher_id: 77,
        out: out.to_path_buf(),
        timeout: WAIT,
    };
    let s = load::run(&opts, |_| {})?;
    assert_eq!(s.scans_sent, 30);
    assert_eq!(
        s.scans_accepted + s.scans_skipped,
        30,
        "every scan fitted or counted as skipped"
    );
    assert_eq!(s.scans_rejected, 0);
    assert_eq!(s.scans_without_update, s.scans_skipped);
    assert!(s.scan_to_queryable_p50_ms > 0.0 && s.scan_to_queryable_p99_ms >= s.scan_to_queryable_p50_ms);
    for kind in ["elevation", "variance", "ray", "echo"] {
        let r = &s.rtt[kind];
        assert!(r.count > 0 && r.errors == 0, "{kind}: {r:?}");
    }
    assert!(s.echo_rtt_p50_us > 0.0 && s.elevation_rtt_p50_us > 0.0);
    assert!(s.rss_start_mb > 0.0 && s.rss_end_mb > 0.0);
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json"))?)?;
    for key in [
        "preset",
        "rate_hz",
        "seconds",
        "scans_sent",
        "scans_skipped",
        "scan_to_queryable_p50_ms",
        "scan_to_queryable_p99_ms",
        "elevation_rtt_p50_us",
        "echo_rtt_p50_us",
        "rss_start_mb",
        "rss_end_mb",
    ] {
        assert!(json.get(key).is_some(), "summary.json lacks {key}");
    }
    Ok(())
}
