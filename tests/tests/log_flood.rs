//! Per-scan events at sensor rate are summarised, not logged one line each: scans published
//! back to back, far faster than they can be fitted, are mostly skipped (newest wins), and the
//! daemon's WARN lines about it stay a handful. Its own binary: it installs the global tracing
//! subscriber that counts them.

use anyhow::Result;
use rangegp_lab::scangen::{now_ns, GeneratedScan};
use rangegp_proto::scan::ScanHeader;
use rangegp_tests::{ping_pong, world, Harness};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::{Context, SubscriberExt};
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

/// Counts the daemon's WARN events.
struct WarnCount(Arc<AtomicU64>);

impl<S: Subscriber> Layer<S> for WarnCount {
    fn on_event(&self, event: &Event<'_>, _: Context<'_, S>) {
        let m = event.metadata();
        if *m.level() == Level::WARN && m.target().starts_with("rangegp") {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[test]
fn skipped_scans_are_logged_as_a_summary_not_one_line_each() -> Result<()> {
    let warnings = Arc::new(AtomicU64::new(0));
    tracing_subscriber::registry()
        .with(WarnCount(Arc::clone(&warnings)))
        .init();
    let h = Harness::start(|c| c.ingest.queue_len = 1)?;
    let started = std::time::Instant::now();
    let mut publisher = h.publisher(2)?;
    let mut w = world(2, 8);
    let scans: Vec<GeneratedScan> = (0..8).map(|i| w.scan(i, 0)).collect();
    let n = 300u64;
    for i in 0..n {
        let scan = &scans[ping_pong(i as usize, scans.len())];
        let header = ScanHeader {
            stamp_ns: now_ns(),
            ..scan.header
        };
        publisher.publish(header, &scan.points)?;
        // Stay inside the subscriber's buffer (8): iceoryx2 would overwrite the oldest sample.
        if (i + 1) % 6 == 0 || i + 1 == n {
            h.wait_status("the daemon to take the batch", |s| s.scans_received == i + 1)?;
        }
    }
    let s = h.wait_status("every scan fitted or skipped", |s| {
        s.scans_accepted + s.scans_skipped == n
    })?;
    let lines = warnings.load(Ordering::Relaxed);
    // One summary line per 5 s at most, the first at once.
    let allowed = 1 + started.elapsed().as_secs() / 5;
    eprintln!("{} of {n} scans skipped, {lines} WARN lines", s.scans_skipped);
    assert!(
        s.scans_skipped >= 50,
        "the premise: most scans skipped ({})",
        s.scans_skipped
    );
    assert!(
        lines <= allowed,
        "{lines} WARN lines for {} skipped scans (at most {allowed})",
        s.scans_skipped
    );
    Ok(())
}
