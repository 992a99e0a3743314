//! End-to-end: scans in over iceoryx2, queries out over Zenoh, against ground truth.

use nalgebra::Vector3;
use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{Provenance, Ray, Source};
use rangegp_tests::{points_ahead, rms, world, Harness};

#[test]
fn five_scans_in_elevation_out_matches_ground_truth() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(1)?;
    let mut w = world(3, 5);
    let mut poses = Vec::new();
    for i in 0..5 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
        poses.push((scan.pose, w.path.waypoints[i][2]));
    }
    let status = h.wait_status("5 accepted scans", |s| s.scans_accepted == 5)?;
    assert_eq!(status.scans_rejected, 0);
    assert_eq!(status.window_len, 5);

    // Points in front of each pose, inside the scanner's field of view.
    let points = points_ahead(&poses);
    let items = h.client.elevation(&points)?;
    let (mut errors, mut observed) = (Vec::new(), 0);
    for (p, item) in points.iter().zip(&items) {
        if item.z_m.is_none() {
            continue;
        }
        // Where no window map sees the point (a shadow), the aggregate may: both are maps.
        assert!(
            matches!(item.source, Source::Window | Source::Aggregate),
            "{item:?}"
        );
        let (z, var) = (item.z_m.expect("z"), item.z_var_m2.expect("variance"));
        assert!(var > 0.0, "σ must be positive");
        // Per-axis σ of the surface point along the answering sensor's ray: finite, and for a
        // window map not all vertical (the ray is slanted); graded provenance.
        let sd = item.point_sigma_m.expect("per-axis σ with every value");
        assert!(sd.iter().all(|v| v.is_finite() && *v >= 0.0), "{item:?}");
        if item.source == Source::Window {
            assert!(sd[0] + sd[1] > 0.0, "{item:?}");
        }
        assert_ne!(item.provenance, Provenance::None, "{item:?}");
        observed += usize::from(item.provenance == Provenance::Observed);
        errors.push(z - w.terrain.height(p[0], p[1]).expect("on the map"));
    }
    assert!(errors.len() >= 80, "only {} of 100 points observed", errors.len());
    // 3.5–7.5 m ahead of the sensors, among their returns: mostly observed.
    assert!(
        2 * observed >= errors.len(),
        "{observed} of {} answers observed",
        errors.len()
    );
    let e = rms(&errors);
    assert!(e < 0.05, "elevation RMSE {e}");
    // Far from every scan: honestly unanswered, never a silent prior.
    let far = h.client.elevation(&[[25.0, -25.0]])?;
    assert_eq!((far[0].source, far[0].z_m), (Source::None, None));
    Ok(())
}

#[test]
fn ray_from_a_pose_never_visited_meets_the_ground_truth() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(9)?;
    let mut w = world(5, 3);
    let mut last = None;
    for i in 0..3 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
        last = Some((scan.pose, w.path.waypoints[i][2]));
    }
    h.wait_status("3 accepted scans", |s| s.scans_accepted == 3)?;
    let (pose, heading) = last.expect("scans");
    let s = pose.translation.vector;
    // An origin 0.6 m to the side and 0.5 m above the last sensor: no scan was taken there.
    let side = Vector3::new(-heading.sin(), heading.cos(), 0.0);
    let origin = s + side * 0.6 + Vector3::new(0.0, 0.0, 0.5);
    let mut rays = Vec::new();
    let mut truths = Vec::new();
    for k in 0..9 {
        let az = heading + (-40.0 + 10.0 * k as f64).to_radians();
        let dir = Vector3::new(az.cos(), az.sin(), -0.3).normalize();
        if let Some(t) = w.terrain.cast(origin, dir, 9.0) {
            rays.push(Ray {
                origin_m: origin.into(),
                direction: dir.into(),
                max_range_m: 9.0,
            });
            truths.push(t);
        }
    }
    assert!(rays.len() >= 6);
    let items = h.client.ray(&rays)?;
    let mut errors = Vec::new();
    for (item, truth) in items.iter().zip(&truths) {
        let r = item.range_m.expect("hit predicted");
        assert!(item.hit_probability.is_some_and(|p| p > 0.9), "{item:?}");
        assert!(item.range_var_m2.expect("variance") > 0.0);
        errors.push(r - truth);
    }
    let e = rms(&errors);
    assert!(e < 0.1, "ray range RMSE {e}");
    Ok(())
}

#[test]
fn online_hyperparameters_are_learned_off_the_ingest_path() -> anyhow::Result<()> {
    let h = Harness::start(|c| c.gp.online.enabled = true)?;
    let start = h.client.status()?.hyperparameters;
    let mut publisher = h.publisher(3)?;
    let mut w = world(12, 6);
    for i in 0..6 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    let s = h.wait_status("six scans and at least one hyperparameter update", |s| {
        s.scans_accepted == 6 && s.hyperparameter_updates >= 1
    })?;
    let learned = s.hyperparameters;
    assert!(learned.variance != start.variance && learned.length_scale != start.length_scale);
    // The likelihood optimum on this terrain lies well inside the configured bounds
    // (σ² in [1e-6, 10] of the amplitude-scaled residual, ℓ in [0.01, 50] m).
    let inside = learned.length_scale > 0.05
        && learned.length_scale < 20.0
        && learned.variance > 1e-5
        && learned.variance < 1.0;
    assert!(inside, "learned {learned:?} from {start:?}");
    Ok(())
}

#[test]
fn a_sweep_taken_while_driving_and_turning_is_deskewed_and_a_nonsense_twist_is_refused() -> anyhow::Result<()>
{
    use rand::SeedableRng;
    use rangegp_lab::eval::world::issue_motion;
    use rangegp_lab::scangen::{to_message, with_motion};
    use rangegp_proto::scan::ScanHeader;
    use rangegp_sim::{simulate_sweep, ScannerPreset};

    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(4)?;
    let w = world(7, 2);
    let preset = ScannerPreset::vlp16();
    let pose = w.path.pose(&w.terrain, 0, preset.mount_height_m);
    let motion = issue_motion();
    let rays = simulate_sweep(
        &w.terrain,
        &pose,
        &preset,
        &motion,
        &mut rand_pcg::Pcg64::seed_from_u64(1),
    );
    let (header, points) = to_message(&preset, &pose, &rays, now_ns());
    assert!(
        points.iter().any(|p| p.time_offset_ns > 90_000_000),
        "the sweep's last columns fire late"
    );
    let header = with_motion(header, &motion);
    let before = h.client.status()?.scans_accepted;
    publisher.publish(header, &points)?;
    h.wait_status("the sweep fitted", |s| s.scans_accepted > before)?;

    // All around the sensor, 3–12 m, where the sweep's start and end meet too.
    let s = pose.translation.vector;
    let points_xy: Vec<[f64; 2]> = (0..72)
        .map(|k| {
            let (az, rho) = ((5.0 * k as f64).to_radians(), 3.0 + (k % 10) as f64);
            [s.x + rho * az.cos(), s.y + rho * az.sin()]
        })
        .collect();
    let items = h.client.elevation(&points_xy)?;
    let errors: Vec<f64> = points_xy
        .iter()
        .zip(&items)
        .filter_map(|(p, item)| Some(item.z_m? - w.terrain.height(p[0], p[1])?))
        .collect();
    assert!(errors.len() >= 50, "only {} of 72 answered", errors.len());
    let e = rms(&errors);
    assert!(e < 0.05, "elevation RMSE {e}");

    // A twist no sensor has: refused and counted under its own reason.
    let bad = ScanHeader {
        wz_radps: f64::NAN,
        ..header
    };
    publisher.publish(bad, &points)?;
    let status = h.wait_status("invalid_motion counted", |s| {
        s.rejections
            .iter()
            .any(|r| r.reason == "invalid_motion" && r.count == 1)
    })?;
    assert_eq!(status.scans_accepted, before + 1);
    Ok(())
}
