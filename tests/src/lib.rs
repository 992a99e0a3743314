//! Shared harness for rangegp's end-to-end tests: a daemon on its own loopback endpoint and its
//! own iceoryx2 service, a client, a publisher, and bounded waits. No mocks: real transports.

pub mod child;
pub mod pyenv;

use anyhow::{bail, Result};
use rangegp_client::{Client, ScanPublisher};
use rangegp_lab::scangen::{GeneratedScan, ScanGenerator};
use rangegp_proto::msg::StatusReply;
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_sim::ScannerPreset;
use rangegp_transport::reserve_loopback_endpoint;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// Upper bound of every wait in the tests.
pub const WAIT: Duration = Duration::from_secs(20);

/// A name no other test (or test run) uses: process id, a counter and the clock.
pub fn unique_id(prefix: &str) -> String {
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    format!(
        "{prefix}_{}_{}_{nanos}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    )
}

/// A directory of its own under the system's temporary directory, removed with everything in it
/// when dropped: on a failed assertion or an early `?` too, so that no run leaves files behind.
pub struct TempDir(PathBuf);

impl TempDir {
    /// Creates `<temp>/<unique id with prefix>`.
    pub fn new(prefix: &str) -> Result<Self> {
        let dir = std::env::temp_dir().join(unique_id(prefix));
        std::fs::create_dir_all(&dir)?;
        Ok(Self(dir))
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Whether `program` runs (`program --version`). Without it a test is skipped where it runs by
/// hand (and says so) but fails under CI (`CI` set), so that CI never passes it silently.
pub fn tool_or_skip(program: &str, exercised: &str) -> Result<bool> {
    if std::process::Command::new(program)
        .arg("--version")
        .output()
        .is_ok()
    {
        return Ok(true);
    }
    anyhow::ensure!(
        std::env::var_os("CI").is_none(),
        "{program} is required in CI ({exercised})"
    );
    eprintln!("SKIPPED: {program} not found; {exercised} was not exercised");
    Ok(false)
}

/// A running daemon with a connected client.
pub struct Harness {
    /// The daemon (dropped last).
    pub daemon: Daemon,
    /// A client connected to it over loopback Zenoh.
    pub client: Client,
    /// Its configuration (endpoint, service name, map id).
    pub config: Config,
    /// The loopback endpoint it listens on.
    pub endpoint: String,
}

impl Harness {
    /// Starts a daemon with unique names, letting `tweak` adjust the configuration first.
    pub fn start(tweak: impl FnOnce(&mut Config)) -> Result<Self> {
        let reserved = reserve_loopback_endpoint()?;
        let endpoint = reserved.endpoint().to_owned();
        let mut config = Config {
            map_id: unique_id("t"),
            ..Config::default()
        };
        config.zenoh.listen = vec![endpoint.clone()];
        config.ingest.service_name = format!("rangegp/{}/scans", unique_id("svc"));
        config.metrics.listen = "127.0.0.1:0".into();
        tweak(&mut config);
        // Checkpoints only where a test names its own directory: never in the user's state
        // directory.
        if config.checkpoint.dir.is_none() {
            config.checkpoint.enabled = false;
        }
        let daemon = Daemon::builder(config.clone()).start()?;
        drop(reserved);
        let client = Client::builder(&config.map_id)
            .connect([endpoint.clone()])
            .timeout(WAIT)
            .open()?;
        client.wait_for_daemon(WAIT)?;
        Ok(Self {
            daemon,
            client,
            config,
            endpoint,
        })
    }

    /// A publisher on this daemon's scan service.
    pub fn publisher(&self, publisher_id: u64) -> Result<ScanPublisher> {
        Ok(ScanPublisher::new(
            &self.config.scan_service_name(),
            publisher_id,
            4096,
        )?)
    }

    /// Publishes `scan` and waits (bounded) until the daemon has fitted it. The intake is
    /// newest-wins by design, so a test about N maps publishes them one at a time.
    pub fn publish_fitted(&self, publisher: &mut ScanPublisher, scan: &GeneratedScan) -> Result<()> {
        let before = self.client.status()?.scans_accepted;
        publisher.publish(scan.header, &scan.points)?;
        self.wait_status("the scan fitted", |s| s.scans_accepted > before)?;
        Ok(())
    }

    /// Polls status until `done` holds (bounded by [`WAIT`]).
    pub fn wait_status(&self, what: &str, done: impl Fn(&StatusReply) -> bool) -> Result<StatusReply> {
        let deadline = Instant::now() + WAIT;
        loop {
            let s = self.client.status()?;
            if done(&s) {
                return Ok(s);
            }
            if Instant::now() > deadline {
                bail!("timed out waiting for {what}; last status: {s:?}");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// 20 points in front of each (sensor pose, heading), 3.5–7.5 m away over ±70°: inside the
/// seed-000 scanner's field of view.
pub fn points_ahead(poses: &[(nalgebra::Isometry3<f64>, f64)]) -> Vec<[f64; 2]> {
    let mut points = Vec::with_capacity(20 * poses.len());
    for (pose, heading) in poses {
        let s = pose.translation.vector;
        for k in 0..20 {
            let az = heading + (-70.0 + 7.0 * k as f64).to_radians();
            let rho = 3.5 + (k % 5) as f64;
            points.push([s.x + rho * az.cos(), s.y + rho * az.sin()]);
        }
    }
    points
}

/// The seed-000 world used by the tests: 60 m cratered terrain, scans 1 m apart.
pub fn world(seed: u64, scans: usize) -> ScanGenerator {
    ScanGenerator::new(seed, 60.0, ScannerPreset::seed000(), scans, 1.0)
}

/// The `i`-th index of a walk forth and back over `n` waypoints (0, 1, …, n−1, n−2, …, 1, 0, …):
/// a publisher replaying a short path this way never jumps, as a real robot never does (a jump
/// from the last waypoint to the first would be rejected `implausible_pose`).
pub fn ping_pong(i: usize, n: usize) -> usize {
    if n < 2 {
        return 0;
    }
    let k = i % (2 * n - 2);
    if k < n {
        k
    } else {
        2 * n - 2 - k
    }
}

/// A test size from the environment variable `var` (long variants), `default` otherwise.
pub fn env_count(var: &str, default: usize) -> usize {
    std::env::var(var)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Root mean square.
pub fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|e| e * e).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// The error code of a query the daemon refused (panics on any other failure: the test's premise).
pub fn error_code(e: rangegp_client::ClientError) -> rangegp_proto::msg::ErrorCode {
    match e {
        rangegp_client::ClientError::Server { code, .. } => code,
        other => panic!("expected a server error, got {other}"),
    }
}
