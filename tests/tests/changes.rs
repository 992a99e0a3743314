//! Change events end to end: scans over iceoryx2 of ground, then of the same ground with a box
//! standing on it; the daemon replaces the aggregate's cells there and says so on
//! `rangegp/<map>/events/change`, received by a planner's client over Zenoh.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::ChangeEvent;
use rangegp_tests::{world, Harness, WAIT};
use std::sync::mpsc;

#[test]
fn a_box_that_appears_is_announced_where_it_stands() -> anyhow::Result<()> {
    let h = Harness::start(|c| c.aggregate.change_detection = true)?;
    let (tx, rx) = mpsc::channel::<ChangeEvent>();
    let tx = std::sync::Mutex::new(tx);
    let _subscriber = h.client.subscribe_changes(move |e| {
        let _ = tx.lock().map(|tx| tx.send(e));
    })?;
    let mut publisher = h.publisher(6)?;
    let mut w = world(21, 4);
    for i in 0..4 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    h.wait_status("4 scans fused", |s| s.aggregate.inserts == 4)?;
    assert_eq!(
        h.client.status()?.aggregate.changed_cells,
        0,
        "static ground changed"
    );
    // A 2 × 1.6 × 0.5 m box 4 m ahead of the last pose; the robot looks at it twice more.
    let [x, y, heading] = w.path.waypoints[3];
    let (bx, by) = (x + 4.0 * heading.cos(), y + 4.0 * heading.sin());
    w.terrain = w.terrain.with_box(bx, by, [1.0, 0.8], 0.5);
    for i in [3, 2, 3] {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    let status = h.wait_status("the box fused", |s| {
        s.aggregate.inserts == 7 && s.aggregate.changed_cells > 0
    })?;
    let mut risen = 0;
    let deadline = std::time::Instant::now() + WAIT;
    while risen == 0 {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        let event = rx.recv_timeout(left)?;
        assert_eq!(event.publisher_id, 6);
        for c in &event.cells {
            let on_box = (c.x_m - bx).abs() <= 1.25 && (c.y_m - by).abs() <= 1.05;
            if c.new_z_m.is_some_and(|z| z > c.old_z_m + 0.2) {
                assert!(on_box, "a cell rose off the box: {c:?} (box at {bx:.2}, {by:.2})");
                risen += 1;
            }
        }
    }
    assert!(status.aggregate.changed_cells >= risen as u64);
    Ok(())
}
