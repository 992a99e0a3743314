//! The aggregate inside the daemon: a place only an evicted scan saw is still answered, from
//! the aggregate, close to the ground truth, by elevation and by rays; a place nobody saw is not.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{Provenance, Ray, Source};
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
        h.publish_fitted(&mut publisher, &scan)?;
        first.get_or_insert((scan.pose.translation.vector, w.path.waypoints[i][2]));
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
            assert!(item.provenance != Provenance::None && item.z_var_m2.is_some_and(|v| v > 0.0));
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

#[test]
fn rays_from_a_pose_out_of_the_window_are_answered_by_the_aggregate() -> anyhow::Result<()> {
    // The maps' own σ: the prequential scales depend on which maps stood when each scan's
    // returns were tested, which the concurrently fusing aggregate thread decides (seen from
    // 0.3× to 3× here between runs); the calibration has its own tests. (Without it the window
    // maps keep no index of their data, which nothing here asks for.)
    let h = Harness::start(|c| {
        c.window.capacity = 2;
        c.gp.prequential_calibration = false;
    })?;
    let mut publisher = h.publisher(8)?;
    let mut w = world(13, 6);
    let mut first = None;
    for i in 0..6 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
        first.get_or_insert((scan.pose.translation.vector, w.path.waypoints[i][2]));
    }
    h.wait_status("every scan fused", |s| s.aggregate.inserts == 6)?;
    // From the first pose (its map left the window four scans ago), down onto ground it saw and
    // the map answers for.
    let (s, heading) = first.expect("a scan");
    let targets: Vec<[f64; 2]> = (0..24)
        .map(|k| {
            let az = heading + (-40.0 + 3.5 * k as f64).to_radians();
            [s.x + 4.0 * az.cos(), s.y + 4.0 * az.sin()]
        })
        .collect();
    let known = h.client.elevation(&targets)?;
    let (mut rays, mut truths) = (Vec::new(), Vec::new());
    for (g, e) in targets.iter().zip(&known) {
        let (Some(gz), Provenance::Observed) = (w.terrain.height(g[0], g[1]), e.provenance) else {
            continue;
        };
        let d = [g[0] - s.x, g[1] - s.y, gz - s.z];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        rays.push(Ray {
            origin_m: [s.x, s.y, s.z],
            direction: d,
            max_range_m: 2.0 * n,
        });
        truths.push(n);
    }
    assert!(
        rays.len() >= 6,
        "only {} of 24 targets observed: {known:?}",
        rays.len()
    );
    let items = h.client.ray(&rays)?;
    // Where the two window maps still see the ground they answer; elsewhere only the aggregate
    // can. Every answer must meet the ground.
    let (mut errors, mut from_aggregate) = (Vec::new(), 0);
    for (item, truth) in items.iter().zip(&truths) {
        if item.source == Source::None {
            continue;
        }
        let Some(r) = item.range_m else {
            panic!("a ray answered here meets the ground: {item:?}\n{items:?}");
        };
        assert!(item.hit_probability.is_some_and(|p| p > 0.9), "{item:?}");
        assert!(item
            .hit_sigma_m
            .is_some_and(|s| s.iter().all(|v| v.is_finite() && *v >= 0.0)));
        assert_ne!(item.provenance, Provenance::None, "{item:?}");
        from_aggregate += usize::from(item.source == Source::Aggregate);
        errors.push(r - truth);
    }
    assert_eq!(
        errors.len(),
        rays.len(),
        "every ray to observed ground answered: {items:?}"
    );
    assert!(
        from_aggregate >= 5,
        "aggregate answered {from_aggregate} of {} rays",
        rays.len()
    );
    // Each range within 3 σ of the truth (σ of the range: a slanted view of an uncertain height
    // can be wide), and the confident ones close.
    let mut confident = Vec::new();
    for ((item, truth), e) in items.iter().zip(&truths).zip(&errors) {
        let sd = item.range_var_m2.expect("a hit has a variance").sqrt();
        assert!(
            e.abs() <= 3.0 * sd + 0.02,
            "range {:?} vs truth {truth}: {item:?}",
            item.range_m
        );
        if sd < 0.05 && item.source == Source::Aggregate {
            confident.push(*e);
        }
    }
    // 4 of 8 aggregate rays are confident (the same in every run: the maps' own σ); three keep
    // the accuracy check below from passing vacuously.
    assert!(confident.len() >= 3, "{} confident rays", confident.len());
    let e = rms(&confident);
    assert!(e < 0.05, "aggregate ray RMSE {e} over the confident rays");

    // Far from everything mapped: nothing is known, and the reply says so (not 0).
    let lost = h.client.ray(&[Ray {
        origin_m: [400.0, 400.0, 1.0],
        direction: [1.0, 0.0, -0.1],
        max_range_m: 20.0,
    }])?;
    assert_eq!(lost[0].source, Source::None);
    assert_eq!(
        (lost[0].hit_probability, lost[0].provenance),
        (None, Provenance::None)
    );
    Ok(())
}
