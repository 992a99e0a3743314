//! The Zenoh query server: queryables for elevation, variance, ray, grid and status, a
//! liveliness token, and a bounded worker pool so that query load never touches ingest and
//! overload is answered (`overloaded`) instead of timing out. Requests of a few points are
//! answered on the Zenoh callback directly (bounded work, no hand-off, never behind a batch).
//! `rangegp/<map>/echo` returns the request's bytes from the callback: the transport floor.

pub mod corrections;
pub mod handler;
pub mod reply;

use crate::state::DaemonState;
use handler::Endpoint;
use rangegp_proto::codec::{self, Encoding, MAX_DECODE_BYTES};
use rangegp_proto::keys::QueryKind;
use rangegp_proto::msg::{ErrorCode, ErrorReply};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_transport::protocol_encoding;
use reply::{Outcome, ReplySender};
use std::panic::AssertUnwindSafe;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Instant;
use thiserror::Error;
use tracing::{error, info, warn};
use zenoh::query::Query;
use zenoh::Wait;

/// The server could not start.
#[derive(Debug, Error)]
pub enum ServerError {
    /// A queryable or the liveliness token could not be declared.
    #[error("cannot declare {what}")]
    Declare {
        /// Key expression.
        what: String,
        /// Zenoh's error.
        #[source]
        source: zenoh::Error,
    },
    /// A worker thread could not be spawned.
    #[error("cannot spawn a query worker")]
    Spawn(#[from] std::io::Error),
}

/// A query waiting for a worker, with when it was queued.
type Job = (Endpoint, Query, Instant);

/// Running queryables and workers; dropping it undeclares everything and joins the workers.
pub struct QueryServer {
    queryables: Vec<zenoh::query::Queryable<()>>,
    token: Option<zenoh::liveliness::LivelinessToken>,
    sender: Option<SyncSender<Job>>,
    workers: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for QueryServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QueryServer")
            .field("workers", &self.workers.len())
            .finish()
    }
}

impl QueryServer {
    /// Declares the queryables on `session` and starts `workers` threads with a queue of
    /// `queue_len` pending queries.
    pub fn start(
        session: &zenoh::Session,
        state: Arc<DaemonState>,
        workers: usize,
        queue_len: usize,
    ) -> Result<Self, ServerError> {
        let (sender, receiver) = sync_channel::<Job>(queue_len);
        let receiver = Arc::new(Mutex::new(receiver));
        let replies = ReplySender::new(Arc::clone(&state.metrics));
        let mut handles = Vec::with_capacity(workers);
        for i in 0..workers.max(1) {
            let (rx, st, replies) = (Arc::clone(&receiver), Arc::clone(&state), replies.clone());
            handles.push(
                std::thread::Builder::new()
                    .name(format!("rangegp-query-{i}"))
                    .spawn(move || worker(&rx, &st, &replies))?,
            );
        }
        let mut endpoints: Vec<(String, Endpoint)> = QueryKind::ALL
            .iter()
            .map(|&k| (state.keys.query(k), Endpoint::Query(k)))
            .collect();
        endpoints.push((state.keys.status(), Endpoint::Status));
        endpoints.push((state.keys.corrections(), Endpoint::Corrections));
        let mut queryables = Vec::with_capacity(endpoints.len());
        for (key, endpoint) in endpoints {
            let tx = sender.clone();
            let st = Arc::clone(&state);
            let reply_key = key.clone();
            let q = session
                .declare_queryable(&key)
                .complete(true)
                .callback(move |query| {
                    if inline(endpoint, &query) {
                        let (encoding, outcome) = serve(endpoint, &query, &st);
                        return reply::put(&query, &reply_key, encoding, outcome);
                    }
                    match tx.try_send((endpoint, query, Instant::now())) {
                        Ok(()) => {}
                        Err(TrySendError::Full((_, query, _)))
                        | Err(TrySendError::Disconnected((_, query, _))) => {
                            st.metrics.queries_failed.fetch_add(1, Relaxed);
                            let encoding = request_encoding(&query);
                            let outcome =
                                error_reply(encoding, ErrorCode::Overloaded, "query queue full, retry later");
                            reply::put(&query, &reply_key, encoding, outcome);
                        }
                    }
                })
                .wait()
                .map_err(|source| ServerError::Declare {
                    what: key.clone(),
                    source,
                })?;
            queryables.push(q);
        }
        let echo = state.keys.echo();
        let echo_key = echo.clone();
        queryables.push(
            session
                .declare_queryable(&echo)
                .complete(true)
                .callback(move |query| {
                    let payload = query
                        .payload()
                        .map(|p| p.to_bytes().into_owned())
                        .unwrap_or_default();
                    if let Err(e) = query.reply(echo_key.as_str(), payload).wait() {
                        warn!(error = %e, "echo reply failed");
                    }
                })
                .wait()
                .map_err(|source| ServerError::Declare {
                    what: echo.clone(),
                    source,
                })?,
        );
        let alive = state.keys.alive();
        let token = session
            .liveliness()
            .declare_token(&alive)
            .wait()
            .map_err(|source| ServerError::Declare {
                what: alive.clone(),
                source,
            })?;
        info!(map = state.keys.map_id(), "queryables declared");
        Ok(Self {
            queryables,
            token: Some(token),
            sender: Some(sender),
            workers: handles,
        })
    }
}

impl Drop for QueryServer {
    fn drop(&mut self) {
        self.token.take();
        for q in self.queryables.drain(..) {
            if let Err(e) = q.undeclare().wait() {
                warn!(error = %e, "undeclaring a queryable failed");
            }
        }
        self.sender.take();
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

fn worker(receiver: &Mutex<Receiver<Job>>, state: &DaemonState, replies: &ReplySender) {
    crate::priority::lower_current_thread(crate::priority::Background::Batch);
    loop {
        let job = receiver.lock().unwrap_or_else(PoisonError::into_inner).recv();
        let Ok((endpoint, query, queued)) = job else {
            return;
        };
        let waited = queued.elapsed();
        let (encoding, outcome) = if waited > state.queue_deadline {
            state.metrics.queries_expired.fetch_add(1, Relaxed);
            state.metrics.queries_failed.fetch_add(1, Relaxed);
            let encoding = request_encoding(&query);
            let message = format!("waited {} ms for a worker, retry later", waited.as_millis());
            (encoding, error_reply(encoding, ErrorCode::Overloaded, &message))
        } else {
            serve(endpoint, &query, state)
        };
        let key = match endpoint {
            Endpoint::Query(k) => state.keys.query(k),
            Endpoint::Status => state.keys.status(),
            Endpoint::Corrections => state.keys.corrections(),
        };
        replies.send(query, key, encoding, outcome);
    }
}

/// Requests at most this large (a few points) are answered on the Zenoh callback itself:
/// bounded work (tens of µs) that would otherwise pay a thread hand-off and wait behind batches.
pub const INLINE_MAX_BYTES: usize = 64;

/// Whether `query` is cheap enough to answer without a worker (elevation, variance, status).
fn inline(endpoint: Endpoint, query: &Query) -> bool {
    let small = query.payload().is_none_or(|p| p.len() <= INLINE_MAX_BYTES);
    small
        && matches!(
            endpoint,
            Endpoint::Status | Endpoint::Query(QueryKind::Elevation) | Endpoint::Query(QueryKind::Variance)
        )
}

/// Requests or replies at least this large give their memory back to the OS once answered
/// (glibc keeps freed arenas otherwise: a spike would stay in RSS).
const TRIM_BYTES: usize = 8 << 20;

/// Zenoh's limit on a reassembled request: the codec's limit and room for key and encoding.
/// Larger requests are discarded fragment by fragment by Zenoh, before any copy.
pub const MAX_REQUEST_BYTES: usize = MAX_DECODE_BYTES + (64 << 10);

/// The encoding a query's label names (bincode when unlabelled).
fn request_encoding(query: &Query) -> Encoding {
    query.encoding().map(protocol_encoding).unwrap_or_default()
}

/// Answers one query (reading its payload in place, refusing it before any copy when it is
/// over the limit) and records its latency; returns the reply to send.
fn serve(endpoint: Endpoint, query: &Query, state: &DaemonState) -> (Encoding, Outcome) {
    let started = Instant::now();
    let encoding = request_encoding(query);
    let size = query.payload().map_or(0, |p| p.len());
    let answer = if size > MAX_DECODE_BYTES {
        Err(handler::Failure {
            code: ErrorCode::BatchTooLarge,
            message: format!("request of {size} bytes exceeds the {MAX_DECODE_BYTES}-byte limit"),
        })
    } else {
        let payload = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
        // A panic is a bug, but it must cost one request, not a query thread: nothing restarts
        // the workers, and the daemon would answer `overloaded` from then on. Queries only read
        // the published snapshot, so no state is left half-changed.
        std::panic::catch_unwind(AssertUnwindSafe(|| {
            handler::answer(endpoint, encoding, &payload, state)
        }))
        .unwrap_or_else(|panic| {
            let what = panic_message(panic.as_ref());
            error!(%what, ?endpoint, "a query panicked; answered as an internal error");
            Err(handler::Failure {
                code: ErrorCode::Internal,
                message: format!("the daemon failed on this request: {what}"),
            })
        })
    };
    let outcome = match answer {
        Ok(bytes) => {
            state.metrics.queries_ok.fetch_add(1, Relaxed);
            Outcome::Answer(bytes)
        }
        Err(f) => {
            state.metrics.queries_failed.fetch_add(1, Relaxed);
            error_reply(encoding, f.code, &f.message)
        }
    };
    // A correction's time is its reply's `apply_ms`, not a query latency.
    match endpoint {
        Endpoint::Query(k) => state.metrics.query(Some(k)).record(started.elapsed()),
        Endpoint::Status => state.metrics.query(None).record(started.elapsed()),
        Endpoint::Corrections => {}
    }
    let reply_size = match &outcome {
        Outcome::Answer(b) | Outcome::Error(b) => b.len(),
    };
    if size.max(reply_size) >= TRIM_BYTES {
        crate::metrics::return_freed_memory();
    }
    (encoding, outcome)
}

/// The text a panic carries (`panic!` with a literal or a formatted message), else a stand-in.
fn panic_message(panic: &(dyn std::any::Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("a panic without a message")
}

/// Longest error message sent, bytes: a message quoting a hostile value is cut here.
pub const MAX_ERROR_MESSAGE_BYTES: usize = 512;

/// An encoded [`ErrorReply`] with `message` cut to [`MAX_ERROR_MESSAGE_BYTES`].
fn error_reply(encoding: Encoding, code: ErrorCode, message: &str) -> Outcome {
    let body = ErrorReply {
        version: PROTOCOL_VERSION,
        code,
        message: truncate(message, MAX_ERROR_MESSAGE_BYTES),
    };
    match codec::encode(encoding, &body) {
        Ok(bytes) => Outcome::Error(bytes),
        Err(e) => {
            warn!(error = %e, "cannot encode an error reply");
            Outcome::Error(Vec::new())
        }
    }
}

/// `text` cut at a character boundary to at most `max` bytes, saying how long it was.
fn truncate(text: &str, max: usize) -> String {
    if text.len() <= max {
        return text.to_owned();
    }
    let mut end = max;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}… ({} bytes in all)", &text[..end], text.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_messages_are_cut_at_a_character_boundary() {
        assert_eq!(truncate("short", 10), "short");
        let long = "é".repeat(400);
        let cut = truncate(&long, 11);
        assert!(
            cut.starts_with(&"é".repeat(5)) && cut.ends_with("(800 bytes in all)"),
            "{cut}"
        );
    }
}
