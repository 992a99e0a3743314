//! A huge request costs the daemon a bounded amount of memory: Zenoh's own reassembly limit,
//! set by the daemon just above the codec's 64 MiB, drops it fragment by fragment. A real child
//! process sends 512 MB (`RANGEGP_BIG_MB` to change); this test process is the daemon, and its
//! peak resident set (VmHWM, reset first through /proc/self/clear_refs) is compared with its
//! resident set at idle. Its own binary, so no other test's memory is counted.

use anyhow::{Context, Result};
use rangegp_lab::scangen::now_ns;
use rangegp_proto::codec::Encoding;
use rangegp_proto::keys::{MapKeys, QueryKind};
use rangegp_tests::child::{self, ChildProcess};
use rangegp_tests::{env_count, world, Harness, WAIT};
use rangegp_transport::{zenoh_config, zenoh_encoding};
use std::time::Duration;
use zenoh::Wait;

/// Child role: sends one request of `<mb>` megabytes, then a status query on the same link
/// (answered only after the big one was dealt with), and says `done` (`<endpoint> <map> <mb>`).
#[test]
#[ignore = "child process of the big-request test"]
fn child_big_request() -> Result<()> {
    let Some(args) = child::args() else { return Ok(()) };
    let mut parts = args.split(' ');
    let (endpoint, map, mb) = (
        parts.next().context("endpoint")?,
        parts.next().context("map id")?,
        parts.next().context("size")?.parse::<usize>()?,
    );
    let config = zenoh_config("client", &[], &[endpoint.to_owned()], false)?;
    let session = zenoh::open(config).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let keys = MapKeys::new(map)?;
    session
        .get(keys.query(QueryKind::Elevation))
        .payload(vec![7u8; mb << 20])
        .encoding(zenoh_encoding(Encoding::Bincode))
        .timeout(Duration::from_secs(30))
        .callback(|_| {})
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let replies = session
        .get(keys.status())
        .timeout(WAIT)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    replies
        .recv()
        .map_err(|e| anyhow::anyhow!("no status reply: {e}"))?;
    child::say("done");
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

/// A field of /proc/self/status, MiB.
fn proc_status_mb(field: &str) -> Result<f64> {
    let status = std::fs::read_to_string("/proc/self/status")?;
    let line = status
        .lines()
        .find(|l| l.starts_with(field))
        .with_context(|| format!("no {field} in /proc/self/status"))?;
    let kib: f64 = line.split_whitespace().nth(1).context("value")?.parse()?;
    Ok(kib / 1024.0)
}

#[test]
fn a_512_mb_request_costs_the_daemon_at_most_200_mb() -> Result<()> {
    let mb = env_count("RANGEGP_BIG_MB", 512);
    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(1)?;
    let scan = world(1, 1).scan(0, now_ns());
    publisher.publish(scan.header, &scan.points)?;
    h.wait_status("a map", |s| s.scans_accepted == 1)?;
    h.client.elevation(&[[3.0, 0.5]])?;

    std::fs::write("/proc/self/clear_refs", "5").context("resetting the peak resident set")?;
    let idle = proc_status_mb("VmRSS:")?;
    let mut sender = ChildProcess::spawn(
        "child_big_request",
        &format!("{} {} {mb}", h.endpoint, h.config.map_id),
    )?;
    sender.expect("done", Duration::from_secs(120))?;
    let peak = proc_status_mb("VmHWM:")?;
    let after = proc_status_mb("VmRSS:")?;
    sender.kill()?;
    eprintln!(
        "{mb} MB request: daemon RSS idle {idle:.1} MiB, peak {peak:.1} MiB (+{:.1}), after {after:.1} MiB",
        peak - idle
    );
    anyhow::ensure!(
        peak - idle <= 200.0,
        "a {mb} MB request raised the peak RSS by {:.1} MiB",
        peak - idle
    );
    anyhow::ensure!(after - idle <= 100.0, "{:.1} MiB not given back", after - idle);
    h.client.elevation(&[[3.0, 0.5]])?;
    Ok(())
}
