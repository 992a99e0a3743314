//! The one interruptible sleep of the daemon's background threads (aggregate pacing, checkpoint
//! interval, ingest retries): a thread waiting for its next turn still stops within 50 ms of
//! shutdown. Its own module so that every thread's module can use it without depending on the
//! daemon that wires them.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Sleeps until `until` or until `shutdown` is set, whichever comes first (checked every 50 ms).
pub(crate) fn sleep_until(until: Instant, shutdown: &AtomicBool) {
    while !shutdown.load(Ordering::Relaxed) && Instant::now() < until {
        std::thread::sleep(
            until
                .saturating_duration_since(Instant::now())
                .min(Duration::from_millis(50)),
        );
    }
}
