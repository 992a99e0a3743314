//! The Zenoh query server: queryables for elevation, variance, ray, grid and status, a
//! liveliness token, and a bounded worker pool so that query load never touches ingest and
//! overload is answered (`overloaded`) instead of timing out. Requests of a few points are
//! answered on the Zenoh callback directly (bounded work, no hand-off, never behind a batch).
//! `rangegp/<map>/echo` returns the request's bytes from the callback: the transport floor.

pub mod handler;

use crate::gp::Kernel;
use crate::map::MapSnapshot;
use crate::metrics::Metrics;
use arc_swap::ArcSwap;
use handler::Endpoint;
use rangegp_client::transport::{protocol_encoding, zenoh_encoding};
use rangegp_proto::codec;
use rangegp_proto::keys::{MapKeys, QueryKind};
use rangegp_proto::msg::{ErrorCode, ErrorReply};
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use thiserror::Error;
use tracing::{info, warn};
use zenoh::query::Query;
use zenoh::Wait;

/// What the query side reads: the current snapshot, counters and limits.
#[derive(Debug)]
pub struct ServerState {
    /// Current maps, swapped atomically by the fitter.
    pub snapshot: ArcSwap<MapSnapshot>,
    /// Shared counters.
    pub metrics: Arc<Metrics>,
    /// Map id served.
    pub keys: MapKeys,
    /// Largest batch accepted.
    pub max_batch: usize,
    /// Longest ray accepted, metres.
    pub max_ray_range_m: f64,
    /// Threads for one large batch.
    pub batch_threads: usize,
    /// Window capacity (for status).
    pub window_capacity: usize,
    /// Kernel the fitter uses now (updated by online learning).
    pub kernel: Arc<ArcSwap<Kernel>>,
    /// Noise variance added to every training ray (for status).
    pub nugget_m2: f64,
    /// Eviction radius of the aggregate when it is enabled (for status).
    pub aggregate_radius_m: Option<f64>,
}

/// The server could not start.
#[derive(Debug, Error)]
pub enum ServerError {
    /// A queryable or the liveliness token could not be declared.
    #[error("cannot declare {what}: {reason}")]
    Declare {
        /// Key expression.
        what: String,
        /// Zenoh's reason.
        reason: String,
    },
    /// A worker thread could not be spawned.
    #[error("cannot spawn a query worker: {0}")]
    Spawn(#[from] std::io::Error),
}

type Job = (Endpoint, Query);

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
        state: Arc<ServerState>,
        workers: usize,
        queue_len: usize,
    ) -> Result<Self, ServerError> {
        let (sender, receiver) = sync_channel::<Job>(queue_len);
        let receiver = Arc::new(Mutex::new(receiver));
        let mut handles = Vec::with_capacity(workers);
        for i in 0..workers.max(1) {
            let (rx, st) = (Arc::clone(&receiver), Arc::clone(&state));
            handles.push(
                std::thread::Builder::new()
                    .name(format!("rangegp-query-{i}"))
                    .spawn(move || worker(&rx, &st))?,
            );
        }
        let mut endpoints: Vec<(String, Endpoint)> = QueryKind::ALL
            .iter()
            .map(|&k| (state.keys.query(k), Endpoint::Query(k)))
            .collect();
        endpoints.push((state.keys.status(), Endpoint::Status));
        let mut queryables = Vec::with_capacity(endpoints.len());
        for (key, endpoint) in endpoints {
            let tx = sender.clone();
            let st = Arc::clone(&state);
            let q = session
                .declare_queryable(&key)
                .complete(true)
                .callback(move |query| {
                    if inline(endpoint, &query) {
                        return serve(endpoint, &query, &st);
                    }
                    match tx.try_send((endpoint, query)) {
                        Ok(()) => {}
                        Err(TrySendError::Full((_, query))) | Err(TrySendError::Disconnected((_, query))) => {
                            st.metrics
                                .queries_failed
                                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            reply_error(
                                &query,
                                ErrorCode::Overloaded,
                                "query queue full, retry later".into(),
                            );
                        }
                    }
                })
                .wait()
                .map_err(|e| ServerError::Declare {
                    what: key.clone(),
                    reason: e.to_string(),
                })?;
            queryables.push(q);
        }
        let echo = state.keys.echo();
        queryables.push(
            session
                .declare_queryable(&echo)
                .complete(true)
                .callback(|query| {
                    let payload = query
                        .payload()
                        .map(|p| p.to_bytes().into_owned())
                        .unwrap_or_default();
                    if let Err(e) = query.reply(query.key_expr().clone(), payload).wait() {
                        warn!(error = %e, "echo reply failed");
                    }
                })
                .wait()
                .map_err(|e| ServerError::Declare {
                    what: echo.clone(),
                    reason: e.to_string(),
                })?,
        );
        let alive = state.keys.alive();
        let token = session
            .liveliness()
            .declare_token(&alive)
            .wait()
            .map_err(|e| ServerError::Declare {
                what: alive.clone(),
                reason: e.to_string(),
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

fn worker(receiver: &Mutex<Receiver<Job>>, state: &ServerState) {
    crate::priority::lower_current_thread(crate::priority::Background::Batch);
    loop {
        let job = receiver.lock().unwrap_or_else(PoisonError::into_inner).recv();
        let Ok((endpoint, query)) = job else { return };
        serve(endpoint, &query, state);
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

/// Answers one query and records its latency.
fn serve(endpoint: Endpoint, query: &Query, state: &ServerState) {
    let started = std::time::Instant::now();
    let encoding = query.encoding().map(protocol_encoding).unwrap_or_default();
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    match handler::answer(endpoint, encoding, &payload, state) {
        Ok(bytes) => {
            state
                .metrics
                .queries_ok
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if let Err(e) = query
                .reply(query.key_expr().clone(), bytes)
                .encoding(zenoh_encoding(encoding))
                .wait()
            {
                warn!(error = %e, "reply failed");
            }
        }
        Err(f) => {
            state
                .metrics
                .queries_failed
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            reply_error(query, f.code, f.message);
        }
    }
    let kind = match endpoint {
        Endpoint::Query(k) => Some(k),
        Endpoint::Status => None,
    };
    state.metrics.query(kind).record(started.elapsed());
}

fn reply_error(query: &Query, code: ErrorCode, message: String) {
    let encoding = query.encoding().map(protocol_encoding).unwrap_or_default();
    let body = ErrorReply {
        version: PROTOCOL_VERSION,
        code,
        message,
    };
    match codec::encode(encoding, &body) {
        Ok(bytes) => {
            if let Err(e) = query.reply_err(bytes).encoding(zenoh_encoding(encoding)).wait() {
                warn!(error = %e, "error reply failed");
            }
        }
        Err(e) => warn!(error = %e, "cannot encode an error reply"),
    }
}
