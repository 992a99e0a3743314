//! Views over the real transports: a range image from a pose no scan was taken at, answered
//! from the window and the aggregate, against the simulator's exact ray caster; bad views are
//! refused with a reason; an old client is refused by version.

use nalgebra::{UnitQuaternion, Vector3};
use rangegp_client::ClientError;
use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{Camera, ErrorCode, Provenance, Source, ViewRequest};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_tests::{rms, world, Harness};

#[test]
fn a_view_from_a_pose_never_visited_sees_the_ground_truth() -> anyhow::Result<()> {
    let h = Harness::start(|c| c.window.capacity = 2)?;
    let mut publisher = h.publisher(41)?;
    let mut w = world(23, 6);
    let scans: Vec<_> = (0..6).map(|i| w.scan(i, now_ns())).collect();
    for scan in &scans {
        h.publish_fitted(&mut publisher, scan)?;
    }
    h.wait_status("every scan fused", |s| s.aggregate.inserts == 6)?;
    // Between the first two poses, half a metre aside, looking the way the robot drove: ground
    // the first scans saw, which only the aggregate still holds.
    let (p0, p1) = (scans[0].pose.translation.vector, scans[1].pose.translation.vector);
    let heading = w.path.waypoints[0][2];
    let side = Vector3::new(-heading.sin(), heading.cos(), 0.0);
    let position = (p0 + p1) / 2.0 + 0.5 * side;
    let q = UnitQuaternion::from_euler_angles(0.0, 0.0, heading);
    let elevations: Vec<f64> = (0..8).map(|k| (-4.0 - 2.0 * k as f64).to_radians()).collect();
    let columns = 72;
    let req = ViewRequest {
        version: PROTOCOL_VERSION,
        position_m: position.into(),
        orientation_xyzw: [q.i, q.j, q.k, q.w],
        camera: Camera::Lidar {
            ring_elevations_rad: elevations.clone(),
            columns,
            max_range_m: 12.0,
        },
    };
    let rep = h.client.view(&req)?;
    assert_eq!((rep.rows, rep.cols), (8, columns));
    let (mut errors, mut within, mut hits) = (Vec::new(), 0, 0);
    for (k, range) in rep.range_m.iter().enumerate() {
        let (row, col) = (k / columns as usize, k % columns as usize);
        let Some(r) = range else { continue };
        hits += 1;
        assert_ne!(rep.source[k], Source::None);
        assert_ne!(rep.provenance[k], Provenance::None);
        let (e, a) = (
            elevations[row],
            std::f64::consts::TAU * col as f64 / columns as f64,
        );
        let dir = q * Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
        let Some(truth) = w.terrain.cast(position, dir, 12.0) else {
            continue;
        };
        let err = f64::from(*r) - truth;
        let sd = rep.sigma_m[k].map_or(f64::INFINITY, f64::from);
        within += usize::from(err.abs() <= 3.0 * sd + 0.02);
        errors.push(err);
    }
    assert!(hits >= 100, "only {hits} of {} pixels hit", rep.range_m.len());
    assert!(
        rep.source.contains(&Source::Aggregate),
        "the aggregate answers where the window does not see"
    );
    let n = errors.len();
    assert!(
        within as f64 >= 0.9 * n as f64,
        "{within} of {n} ranges within 3 σ of the truth"
    );
    let mut abs: Vec<f64> = errors.iter().map(|e| e.abs()).collect();
    abs.sort_by(f64::total_cmp);
    assert!(
        abs[n / 2] < 0.05,
        "median range error {} m (RMS {})",
        abs[n / 2],
        rms(&errors)
    );
    Ok(())
}

#[test]
fn bad_views_and_old_clients_are_refused_with_a_reason() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let camera = Camera::Pinhole {
        width: 4,
        height: 3,
        hfov_rad: 1.0,
        max_range_m: 10.0,
    };
    let mut req = ViewRequest {
        version: PROTOCOL_VERSION,
        position_m: [0.0, 0.0, 1.0],
        orientation_xyzw: [0.0, 0.0, 0.0, 2.0],
        camera,
    };
    let refused = |r: Result<_, ClientError>| match r {
        Err(ClientError::Server { code, message }) => (code, message),
        other => panic!("expected a refusal, got {other:?}"),
    };
    let (code, message) = refused(h.client.view(&req));
    assert_eq!(code, ErrorCode::InvalidArgument);
    assert!(message.contains("unit quaternion"), "{message}");
    req.orientation_xyzw = [0.0, 0.0, 0.0, 1.0];
    req.version = PROTOCOL_VERSION - 1;
    let (code, _) = refused(h.client.view(&req));
    assert_eq!(code, ErrorCode::UnsupportedVersion);
    // A valid view of an empty map: every pixel unknown, none claims free space.
    req.version = PROTOCOL_VERSION;
    match h.client.view(&req) {
        Ok(rep) => {
            assert_eq!(rep.range_m.len(), 12);
            assert_eq!(rep.hit_probability.len(), 12);
            assert!(rep.hit_probability.iter().all(Option::is_none));
        }
        Err(ClientError::Server { code, .. }) => assert_eq!(code, ErrorCode::NoMap),
        Err(e) => return Err(e.into()),
    }
    Ok(())
}
