//! The ROS 2 bridge against an independent DDS implementation: Eclipse Cyclone DDS's Python
//! binding (PyPI `cyclonedds`) publishes a simulated rover's PointCloud2 and Odometry under ROS
//! 2's topic and type names, the bridge (RustDDS) turns them into scans for a live daemon, and
//! Cyclone receives the bridge's GridMap and OccupancyGrid; both are checked cell by cell
//! against the daemon's own grid answer and the ground truth.
//!
//! DDS discovers by multicast, so the test runs in a network namespace it makes itself
//! (`unshare --net`): only `lo`, multicast on `lo`, nothing can reach a LAN. The outer test
//! makes the Python environment (it needs PyPI), then re-runs this binary's ignored child test
//! inside the namespace.

use anyhow::{ensure, Context, Result};
use rangegp_lab::replay::{self, record};
use rangegp_lab::scangen::{now_ns, GeneratedScan, ScanGenerator};
use rangegp_proto::msg::{GridReply, Layer};
use rangegp_ros2::config::{Reliability, RosConfig, ScansConfig};
use rangegp_ros2::{Bridge, BridgeConfig};
use rangegp_sim::ScannerPreset;
use rangegp_tests::child::{self, ChildProcess};
use rangegp_tests::{pyenv::venv_python, rms, tool_or_skip, Harness, TempDir, WAIT};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// Clouds in the recording.
const SCANS: usize = 8;

/// The lidar's mount on the base: x, y, z (m), roll, pitch, yaw (degrees).
const MOUNT: [f64; 6] = [0.3, -0.1, 0.6, 0.0, 2.0, 15.0];

/// Brings `lo` up with multicast and a multicast route in the new namespace, then runs the
/// command after it (`sh -c SCRIPT sh EXE ARGS...`).
const NETNS_SETUP: &str =
    "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec \"$@\"";

#[test]
fn the_ros2_bridge_exchanges_clouds_and_grids_with_cyclone_dds() -> Result<()> {
    let Some(python) = venv_python()? else {
        return Ok(());
    };
    for tool in ["unshare", "ip"] {
        if !tool_or_skip(tool, "the ROS 2 bridge test (its own network namespace)")? {
            return Ok(());
        }
    }
    let mut child = ChildProcess::spawn_under(
        &["unshare", "--net", "sh", "-c", NETNS_SETUP, "sh"],
        "ros2_bridge_child",
        &python.display().to_string(),
    )?;
    child.expect("done", 6 * WAIT)?;
    ensure!(
        child.wait_exit(WAIT)?,
        "the child test failed (its output is above)"
    );
    Ok(())
}

/// The Cyclone DDS peer (tests/python/ros2_peer.py), every stdout line heard.
fn peer(python: &Path, mcap: &Path, out: &Path, domain: u16) -> Result<ChildProcess> {
    let mut command = Command::new(python);
    command
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("python/ros2_peer.py"))
        .arg(mcap)
        .arg(out)
        .arg(domain.to_string());
    ChildProcess::run(command, false)
}

/// Longest wait for a line of the peer (its own waits are 30 s each).
const PEER_WAIT: Duration = Duration::from_secs(60);

/// A number of the peer's JSON.
fn num(v: &serde_json::Value) -> Result<f64> {
    v.as_f64().context("a number")
}

/// The GridMap layer `k` as (value or None) in grid_map's column-major order.
fn gm_layer(gm: &serde_json::Value, k: usize) -> Result<Vec<Option<f64>>> {
    gm["data"][k]["values"]
        .as_array()
        .context("layer values")?
        .iter()
        .map(|v| Ok(if v.is_null() { None } else { Some(num(v)?) }))
        .collect()
}

/// The reply's value of `layer` for each grid_map index (column-major, (0, 0) at the highest x
/// and y): what the bridge should have sent.
fn expected_layer(rep: &GridReply, name: &str) -> Result<Vec<Option<f64>>> {
    let values: Vec<Option<f64>> = match name {
        "elevation" => rep.elevation_m.iter().map(|v| v.map(f64::from)).collect(),
        "variance" => rep.variance_m2.iter().map(|v| v.map(f64::from)).collect(),
        "cost" => rep
            .costmap
            .iter()
            .map(|&c| (c >= 0).then_some(f64::from(c)))
            .collect(),
        other => {
            let layer = Layer::parse(other).context("a layer name")?;
            let v = rep.layer(layer).context("the layer in the reply")?;
            v.iter().map(|v| v.map(f64::from)).collect()
        }
    };
    let (nx, ny) = (rep.cols as usize, rep.rows as usize);
    let mut out = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            out.push(values[(ny - 1 - j) * nx + (nx - 1 - i)]);
        }
    }
    Ok(out)
}

#[test]
#[ignore = "run by the_ros2_bridge_exchanges_clouds_and_grids_with_cyclone_dds in its own network namespace"]
fn ros2_bridge_child() -> Result<()> {
    let Some(python) = child::args() else {
        return Ok(());
    };
    let python = PathBuf::from(python);
    // Nothing DDS sends can leave: the namespace has no interface but loopback.
    // (/proc/self/net is this namespace's; /sys/class/net would be the mount's.)
    let interfaces: Vec<String> = std::fs::read_to_string("/proc/self/net/dev")?
        .lines()
        .skip(2)
        .filter_map(|l| l.split(':').next())
        .map(|name| name.trim().to_owned())
        .collect();
    ensure!(
        interfaces == ["lo"],
        "not in a loopback-only namespace: {interfaces:?}"
    );

    // A VLP-16 on a rover, recorded as rosbag2 would (odometry of the base, organized clouds).
    let preset = ScannerPreset::by_name("vlp16").context("the vlp16 preset")?;
    let (max_range_m, noise) = (preset.max_range_m, preset.range_noise_per_m);
    let mut w = ScanGenerator::new(17, 100.0, preset, SCANS, 1.0);
    let t0 = now_ns() - 10_000_000_000;
    let scans: Vec<GeneratedScan> = (0..SCANS)
        .map(|i| w.scan(i, t0 + i as u64 * 500_000_000))
        .collect();
    let mount = replay::mount(&MOUNT)?;
    let tmp = TempDir::new("bridge")?;
    let mcap = tmp.path().join("drive.mcap");
    let rec = record::RecordOptions {
        sensor_to_base: mount,
        ..Default::default()
    };
    record::write(std::fs::File::create(&mcap)?, &scans, &rec)?;

    let h = Harness::start(|_| {})?;
    let config = BridgeConfig {
        map_id: h.config.map_id.clone(),
        connect: vec![h.endpoint.clone()],
        scans: ScansConfig {
            service: h.config.scan_service_name(),
            max_range_m,
            range_noise_per_m: noise,
            sensor_to_base: MOUNT,
            ..Default::default()
        },
        ros: RosConfig {
            domain_id: 17,
            only_networks: vec![std::net::Ipv4Addr::LOCALHOST.into()],
            cloud_reliability: Reliability::Reliable,
            ..Default::default()
        },
        grid: rangegp_ros2::config::GridConfig {
            rate_hz: 5.0,
            size_m: 16.0,
            resolution_m: 0.2,
            ..Default::default()
        },
    };
    let bridge = Bridge::start(config.clone())?;
    let out = tmp.path().join("peer.json");
    let mut peer = peer(&python, &mcap, &out, config.ros.domain_id)?;
    peer.expect("matched", PEER_WAIT)?;
    let published = peer.expect("published", PEER_WAIT)?;
    ensure!(published == format!("published {SCANS}"), "{published}");
    h.wait_status("every bridged scan accepted and fused", |s| {
        s.scans_accepted == SCANS as u64 && s.aggregate.inserts == SCANS as u64
    })?;
    // Every grid stamped after this instant shows the whole map.
    peer.tell(&format!("go {}", now_ns()))?;
    peer.expect("wrote", PEER_WAIT)?;
    let stats = bridge.stats();
    bridge.stop();
    eprintln!("bridge: {stats:?}");
    ensure!(stats.scans_published == SCANS as u64, "{stats:?}");
    ensure!(stats.skipped.is_empty(), "{stats:?}");

    let got: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out)?)?;
    let (gm, occ) = (&got["grid_map"], &got["occupancy"]);
    ensure!(
        gm["frame_id"] == "odom" && occ["frame_id"] == "odom",
        "frames: {got}"
    );
    let names: Vec<&str> = gm["layers"]
        .as_array()
        .context("layers")?
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    ensure!(
        names
            == [
                "elevation",
                "variance",
                "slope",
                "slope_sigma",
                "step",
                "risk",
                "cost"
            ],
        "{names:?}"
    );
    ensure!(gm["basic_layers"][0] == "elevation");

    // What the daemon answers for the grid the bridge asked (around the last odometry pose).
    let base = scans[SCANS - 1].pose * mount.inverse();
    let req = rangegp_ros2::bridge::grid_request(&config, base.translation.x, base.translation.y);
    let rep = h.client.grid_request(&req)?;
    let (nx, ny) = (rep.cols as usize, rep.rows as usize);
    ensure!((nx, ny) == (80, 80), "{nx} × {ny}");
    let dims = &gm["data"][0]["dims"];
    ensure!(
        dims[0][0] == "column_index" && num(&dims[0][1])? as usize == ny && num(&dims[1][1])? as usize == nx,
        "layout {dims}"
    );
    for (k, name) in names.iter().enumerate() {
        let sent = gm_layer(gm, k)?;
        let want = expected_layer(&rep, name)?;
        ensure!(sent.len() == want.len(), "{name}: {} values", sent.len());
        for (c, (s, w)) in sent.iter().zip(&want).enumerate() {
            let same = match (s, w) {
                (Some(a), Some(b)) => (a - b).abs() <= 1e-6 * b.abs().max(1.0),
                (None, None) => true,
                _ => false,
            };
            ensure!(
                same,
                "{name} at grid_map index {c}: sent {s:?}, the daemon says {w:?}"
            );
        }
    }
    let occupancy: Vec<i64> = occ["data"]
        .as_array()
        .context("occupancy data")?
        .iter()
        .filter_map(|v| v.as_i64())
        .collect();
    let costmap: Vec<i64> = rep.costmap.iter().map(|&c| i64::from(c)).collect();
    ensure!(
        occupancy == costmap,
        "the OccupancyGrid is the daemon's costmap, row-major from its origin"
    );
    ensure!(num(&occ["width"])? as usize == nx && num(&occ["height"])? as usize == ny);
    let res = rep.resolution_m;
    ensure!((num(&occ["origin"]["x"])? - (rep.origin_m[0] - 0.5 * res)).abs() < 1e-9);
    ensure!((num(&occ["origin"]["y"])? - (rep.origin_m[1] - 0.5 * res)).abs() < 1e-9);
    ensure!((num(&occ["resolution"])? - res).abs() < 1e-6);

    // Where grid_map puts each cell (from the centre, half the length less index + ½ cells,
    // rows towards −x, columns towards −y): on the centre of the daemon's cell whose value it
    // carries (checked above), so each value sits where the daemon measured it; and the
    // ground truth there.
    let elevation = gm_layer(gm, 0)?;
    let (cx, cy) = (num(&gm["pose"]["x"])?, num(&gm["pose"]["y"])?);
    let (lx, ly) = (num(&gm["length_x"])?, num(&gm["length_y"])?);
    let mut errors = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let at = [
                cx + 0.5 * lx - (i as f64 + 0.5) * res,
                cy + 0.5 * ly - (j as f64 + 0.5) * res,
            ];
            let centre = rep.centre((nx - 1 - i) as u32, (ny - 1 - j) as u32);
            ensure!(
                (at[0] - centre[0]).abs() < 1e-9 && (at[1] - centre[1]).abs() < 1e-9,
                "grid_map index ({i}, {j}) lies at {at:?}, its value is the daemon's at {centre:?}"
            );
            if let (Some(z), Some(t)) = (elevation[j * nx + i], w.terrain.height(at[0], at[1])) {
                errors.push(z - t);
            }
        }
    }
    let rmse = rms(&errors);
    eprintln!(
        "GridMap: {} of {} cells known; elevation RMSE against the truth {rmse:.4} m",
        errors.len(),
        nx * ny
    );
    ensure!(errors.len() * 2 >= nx * ny, "fewer than half the cells known");
    ensure!(rmse < 0.05, "RMSE {rmse} m");
    child::say("done");
    Ok(())
}
