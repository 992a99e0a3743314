//! The Python package and examples work against a live daemon: a scan published from Python
//! through iceoryx2 (`rangegp.ScanPublisher`), a bare JSON query over Zenoh, a path planned over
//! the costmap, and the `rangegp` package's pytest suite.
//!
//! A recording the lab writes for `rangegp replay` is read by an independent ROS 2 MCAP
//! implementation (mcap-ros2-support), which writes it again with its own CDR encoder; the
//! replay of that file gives the same map.
//!
//! The virtual environment and its pinned packages: `rangegp_tests::pyenv`.

use rangegp_tests::child::{succeeded_within, ChildProcess};
use rangegp_tests::pyenv::venv_python;
use rangegp_tests::{Harness, WAIT};
use std::path::Path;
use std::process::{Command, Output};

/// The Python examples' directory.
fn examples() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/python")
}

/// Runs the planner-side example `script` against `h`'s daemon (its endpoint, map id and the
/// tests' timeout, then `args`); its output, once it has succeeded.
fn planner_example(python: &Path, script: &str, h: &Harness, args: &[&str]) -> anyhow::Result<Output> {
    let timeout = WAIT.as_secs().to_string();
    succeeded_within(
        Command::new(python)
            .arg(examples().join(script))
            .args([
                "--connect",
                &h.endpoint,
                "--map-id",
                &h.config.map_id,
                "--timeout",
                &timeout,
            ])
            .args(args),
        script,
    )
}

#[test]
fn python_publisher_and_python_planner_talk_to_the_daemon() -> anyhow::Result<()> {
    let Some(python) = venv_python()? else {
        return Ok(());
    };
    let examples = examples();
    let h = Harness::start(|_| {})?;

    // The publisher holds its sample until the daemon has it (a sample vanishes with its
    // publisher), then is told to go.
    let mut publish = Command::new(&python);
    publish.arg(examples.join("publish_scan.py")).args([
        "--service",
        &h.config.scan_service_name(),
        "--x",
        "2.0",
        "--y",
        "-1.0",
        "--heading",
        "0.4",
        "--until-stdin-closes",
    ]);
    let mut publisher = ChildProcess::run(publish, false)?;
    publisher.expect("published", WAIT)?;
    h.wait_status("the Python scan", |s| s.scans_accepted == 1)?;
    publisher.close_input();
    anyhow::ensure!(publisher.wait_exit(WAIT)?, "publish_scan.py failed");

    // Ahead of the sensor (observed) and far away (not observed).
    let out = planner_example(&python, "query_elevation.py", &h, &["7.0", "1.0", "40.0", "40.0"])?;
    let reply: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    let items = reply["items"].as_array().expect("items");
    assert_eq!(items.len(), 2);
    let z = items[0]["z_m"].as_f64().expect("observed z");
    let var = items[0]["z_var_m2"].as_f64().expect("variance");
    assert_eq!(items[0]["source"], "window");
    assert!(z.abs() < 0.01, "flat ground at 0 came back as {z}");
    assert!(var > 0.0);
    assert_eq!(items[1]["source"], "none");
    assert!(items[1]["z_m"].is_null());

    // A path over the cost layer of the flat ground ahead of the sensor.
    let out = planner_example(
        &python,
        "plan_path.py",
        &h,
        &[
            "--bbox", "4", "-2", "10", "4", "--res", "0.1", "--start", "5", "0", "--goal", "9", "2",
        ],
    )?;
    let plan: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    let path = plan["path_m"].as_array().expect("a path");
    let (first, last) = (&path[0], &path[path.len() - 1]);
    assert!(
        (first[0].as_f64().expect("x") - 5.0).abs() < 0.06,
        "starts at {first}"
    );
    assert!(
        (last[1].as_f64().expect("y") - 2.0).abs() < 0.06,
        "ends at {last}"
    );
    let length = plan["length_m"].as_f64().expect("length");
    let straight = (4f64).hypot(2.0);
    assert!(
        (straight - 0.1..straight * 1.15).contains(&length),
        "a {length} m path over flat ground for {straight} m"
    );
    assert!(
        plan["max_cost"].as_i64().expect("cost") < 50,
        "flat ground is free: {plan}"
    );
    Ok(())
}

#[test]
fn the_python_packages_pytest_suite_passes_against_a_live_daemon() -> anyhow::Result<()> {
    let Some(python) = venv_python()? else {
        return Ok(());
    };
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let h = Harness::start(|_| {})?;
    let out = succeeded_within(
        Command::new(&python)
            .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
            .arg(root.join("python/tests"))
            .env("RANGEGP_CONNECT", &h.endpoint)
            .env("RANGEGP_MAP_ID", &h.config.map_id)
            .env("RANGEGP_SERVICE", h.config.scan_service_name()),
        "pytest",
    )?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("5 passed") && !stdout.contains("skipped"),
        "every test of the suite ran: {stdout}"
    );
    Ok(())
}

#[test]
fn an_independent_ros2_mcap_implementation_reads_our_recordings_and_we_read_its() -> anyhow::Result<()> {
    use rangegp_lab::replay::{self, record, Pace, PoseSource, ReplayOptions};
    use rangegp_lab::scangen::{now_ns, ScanGenerator};
    use rangegp_sim::ScannerPreset;
    let Some(python) = venv_python()? else {
        return Ok(());
    };
    let preset = ScannerPreset::by_name("vlp16").expect("a preset");
    let mut w = ScanGenerator::new(23, 100.0, preset, 3, 1.0);
    let t0 = now_ns() - 5_000_000_000;
    let scans: Vec<_> = (0..3).map(|i| w.scan(i, t0 + i as u64 * 500_000_000)).collect();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/pyenv");
    let ours = dir.join(format!("{}.mcap", rangegp_tests::unique_id("ours")));
    let theirs = dir.join(format!("{}.mcap", rangegp_tests::unique_id("theirs")));
    let mount = replay::mount(&[0.1, 0.0, 0.5, 0.0, 0.0, -30.0])?;
    let opts = record::RecordOptions {
        sensor_to_base: mount,
        zstd: true,
        ..Default::default()
    };
    record::write(std::fs::File::create(&ours)?, &scans, &opts)?;
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/reencode_mcap.py");
    let out = succeeded_within(
        Command::new(&python).arg(script).arg(&ours).arg(&theirs),
        "reencode_mcap.py",
    )?;
    let read: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    assert_eq!(
        read["topics"],
        serde_json::json!({"/points": 3, "/odom": 3, "/tf": 3, "/tf_static": 1})
    );
    let first = record::cloud_of(&scans[0], "lidar");
    let cloud = &read["cloud"];
    assert_eq!(cloud["height"], first.height);
    assert_eq!(cloud["width"], first.width);
    assert_eq!(cloud["bytes"], first.data.len());
    assert_eq!(cloud["frame_id"], "lidar");
    assert_eq!(cloud["stamp_ns"], t0);
    let fields: Vec<(String, u32, u8)> = first
        .fields
        .iter()
        .map(|f| (f.name.clone(), f.offset, f.datatype))
        .collect();
    assert_eq!(cloud["fields"], serde_json::to_value(&fields)?);
    let base = scans[0].pose * mount.inverse();
    let odom = &read["odom_first"];
    for (k, v) in base.translation.vector.iter().enumerate() {
        assert!((odom[k].as_f64().unwrap_or(f64::NAN) - v).abs() < 1e-12, "{odom}");
    }
    assert_eq!(odom[3], "base_link");
    assert_eq!(read["tf_first"][0], "odom");
    assert_eq!(read["tf_first"][1], "base_link");

    // Both files, replayed into two daemons, give the same answers.
    let mut answers = Vec::new();
    for file in [&ours, &theirs] {
        let h = Harness::start(|_| {})?;
        let o = ReplayOptions {
            file: file.clone(),
            list: false,
            cloud_topic: None,
            odom_topic: None,
            pose_source: PoseSource::Odom,
            tf_topic: "/tf".into(),
            base_frame: "base_link".into(),
            sensor_to_base: None,
            max_range_m: scans[0].header.max_range_m,
            range_noise_per_m: scans[0].header.range_noise_per_m,
            service: h.config.scan_service_name(),
            publisher_id: 5,
            max_points: 65_536,
            pace: Pace::Accepted,
            speed: 1.0,
            accept_timeout_s: WAIT.as_secs_f64(),
        };
        let summary = replay::run(&o, Some(&h.client), |_| {})?;
        assert_eq!((summary.published, summary.skipped.len()), (3, 0), "{summary:?}");
        assert_eq!(
            summary.mount_from, "/tf_static",
            "the mount read back from /tf_static"
        );
        h.wait_status("3 scans fused", |s| {
            s.scans_accepted == 3 && s.aggregate.inserts == 3
        })?;
        let s = scans[2].pose.translation.vector;
        let points: Vec<[f64; 2]> = (0..60)
            .map(|k| {
                let a = k as f64 * 0.105;
                let r = 3.0 + (k % 7) as f64;
                [s.x + r * a.cos(), s.y + r * a.sin()]
            })
            .collect();
        answers.push(h.client.elevation(&points)?);
    }
    let answered = answers[0].iter().filter(|a| a.z_m.is_some()).count();
    assert!(answered >= 50, "{answered} of 60 answered");
    for (a, b) in answers[0].iter().zip(&answers[1]) {
        assert_eq!(a.z_m.is_some(), b.z_m.is_some());
        if let (Some(x), Some(y)) = (a.z_m, b.z_m) {
            assert!((x - y).abs() < 1e-9, "{x} against {y}");
        }
    }
    std::fs::remove_file(&ours)?;
    std::fs::remove_file(&theirs)?;
    Ok(())
}
