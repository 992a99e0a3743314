//! Pose corrections end to end: scans sent with drifted poses over iceoryx2, the correction
//! over Zenoh, and the map (window and aggregate) answering where the true poses put it.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{ErrorCode, PoseCorrection, Rigid, Source};
use rangegp_tests::{error_code, points_ahead, rms, world, Harness};

fn wire(t: &Isometry3<f64>) -> Rigid {
    let q = t.rotation;
    Rigid {
        translation_m: t.translation.vector.into(),
        rotation_xyzw: [q.i, q.j, q.k, q.w],
    }
}

#[test]
fn a_loop_closure_moves_window_and_aggregate_onto_the_true_poses() -> anyhow::Result<()> {
    // A window of one map: the first four scans' ground is answered by the aggregate alone.
    let h = Harness::start(|c| c.window.capacity = 1)?;
    let mut publisher = h.publisher(4)?;
    let mut w = world(11, 5);
    // The odometry's error: 0.6 m sideways, 0.2 m up and 4° of heading off.
    let drift = Isometry3::from_parts(
        Translation3::new(0.3, 0.6, 0.2),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 4f64.to_radians()),
    );
    let mut poses = Vec::new();
    let start = now_ns();
    for i in 0..5 {
        let mut scan = w.scan(i, start + i as u64 * 100_000_000);
        let sent = drift * scan.pose;
        let (t, q) = (sent.translation.vector, sent.rotation);
        (scan.header.px_m, scan.header.py_m, scan.header.pz_m) = (t.x, t.y, t.z);
        (scan.header.qx, scan.header.qy, scan.header.qz, scan.header.qw) = (q.i, q.j, q.k, q.w);
        h.publish_fitted(&mut publisher, &scan)?;
        poses.push((scan.pose, w.path.waypoints[i][2]));
    }
    h.wait_status("5 scans fused", |s| s.aggregate.inserts == 5)?;
    let points = points_ahead(&poses);
    // RMSE and count of the answers from `source`.
    let errors = |h: &Harness, source: Source| -> anyhow::Result<(f64, usize)> {
        let items = h.client.elevation(&points)?;
        let e: Vec<f64> = points
            .iter()
            .zip(&items)
            .filter(|(_, item)| item.source == source)
            .filter_map(|(p, item)| Some(item.z_m? - w.terrain.height(p[0], p[1])?))
            .collect();
        Ok((rms(&e), e.len()))
    };
    let before = [errors(&h, Source::Window)?.0, errors(&h, Source::Aggregate)?.0];

    // A malformed correction changes nothing and says why.
    let mut bad = wire(&drift.inverse());
    bad.rotation_xyzw = [0.0, 0.0, 0.0, 3.0];
    let refused = h.client.correct(&[PoseCorrection::Transform {
        publisher_id: Some(4),
        from_stamp_ns: start,
        until_stamp_ns: u64::MAX,
        transform: bad,
    }]);
    assert_eq!(
        refused.map_err(error_code).err(),
        Some(ErrorCode::InvalidArgument)
    );

    // The loop closure: every scan of publisher 4 since the first moves by the drift's inverse.
    let reply = h.client.correct(&[PoseCorrection::Transform {
        publisher_id: Some(4),
        from_stamp_ns: start,
        until_stamp_ns: u64::MAX,
        transform: wire(&drift.inverse()),
    }])?;
    assert_eq!(
        (reply.window_maps_moved, reply.aggregate_scans_moved),
        (1, 5),
        "{reply:?}"
    );
    assert_eq!((reply.generation, reply.not_correctable), (1, 0));
    assert!(
        reply.cells_changed > 1000 && reply.tiles_refitted > 0,
        "{reply:?}"
    );
    for (k, source) in [Source::Window, Source::Aggregate].into_iter().enumerate() {
        let (after, n) = errors(&h, source)?;
        assert!(n >= 15, "{n} answers from {source:?}");
        assert!(
            after < 0.05 && after < 0.25 * before[k],
            "{source:?} RMSE {:.3} m before the correction, {after:.3} m after",
            before[k]
        );
    }
    let status = h.client.status()?;
    assert_eq!(status.corrections, 1);
    assert_eq!(status.aggregate.ledger_scans, 5);
    assert!(status.aggregate.ledger_mb > 0.0);
    Ok(())
}
