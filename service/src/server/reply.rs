//! Sending a worker's reply without letting one client stall the workers.
//!
//! Zenoh sends a reply with the congestion control of the query, and a query's default is
//! `Block`: when a client stops reading, `reply().wait()` blocks until Zenoh closes that
//! transport (5 s by default). A worker that sent the reply itself would be blocked with it, and
//! every other client's batch would wait behind. So each worker reply is sent from a thread of
//! its own; at most [`MAX_IN_FLIGHT`] are under way at once (memory and threads stay bounded),
//! and a reply beyond that is dropped and counted (`replies_dropped`). The bound is shared: a
//! client that stops reading holds a slot per reply until Zenoh closes its transport, so only one
//! with that many batch queries outstanding at once can make other clients' replies drop (and
//! they then time out); docs/OPERATIONS.md "Queries under load".

use crate::metrics::Metrics;
use rangegp_proto::codec::Encoding;
use rangegp_transport::zenoh_encoding;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use tracing::{debug, warn};
use zenoh::query::Query;
use zenoh::Wait;

/// Replies being sent at once, at most (each holds its bytes: a 65 536-cell grid is ~1 MB in
/// bincode, ~3 MB in JSON).
pub const MAX_IN_FLIGHT: usize = 128;

/// What a reply carries.
#[derive(Debug)]
pub enum Outcome {
    /// An answer.
    Answer(Vec<u8>),
    /// An error reply (`reply_err`).
    Error(Vec<u8>),
}

/// Sends replies from threads of their own, bounded in number.
#[derive(Debug, Clone)]
pub struct ReplySender {
    in_flight: Arc<AtomicUsize>,
    metrics: Arc<Metrics>,
}

impl ReplySender {
    /// A sender counting into `metrics`.
    pub fn new(metrics: Arc<Metrics>) -> Self {
        Self {
            in_flight: Arc::new(AtomicUsize::new(0)),
            metrics,
        }
    }

    /// Sends `outcome` for `query` in `encoding` without blocking the caller; drops it (counted)
    /// when [`MAX_IN_FLIGHT`] replies are already under way or no thread can be started.
    pub fn send(&self, query: Query, key: String, encoding: Encoding, outcome: Outcome) {
        let taken = self
            .in_flight
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < MAX_IN_FLIGHT).then_some(n + 1)
            });
        if taken.is_err() {
            self.drop_reply("too many replies under way");
            return;
        }
        let slot = Slot(Arc::clone(&self.in_flight));
        let spawned = std::thread::Builder::new()
            .name("rangegp-reply".into())
            .spawn(move || {
                let _slot = slot;
                put(&query, &key, encoding, outcome);
            });
        if let Err(e) = spawned {
            self.drop_reply(&e.to_string());
        }
    }

    fn drop_reply(&self, why: &str) {
        let n = self.metrics.replies_dropped.fetch_add(1, Ordering::Relaxed) + 1;
        if n.is_power_of_two() {
            warn!(
                dropped = n,
                why, "reply dropped: a client is not reading its replies"
            );
        }
    }
}

/// One reply under way; its slot is given back when the sending thread ends, however it ends
/// (a panic included), or when the thread could not be started.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Hands `outcome` to Zenoh on the daemon's own `key` (blocking while the client's transport is
/// congested): a query over many maps (`rangegp/*/query/...`) learns which map answered.
pub fn put(query: &Query, key: &str, encoding: Encoding, outcome: Outcome) {
    let result = match outcome {
        Outcome::Answer(bytes) => query.reply(key, bytes).encoding(zenoh_encoding(encoding)).wait(),
        Outcome::Error(bytes) => query.reply_err(bytes).encoding(zenoh_encoding(encoding)).wait(),
    };
    if let Err(e) = result {
        debug!(error = %e, "reply not sent");
    }
}
