//! One client that stops reading its replies must not stall everybody else's batch queries.
//! A real child process asks for 24 large JSON grids (about 2.6 MB of reply each), blocks its
//! receive thread on the first reply and is then frozen with SIGSTOP. A healthy client's
//! 10 × 10 grids must all be answered within a (generous) timeout while the daemon works through
//! the frozen client's backlog; before the fix both query workers blocked in Zenoh's push for
//! ~5 s and the healthy grids timed out. The p50 / p99 of each phase, and the ratio of the p99
//! with the frozen client's replies undelivered to the p99 alone, are printed (`--nocapture`).

use anyhow::{Context, Result};
use rangegp_client::Client;
use rangegp_lab::scangen::now_ns;
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::keys::{MapKeys, QueryKind};
use rangegp_proto::msg::GridRequest;
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_tests::child::{self, ChildProcess};
use rangegp_tests::{world, Harness, WAIT};
use rangegp_transport::{zenoh_config, zenoh_encoding};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// Large grids asked by the slow client: about 60 MB of replies, more than loopback TCP buffers
/// hold (receive buffers grow to 32 MiB here while the first reply is read).
const SLOW_GRIDS: usize = 24;

/// Child role: a client that asks for large grids and never reads the replies
/// (`<endpoint> <map id>`).
#[test]
#[ignore = "child process of the slow-client test"]
fn child_slow_client() -> Result<()> {
    let Some(args) = child::args() else { return Ok(()) };
    let (endpoint, map) = args.split_once(' ').context("args: <endpoint> <map id>")?;
    let config = zenoh_config("client", &[], &[endpoint.to_owned()], false)?;
    let session = zenoh::open(config).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let key = MapKeys::new(map)?.query(QueryKind::Grid);
    // 512 × 512 cells where nothing is mapped: cheap to answer, about 3 MB of JSON each.
    let request = GridRequest {
        version: PROTOCOL_VERSION,
        min_m: [1000.0, 1000.0],
        max_m: [1064.0, 1064.0],
        resolution_m: 0.125,
        layers: Vec::new(),
        robot: None,
    };
    let payload = codec::encode(Encoding::Json, &request)?;
    for _ in 0..SLOW_GRIDS {
        session
            .get(&key)
            .payload(payload.clone())
            .encoding(zenoh_encoding(Encoding::Json))
            .timeout(Duration::from_secs(60))
            // A receive thread that blocks: the first reply stops all reading.
            .callback(|_reply| {
                child::say("replying");
                std::thread::park();
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

fn percentile(sorted: &[Duration], q: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Times `n` healthy 10 × 10 grids over the mapped area.
fn healthy_grids(client: &Client, n: usize) -> Result<Vec<Duration>> {
    let mut took = Vec::with_capacity(n);
    for _ in 0..n {
        let started = Instant::now();
        let grid = client.grid([0.0, -2.5], [5.0, 2.5], 0.5)?;
        took.push(started.elapsed());
        anyhow::ensure!(grid.cols == 10 && grid.rows == 10);
    }
    took.sort();
    Ok(took)
}

#[test]
fn a_frozen_client_does_not_stall_other_clients_batches() -> Result<()> {
    let h = Harness::start(|c| c.query.max_batch = 512 * 512)?;
    let mut publisher = h.publisher(9)?;
    let mut w = world(9, 4);
    for i in 0..4 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    h.wait_status("four scans", |s| s.scans_accepted == 4)?;
    // A healthy grid takes milliseconds; before the fix the frozen client held the workers for
    // about 5 s. The timeout lies far from both.
    let healthy = Client::builder(&h.config.map_id)
        .connect([h.endpoint.clone()])
        .timeout(Duration::from_secs(2))
        .open()?;
    healthy.wait_for_daemon(WAIT)?;
    let before = healthy_grids(&healthy, 200)?;

    // Grids the daemon has dealt with: answered (their latency recorded) or expired in the queue.
    let handled = |s: &rangegp_proto::msg::StatusReply| s.query_ms.grid.count + s.queries_expired;
    let before_slow = handled(&h.client.status()?);
    let mut slow = ChildProcess::spawn(
        "child_slow_client",
        &format!("{} {}", h.endpoint, h.config.map_id),
    )?;
    // The daemon is sending: the child's receive thread has blocked on the first grid.
    slow.expect("replying", WAIT)?;
    slow.stop()?;
    // While the daemon works through the frozen client's backlog (its grids are computed, its
    // replies cannot be delivered), every healthy grid is answered.
    let backlog = healthy_grids(&healthy, 40)?;
    // Then, with the frozen client's replies still undelivered (Zenoh closes its transport
    // only after 5 s), the healthy client's latency against its own baseline.
    h.wait_status("the frozen client's grids handled", |s| {
        handled(s) >= before_slow + SLOW_GRIDS as u64 + 40
    })?;
    let during = healthy_grids(&healthy, 200)?;
    let s = h.client.status()?;
    eprintln!(
        "healthy 10 × 10 grid: p50 {:?} / p99 {:?} alone; p50 {:?} / p99 {:?} behind the frozen \
         client's backlog; p50 {:?} / p99 {:?} with its replies undelivered (p99 × {:.2}); \
         replies dropped {}, grids expired in the queue {}",
        percentile(&before, 0.5),
        percentile(&before, 0.99),
        percentile(&backlog, 0.5),
        percentile(&backlog, 0.99),
        percentile(&during, 0.5),
        percentile(&during, 0.99),
        percentile(&during, 0.99).as_secs_f64() / percentile(&before, 0.99).as_secs_f64(),
        s.replies_dropped,
        s.queries_expired,
    );
    slow.kill()?;
    Ok(())
}
