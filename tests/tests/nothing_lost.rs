//! Nothing already mapped is lost to one bad input: a localisation glitch, extreme sequence
//! numbers, scans that were rejected. Real transports, an in-process daemon restarted on its own
//! checkpoint directory.

use anyhow::{ensure, Result};
use rangegp_client::ScanPublisher;
use rangegp_lab::scangen::{now_ns, GeneratedScan};
use rangegp_proto::msg::{ElevationItem, Source, StatusReply};
use rangegp_proto::scan::ScanHeader;
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_tests::{unique_id, world, Harness, TempDir};
use std::path::PathBuf;

fn rejected(s: &StatusReply, reason: &str) -> u64 {
    s.rejections
        .iter()
        .find(|r| r.reason == reason)
        .map_or(0, |r| r.count)
}

/// Sends `scan` as `publisher` with `sequence`, stamped now, at `position` if given.
fn send(
    publisher: &ScanPublisher,
    id: u64,
    scan: &GeneratedScan,
    sequence: u64,
    position: Option<[f64; 2]>,
) -> Result<()> {
    let mut header = ScanHeader {
        protocol_version: PROTOCOL_VERSION,
        publisher_id: id,
        sequence,
        stamp_ns: now_ns(),
        point_count: scan.points.len() as u32,
        ..scan.header
    };
    if let Some([x, y]) = position {
        header.px_m = x;
        header.py_m = y;
    }
    publisher.publish_raw(header, &scan.points)?;
    Ok(())
}

#[test]
fn a_scan_at_a_far_pose_is_refused_and_every_mapped_point_survives_a_restart() -> Result<()> {
    let tmp = TempDir::new("far-pose")?;
    let dir = tmp.path().to_path_buf();
    let map_id = unique_id("far");
    let tweak = |c: &mut rangegp_service::config::Config| {
        c.map_id = map_id.clone();
        c.checkpoint.dir = Some(dir.clone());
        c.checkpoint.interval_ms = 20;
        c.aggregate.queue_len = 16;
    };
    let h = Harness::start(tweak)?;
    let publisher = h.publisher(3)?;
    let mut w = world(3, 8);
    let scans: Vec<GeneratedScan> = (0..8).map(|i| w.scan(i, 0)).collect();
    for (i, scan) in scans.iter().enumerate() {
        send(&publisher, 3, scan, i as u64 + 1, None)?;
        h.wait_status("the scan in the aggregate", |s| {
            s.aggregate.inserts == i as u64 + 1
        })?;
    }
    // Probe 2 m ahead of every sensor position: ground the scans saw.
    let probes: Vec<[f64; 2]> = scans
        .iter()
        .map(|s| {
            let t = s.pose.translation.vector;
            let ahead = s.pose.rotation * nalgebra::Vector3::x();
            [t.x + 2.0 * ahead.x, t.y + 2.0 * ahead.y]
        })
        .collect();
    let answers: Vec<ElevationItem> = h.client.elevation(&probes)?;
    let (probes, mapped): (Vec<[f64; 2]>, Vec<ElevationItem>) = probes
        .into_iter()
        .zip(answers)
        .filter(|(_, a)| a.z_m.is_some())
        .unzip();
    ensure!(probes.len() >= 6, "the premise: mapped ground ({mapped:?})");

    // A localisation glitch: three scans at (1e6, 1e6) from the mapping publisher, three from
    // a new publisher id (no earlier pose to compare with: the map's bounds refuse them).
    let last = &scans[7];
    for k in 0..3 {
        send(&publisher, 3, last, 9 + k, Some([1e6, 1e6]))?;
        send(&publisher, 4, last, 1 + k, Some([1e6, 1e6]))?;
    }
    let s = h.wait_status("six scans refused", |s| {
        s.scans_received == 14 && s.scans_rejected == 6
    })?;
    assert_eq!(rejected(&s, "implausible_pose"), 6, "{:?}", s.rejections);
    assert_eq!(s.scans_accepted, 8);
    // The map the daemon wrote last is the good one.
    h.wait_status("the aggregate checkpointed", |_| {
        h.daemon
            .metrics()
            .checkpoints_written
            .load(std::sync::atomic::Ordering::Relaxed)
            > 0
    })?;
    drop(h);

    let h = Harness::start(tweak)?;
    let restored = h.client.elevation(&probes)?;
    for (p, (before, after)) in probes.iter().zip(mapped.iter().zip(&restored)) {
        ensure!(
            after.source == Source::Aggregate && after.z_m.is_some(),
            "at {p:?}: before the glitch {before:?}, after the restart {after:?}"
        );
    }
    drop(h);
    Ok(())
}

#[test]
fn extreme_sequence_numbers_restart_a_source_and_rejected_scans_are_not_lost_ones() -> Result<()> {
    let h = Harness::start(|_| {})?;
    let publisher = h.publisher(5)?;
    let mut w = world(5, 8);
    let scans: Vec<GeneratedScan> = (0..8).map(|i| w.scan(i, 0)).collect();
    let sequences = [1, 2, 3, u64::MAX, 4, 5];
    // Each scan fitted before the next is sent: a burst could overtake the fitter, and the
    // newest-wins queue would skip one (counted, but not accepted).
    for (k, (&seq, scan)) in sequences.iter().zip(&scans).enumerate() {
        send(&publisher, 5, scan, seq, None)?;
        h.wait_status("the scan fitted", |s| s.scans_accepted == k as u64 + 1)?;
    }
    let s = h.wait_status("six scans fitted", |s| s.scans_accepted == 6)?;
    assert_eq!(
        rejected(&s, "stale_sequence"),
        0,
        "never locked out: {:?}",
        s.rejections
    );
    assert_eq!(s.sequence_gaps, 0, "a restart is not a loss");
    assert_eq!(s.ingest.publisher_restarts, 2, "to u64::MAX and back");

    // A rejected scan arrived: it is not lost in transport.
    let mut broken = scans[6].clone();
    broken.points[0].range_m = f32::NAN;
    send(&publisher, 5, &broken, 6, None)?;
    send(&publisher, 5, &scans[6], 7, None)?;
    let s = h.wait_status("the next scan fitted", |s| s.scans_accepted == 7)?;
    assert_eq!(rejected(&s, "invalid_range"), 1);
    assert_eq!(s.sequence_gaps, 0, "scan 6 arrived (and was refused)");
    // Two numbers that never arrived are.
    send(&publisher, 5, &scans[7], 10, None)?;
    let s = h.wait_status("the scan after a loss", |s| s.scans_accepted == 8)?;
    assert_eq!(s.sequence_gaps, 2);
    Ok(())
}

#[test]
fn the_operations_guide_names_only_error_codes_that_exist() -> Result<()> {
    let codes: Vec<String> = [
        "unsupported_version",
        "malformed_request",
        "batch_too_large",
        "invalid_argument",
        "no_map",
        "overloaded",
        "internal",
    ]
    .iter()
    .map(|c| c.to_string())
    .collect();
    for code in &codes {
        let json = serde_json::to_string(&serde_json::from_str::<rangegp_proto::msg::ErrorCode>(&format!(
            "{code:?}"
        ))?)?;
        ensure!(json == format!("{code:?}"), "{code} is not an error code");
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    for doc in ["docs/OPERATIONS.md", "docs/PROTOCOL.md"] {
        let text = std::fs::read_to_string(root.join(doc))?;
        for token in text.split('`').skip(1).step_by(2) {
            let code_like = token.ends_with("_request") || token.ends_with("_argument");
            ensure!(
                !code_like || codes.iter().any(|c| c == token),
                "{doc} names `{token}`, not an error code"
            );
        }
    }
    Ok(())
}
