//! The aggregate inside the daemon: a place only an evicted scan saw is still answered, from
//! the aggregate, close to the ground truth; a place nobody saw is not.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::Source;
use rangegp_tests::{rms, world, Harness, WAIT};
use std::time::Instant;

#[test]
fn scans_evicted_from_the_window_are_answered_by_the_aggregate() -> anyhow::Result<()> {
    let h = Harness::start(|c| {
        c.window.capacity = 2;
        c.aggregate.enabled = true;
    })?;
    let mut publisher = h.publisher(6)?;
    let mut w = world(11, 6);
    let mut first = None;
    for i in 0..6 {
        let scan = w.scan(i, now_ns());
        publisher.publish(scan.header, &scan.points)?;
        first.get_or_insert((scan.pose.translation.vector, w.path.waypoints[i][2]));
        // One at a time: under load the newest-wins queue would (rightly) skip scans.
        h.wait_status("the scan accepted", |s| s.scans_accepted == i as u64 + 1)?;
    }
    // Ahead of the first pose, behind the last two (the path moves 1 m per scan).
    let (s, heading) = first.expect("a scan");
    let points: Vec<[f64; 2]> = (0..12)
        .map(|k| {
            let az = heading + (-60.0 + 10.0 * k as f64).to_radians();
            [s.x + 3.5 * az.cos(), s.y + 3.5 * az.sin()]
        })
        .collect();
    // The aggregate publishes after its own thread folds each scan in: wait for it, bounded.
    let deadline = Instant::now() + WAIT;
    let items = loop {
        let items = h.client.elevation(&points)?;
        let from_aggregate = items.iter().filter(|i| i.source == Source::Aggregate).count();
        if from_aggregate >= 6 || Instant::now() > deadline {
            break items;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let mut errors = Vec::new();
    for (p, item) in points.iter().zip(&items) {
        if item.source == Source::Aggregate {
            assert!(item.observed && item.z_var_m2.is_some_and(|v| v > 0.0));
            errors.push(item.z_m.expect("z") - w.terrain.height(p[0], p[1]).expect("on the map"));
        }
    }
    assert!(
        errors.len() >= 6,
        "aggregate answered {} of 12: {items:?}",
        errors.len()
    );
    let e = rms(&errors);
    assert!(e < 0.05, "aggregate RMSE {e}");
    let far = h.client.elevation(&[[-30.0, 30.0]])?;
    assert_eq!(far[0].source, Source::None);
    Ok(())
}
