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

/// With a radius shorter than the fusion's reach, ground beside the path is fused while its
/// tile lies beyond the radius, evicted to disk after each insert, and must come back before the
/// next scan fuses into it: otherwise each eviction would replace its page with that scan's
/// cells alone. Here the robot drives along y = 0 with a 2 m radius, one scan per insert, and the
/// tile row at y 2.5–5 m (centres 3.75 m from the path) is evicted after every insert; a cell at
/// y = 2.8 m lies within the smallest reach (3 m) of at least two poses, so on disk it holds at
/// least two scans. Before the fix it held one: the last insert's.
#[test]
fn tiles_fused_beyond_the_radius_keep_every_scan_on_disk() -> anyhow::Result<()> {
    let tmp = TempDir::new("sitemap-reach")?;
    let dir = tmp.path().to_path_buf();
    let h = Harness::start(|c| {
        c.checkpoint.dir = Some(dir.clone());
        c.window.capacity = 2;
        c.aggregate.radius_m = 2.0;
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
    assert!(
        s.aggregate.paged_out > 0 && s.aggregate.paged_in > 0,
        "{:?}",
        s.aggregate
    );
    let identity = rangegp_service::checkpoint::identity(
        &h.config.map_id,
        &rangegp_service::map::aggregate::world::WorldParams::default(),
    );
    let pages = rangegp_service::checkpoint::PageStore::open(&dir, identity)?;
    let mut checked = 0;
    for x in [2.0, 3.0, 4.0, 5.0] {
        let params = rangegp_service::map::aggregate::world::WorldParams::default();
        let cell = (
            (x / params.cell_m).floor() as i32,
            (2.8 / params.cell_m).floor() as i32,
        );
        let tile = (
            cell.0.div_euclid(params.tile_cells),
            cell.1.div_euclid(params.tile_cells),
        );
        let page = pages.read(tile)?;
        let scans = page.cells.iter().find(|(c, _)| *c == cell).map(|(_, c)| c.scans);
        println!("cell {cell:?} (x {x} m, y 2.8 m) on disk holds {scans:?} scans");
        if let Some(n) = scans {
            assert!(
                n >= 2,
                "the page of tile {tile:?} holds cell {cell:?} with {n} scan(s)"
            );
            checked += 1;
        }
    }
    assert!(checked >= 3, "only {checked} of 4 cells beside the path on disk");
    drop(h);
    Ok(())
}
