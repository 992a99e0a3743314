//! The site map beyond the radius: tiles the robot leaves go to disk beside the checkpoints and
//! come back when it returns, over the real transports.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::Source;
use rangegp_tests::{world, Harness, TempDir};

#[test]
fn tiles_left_behind_go_to_disk_and_come_back_when_the_robot_returns() -> anyhow::Result<()> {
    let tmp = TempDir::new("sitemap")?;
    let dir = tmp.path().to_path_buf();
    let h = Harness::start(|c| {
        c.checkpoint.dir = Some(dir.clone());
        c.window.capacity = 2;
        c.aggregate.radius_m = 10.0;
    })?;
    let mut outward = h.publisher(31)?;
    let mut w = world(17, 26);
    let scans: Vec<_> = (0..26).map(|i| w.scan(i, now_ns())).collect();
    for scan in &scans[..5] {
        h.publish_fitted(&mut outward, scan)?;
    }
    h.wait_status("the start area fused", |s| s.aggregate.inserts == 5)?;
    // Ground ahead of the first pose, answered by the aggregate (the window holds scans 3, 4).
    let s0 = scans[0].pose.translation.vector;
    let heading = w.path.waypoints[0][2];
    let probes: Vec<[f64; 2]> = (0..16)
        .map(|k| {
            let az = heading + (-45.0 + 6.0 * k as f64).to_radians();
            let r = 2.5 + 0.1 * k as f64;
            [s0.x + r * az.cos(), s0.y + r * az.sin()]
        })
        .collect();
    let before = h.client.elevation(&probes)?;
    let known = before.iter().filter(|e| e.z_m.is_some()).count();
    assert!(known >= 8, "only {known} of 16 start-area points answered");

    // Drive away: the start area leaves the 10 m radius.
    for scan in &scans[5..] {
        h.publish_fitted(&mut outward, scan)?;
    }
    let s = h.wait_status("the drive fused", |s| s.aggregate.inserts == 26)?;
    assert!(s.aggregate.paged_out > 0, "{:?}", s.aggregate);
    assert_eq!(s.aggregate.page_failures, 0);
    let pages = std::fs::read_dir(dir.join("tiles"))?
        .filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().ends_with(".page"))
        .count();
    assert!(pages as u64 >= s.aggregate.paged_out.min(1), "{pages} page files");
    let away = h.client.elevation(&probes)?;
    assert!(
        away.iter().all(|e| e.source == Source::None),
        "the start area should be out of memory: {away:?}"
    );

    // Back at the start (another driver process: its own pose history).
    let mut back = h.publisher(32)?;
    h.publish_fitted(&mut back, &w.scan(0, now_ns()))?;
    let s = h.wait_status("the return fused", |s| s.aggregate.inserts == 27)?;
    assert!(s.aggregate.paged_in > 0, "{:?}", s.aggregate);
    let after = h.client.elevation(&probes)?;
    let mut compared = 0;
    for (b, a) in before.iter().zip(&after) {
        if let (Some(zb), Some(za)) = (b.z_m, a.z_m) {
            // The returning scan is fused on top of the paged tiles: close, not equal.
            assert!((za - zb).abs() < 0.02, "{zb} before, {za} after");
            compared += 1;
        }
    }
    assert!(
        compared >= known.saturating_sub(2),
        "{compared} of {known} answered again"
    );
    drop(h);
    Ok(())
}

/// With a radius shorter than the fusion's reach, ground ahead is fused while its tile lies
/// beyond the radius, evicted to disk after each insert, and must come back before the next scan
/// fuses into it: otherwise each eviction would replace its page with that scan's cells alone.
/// The same drive with a radius that evicts nothing is the reference: every cell ahead holds as
/// many scans, bit for bit the same height.
#[test]
fn tiles_fused_beyond_the_radius_keep_every_scan_on_disk() -> anyhow::Result<()> {
    let probes: Vec<[f64; 2]> = (0..8).map(|k| [4.5 + 0.5 * k as f64, 0.3]).collect();
    let cells = |radius_m: f64| -> anyhow::Result<Vec<Vec<rangegp_proto::fleet::RobotCell>>> {
        let tmp = TempDir::new("sitemap-reach")?;
        let dir = tmp.path().to_path_buf();
        let h = Harness::start(|c| {
            c.checkpoint.dir = Some(dir.clone());
            c.window.capacity = 2;
            c.aggregate.radius_m = radius_m;
        })?;
        let mut publisher = h.publisher(41)?;
        let mut w = world(19, 8);
        w.path = rangegp_sim::path::Path {
            waypoints: (0..8).map(|i| [i as f64, 0.0, 0.0]).collect(),
        };
        for i in 0..8 {
            h.publish_fitted(&mut publisher, &w.scan(i, now_ns()))?;
            h.wait_status("the scan fused", |s| s.aggregate.inserts == i as u64 + 1)?;
        }
        let s = h.client.status()?;
        if radius_m < 10.0 {
            assert!(
                s.aggregate.paged_out > 0 && s.aggregate.paged_in > 0,
                "{:?}",
                s.aggregate
            );
        } else {
            assert_eq!(s.aggregate.paged_out, 0, "{:?}", s.aggregate);
        }
        Ok(h.client.sources(&probes)?)
    };
    let reference = cells(1000.0)?;
    let evicted = cells(4.0)?;
    let scans = |c: &[rangegp_proto::fleet::RobotCell]| c.first().map_or(0, |c| c.scans);
    let counts: Vec<(u32, u32)> = reference
        .iter()
        .zip(&evicted)
        .map(|(r, e)| (scans(r), scans(e)))
        .collect();
    println!("scans per probe cell, kept in memory / evicted at 4 m: {counts:?}");
    assert!(counts.iter().filter(|(r, _)| *r >= 4).count() >= 4, "{counts:?}");
    let values = |cells: &[Vec<rangegp_proto::fleet::RobotCell>]| -> Vec<Vec<(f64, f64, u32)>> {
        cells
            .iter()
            .map(|c| c.iter().map(|c| (c.z_m, c.var_m2, c.scans)).collect())
            .collect()
    };
    assert_eq!(
        values(&reference),
        values(&evicted),
        "cells after eviction differ from the reference"
    );
    Ok(())
}
