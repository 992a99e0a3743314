//! `rangegp replay`: simulated scans recorded as a rosbag2 MCAP (PointCloud2 + Odometry + /tf in
//! ROS 2 CDR), fed to a daemon over iceoryx2, and the map it gives against the same scans sent
//! directly, both scored on the ground truth over Zenoh.

use clap::Parser;
use rangegp_client::ScanPublisher;
use rangegp_lab::replay::{self, record, Pace, PoseSource, ReplayOptions};
use rangegp_lab::scangen::{now_ns, GeneratedScan, ScanGenerator};
use rangegp_sim::ScannerPreset;
use rangegp_tests::{points_ahead, rms, Harness, TempDir};

/// Elevation RMSE against the truth at `points` and how many were answered.
fn score(h: &Harness, points: &[[f64; 2]], truth: impl Fn(&[f64; 2]) -> f64) -> anyhow::Result<(f64, usize)> {
    let items = h.client.elevation(points)?;
    let errors: Vec<f64> = points
        .iter()
        .zip(&items)
        .filter_map(|(p, i)| i.z_m.map(|z| z - truth(p)))
        .collect();
    Ok((rms(&errors), errors.len()))
}

/// Clap's parse of `rangegp replay FILE` with the daemon's service, then the test's settings;
/// the mount from the command line, or else from the recording's /tf_static.
fn options(file: &std::path::Path, h: &Harness, scan: &GeneratedScan, source: PoseSource) -> ReplayOptions {
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        options: ReplayOptions,
    }
    let file = file.display().to_string();
    let mut args = vec!["replay", &file, "--pace", "accepted"];
    if source == PoseSource::Odom {
        args.extend(["--sensor-to-base", "0.3", "-0.1", "0.6", "0", "2", "15"]);
    }
    let mut o = Cli::parse_from(args).options;
    o.service = h.config.scan_service_name();
    o.max_range_m = scan.header.max_range_m;
    o.range_noise_per_m = scan.header.range_noise_per_m;
    o.pose_source = source;
    o
}

#[test]
fn a_recorded_mcap_replayed_maps_as_well_as_the_scans_sent_directly() -> anyhow::Result<()> {
    const SCANS: usize = 6;
    // A VLP-16 (360°, its upper rings mostly sky: rows of NaN in the organized cloud).
    let preset = ScannerPreset::by_name("vlp16").expect("a preset");
    let rays = preset.ray_count();
    let mut w = ScanGenerator::new(17, 100.0, preset, SCANS, 1.0);
    // Recorded half a second apart, ending a few seconds ago (the daemon takes past stamps).
    let t0 = now_ns() - 10_000_000_000;
    let scans: Vec<GeneratedScan> = (0..SCANS)
        .map(|i| w.scan(i, t0 + i as u64 * 500_000_000))
        .collect();
    let tmp = TempDir::new("replay")?;
    let file = tmp.path().join("drive.mcap");
    let mount = replay::mount(&[0.3, -0.1, 0.6, 0.0, 2.0, 15.0])?;
    let rec = record::RecordOptions {
        sensor_to_base: mount,
        zstd: true,
        ..Default::default()
    };
    record::write(std::fs::File::create(&file)?, &scans, &rec)?;

    let topics = replay::list(&file)?;
    let names: Vec<(&str, &str, u64)> = topics
        .iter()
        .map(|t| (t.topic.as_str(), t.schema.as_str(), t.messages))
        .collect();
    assert_eq!(
        names,
        [
            ("/odom", "nav_msgs/msg/Odometry", SCANS as u64),
            ("/points", "sensor_msgs/msg/PointCloud2", SCANS as u64),
            ("/tf", "tf2_msgs/msg/TFMessage", SCANS as u64),
            ("/tf_static", "tf2_msgs/msg/TFMessage", 1),
        ]
    );

    let direct = Harness::start(|_| {})?;
    let mut publisher = ScanPublisher::new(&direct.config.scan_service_name(), 1, rays)?;
    for scan in &scans {
        direct.publish_fitted(&mut publisher, scan)?;
    }
    let poses: Vec<_> = scans
        .iter()
        .enumerate()
        .map(|(i, s)| (s.pose, w.path.waypoints[i][2]))
        .collect();
    let points = points_ahead(&poses);
    let fused = |s: &rangegp_proto::msg::StatusReply| s.aggregate.inserts == SCANS as u64;
    direct.wait_status("every scan fused", fused)?;
    let truth = |p: &[f64; 2]| w.terrain.height(p[0], p[1]).unwrap_or(f64::NAN);
    let (direct_rmse, direct_n) = score(&direct, &points, truth)?;

    for source in [PoseSource::Odom, PoseSource::Tf] {
        let h = Harness::start(|_| {})?;
        let opts = options(&file, &h, &scans[0], source);
        let summary = replay::run(&opts, Some(&h.client), |_| {})?;
        assert_eq!(
            (summary.clouds, summary.published, summary.skipped.len()),
            (SCANS as u64, SCANS as u64, 0),
            "{summary:?}"
        );
        let from = if source == PoseSource::Odom {
            "--sensor-to-base"
        } else {
            "/tf_static"
        };
        assert_eq!(summary.mount_from, from);
        let status = h.wait_status("every replayed scan accepted and fused", |s| {
            s.scans_accepted == SCANS as u64 && fused(s)
        })?;
        assert_eq!(status.scans_rejected, 0, "{status:?}");
        let (rmse, n) = score(&h, &points, truth)?;
        eprintln!(
            "{source:?}: replayed RMSE {rmse:.4} m ({n} answered), direct {direct_rmse:.4} m ({direct_n})"
        );
        assert!(
            rmse <= 1.2 * direct_rmse,
            "{source:?}: replayed RMSE {rmse} against {direct_rmse} sent directly"
        );
        assert!(
            10 * n >= 9 * direct_n,
            "{source:?}: {n} answered against {direct_n}"
        );
    }

    // A wrong topic or frame is a clear error, not an empty replay.
    let h = Harness::start(|_| {})?;
    let mut opts = options(&file, &h, &scans[0], PoseSource::Tf);
    opts.base_frame = "chassis".into();
    let err = replay::run(&opts, Some(&h.client), |_| {}).expect_err("no chassis frame in /tf");
    assert!(matches!(err, replay::ReplayError::NoPoses(_)), "{err}");
    // Odometry poses, but no /tf_static chain from a "mast" base to the lidar: the mount is
    // asked for, not taken as the identity.
    opts.base_frame = "mast".into();
    opts.pose_source = PoseSource::Odom;
    let err = replay::run(&opts, Some(&h.client), |_| {}).expect_err("no mount for mast");
    assert!(err.to_string().contains("--sensor-to-base"), "{err}");
    opts.cloud_topic = Some("/velodyne_points".into());
    let err = replay::run(&opts, Some(&h.client), |_| {}).expect_err("no such topic");
    assert!(err.to_string().contains("/velodyne_points"), "{err}");
    // Options that replay well, but a pace that waits on the daemon and no way to ask it.
    let opts = options(&file, &h, &scans[0], PoseSource::Tf);
    assert_eq!(opts.pace, Pace::Accepted);
    let err = replay::run(&opts, None, |_| {}).expect_err("accepted pace needs a client");
    assert!(
        matches!(&err, replay::ReplayError::Option(m) if m.contains("daemon's connection")),
        "{err}"
    );
    Ok(())
}
