//! Counters and latencies the status query reports and Prometheus scrapes; shared by all threads.

pub mod latency;
pub mod throttle;

use crate::scan::RejectReason;
pub use latency::Latency;
use rangegp_proto::keys::QueryKind;
use rangegp_proto::msg::{QueryLatencies, RejectionCount};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

/// Daemon-wide counters.
#[derive(Debug)]
pub struct Metrics {
    started: Instant,
    /// Scans taken from shared memory.
    pub received: AtomicU64,
    /// Scans fitted into the window.
    pub accepted: AtomicU64,
    rejected: [AtomicU64; RejectReason::ALL.len()],
    /// Valid scans skipped because fitting fell behind.
    pub skipped: AtomicU64,
    /// Scans lost in transport (sequence numbers that never arrived), all publishers.
    pub sequence_gaps: AtomicU64,
    /// Sources whose sequence number jumped beyond `ingest.sequence_restart_window`.
    pub publisher_restarts: AtomicU64,
    /// Publishers followed to a new place after `ingest.pose_confirm_scans` agreeing scans.
    pub relocations: AtomicU64,
    /// Whether the ingest thread holds its iceoryx2 subscriber now.
    pub ingest_connected: AtomicBool,
    /// Failed attempts to open the scan service or its subscriber (retried with back-off).
    pub ingest_retries: AtomicU64,
    /// Why the last attempt failed (cleared once connected).
    ingest_error: Mutex<Option<String>>,
    /// Batch queries answered `overloaded` because they waited past `query.queue_deadline_ms`.
    pub queries_expired: AtomicU64,
    /// Worker replies dropped because too many were already being sent (a client not reading).
    pub replies_dropped: AtomicU64,
    /// Empty aggregates not written over a non-empty checkpoint.
    pub checkpoints_empty_refused: AtomicU64,
    /// Valid scans and missing sequence numbers per publisher id (bounded, see [`MAX_PUBLISHERS`]).
    publishers: Mutex<BTreeMap<u64, PublisherCounts>>,
    /// Online hyperparameter updates applied.
    pub hyper_updates: AtomicU64,
    /// Local experts that needed Cholesky jitter.
    pub jittered_tiles: AtomicU64,
    /// Fitted scans folded into the aggregate.
    pub aggregate_inserts: AtomicU64,
    /// Fitted scans displaced from the aggregate's queue (it fell `aggregate.queue_len` behind).
    pub aggregate_skipped: AtomicU64,
    /// Fitted scans the aggregate could not fold in (its tile fit failed; the map keeps its state).
    pub aggregate_failed: AtomicU64,
    /// World-aggregate tiles evicted for lying beyond its radius.
    pub aggregate_evicted_tiles: AtomicU64,
    /// Reach each scan is fused out to now, millimetres (the fusion budget's choice).
    pub aggregate_reach_mm: AtomicU64,
    /// Tiles written to the site map on disk when they left the radius.
    pub aggregate_paged_out: AtomicU64,
    /// Tiles read back from the site map when the robot returned.
    pub aggregate_paged_in: AtomicU64,
    /// Tile pages that could not be written or read back.
    pub aggregate_page_failures: AtomicU64,
    /// Scans the aggregate's ledger keeps (what a pose correction can move).
    pub ledger_scans: AtomicU64,
    /// Bytes the ledger holds.
    pub ledger_bytes: AtomicU64,
    /// Pose corrections applied.
    pub corrections: AtomicU64,
    /// Aggregate cells replaced by disagreeing scans (changes).
    pub changed_cells: AtomicU64,
    /// Checkpoints written.
    pub checkpoints_written: AtomicU64,
    /// Checkpoint writes that failed (disk full, I/O error); the daemon keeps running.
    pub checkpoint_failures: AtomicU64,
    /// Checkpoint files passed over at start (damaged or foreign).
    pub checkpoints_rejected: AtomicU64,
    /// One checkpoint write (encode, write, fsync, rename).
    pub checkpoint_write: Latency,
    /// Fit of one scan.
    pub fit: Latency,
    /// Scan taken from shared memory to its map published for queries.
    pub scan_to_queryable: Latency,
    /// One aggregate insert.
    pub aggregate_insert: Latency,
    /// One scan's test of the maps before it (prequential σ calibration).
    pub calibrate: Latency,
    /// Query handling, by [`QueryKind`] in [`QueryKind::ALL`] order, then status.
    queries: [Latency; QueryKind::ALL.len() + 1],
    /// Queries answered.
    pub queries_ok: AtomicU64,
    /// Queries answered with an error.
    pub queries_failed: AtomicU64,
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            started: Instant::now(),
            received: AtomicU64::new(0),
            accepted: AtomicU64::new(0),
            rejected: std::array::from_fn(|_| AtomicU64::new(0)),
            skipped: AtomicU64::new(0),
            sequence_gaps: AtomicU64::new(0),
            publisher_restarts: AtomicU64::new(0),
            relocations: AtomicU64::new(0),
            ingest_connected: AtomicBool::new(false),
            ingest_retries: AtomicU64::new(0),
            ingest_error: Mutex::new(None),
            queries_expired: AtomicU64::new(0),
            replies_dropped: AtomicU64::new(0),
            checkpoints_empty_refused: AtomicU64::new(0),
            publishers: Mutex::new(BTreeMap::new()),
            hyper_updates: AtomicU64::new(0),
            jittered_tiles: AtomicU64::new(0),
            aggregate_inserts: AtomicU64::new(0),
            aggregate_skipped: AtomicU64::new(0),
            aggregate_failed: AtomicU64::new(0),
            aggregate_evicted_tiles: AtomicU64::new(0),
            aggregate_reach_mm: AtomicU64::new(0),
            aggregate_paged_out: AtomicU64::new(0),
            aggregate_paged_in: AtomicU64::new(0),
            aggregate_page_failures: AtomicU64::new(0),
            ledger_scans: AtomicU64::new(0),
            ledger_bytes: AtomicU64::new(0),
            corrections: AtomicU64::new(0),
            changed_cells: AtomicU64::new(0),
            checkpoints_written: AtomicU64::new(0),
            checkpoint_failures: AtomicU64::new(0),
            checkpoints_rejected: AtomicU64::new(0),
            checkpoint_write: Latency::default(),
            fit: Latency::default(),
            scan_to_queryable: Latency::default(),
            aggregate_insert: Latency::default(),
            calibrate: Latency::default(),
            queries: std::array::from_fn(|_| Latency::default()),
            queries_ok: AtomicU64::new(0),
            queries_failed: AtomicU64::new(0),
        }
    }
}

/// Publishers counted separately at most; scans of others are counted under id `u64::MAX`.
pub const MAX_PUBLISHERS: usize = 64;

/// What one publisher sent that passed validation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PublisherCounts {
    /// Valid scans.
    pub scans: u64,
    /// Scans lost in transport between them.
    pub gaps: u64,
}

impl Metrics {
    /// Counts one valid scan of `publisher` and the scans of it lost in transport before it.
    pub fn count_source(&self, publisher: u64, gaps: u64) {
        add_saturating(&self.sequence_gaps, gaps);
        let mut table = self.publishers.lock().unwrap_or_else(PoisonError::into_inner);
        let key = if table.len() < MAX_PUBLISHERS || table.contains_key(&publisher) {
            publisher
        } else {
            u64::MAX
        };
        let entry = table.entry(key).or_default();
        entry.scans = entry.scans.saturating_add(1);
        entry.gaps = entry.gaps.saturating_add(gaps);
    }

    /// Records whether the ingest thread is subscribed, and why not.
    pub fn set_ingest_state(&self, error: Option<String>) {
        self.ingest_connected.store(error.is_none(), Relaxed);
        if error.is_some() {
            self.ingest_retries.fetch_add(1, Relaxed);
        }
        *self.ingest_error.lock().unwrap_or_else(PoisonError::into_inner) = error;
    }

    /// Why the ingest thread is not subscribed (`None` when it is, or before its first try).
    pub fn ingest_error(&self) -> Option<String> {
        self.ingest_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Per-publisher counts, by publisher id.
    pub fn publishers(&self) -> Vec<(u64, PublisherCounts)> {
        let table = self.publishers.lock().unwrap_or_else(PoisonError::into_inner);
        table.iter().map(|(&k, &v)| (k, v)).collect()
    }

    /// Counts one rejection.
    pub fn reject(&self, reason: RejectReason) {
        self.rejected[reason as usize].fetch_add(1, Relaxed);
    }

    /// Rejections for one reason.
    pub fn rejected(&self, reason: RejectReason) -> u64 {
        self.rejected[reason as usize].load(Relaxed)
    }

    /// Every reason with its count.
    pub fn rejections(&self) -> Vec<RejectionCount> {
        RejectReason::ALL
            .iter()
            .map(|&r| RejectionCount {
                reason: r.as_str().to_owned(),
                count: self.rejected(r),
            })
            .collect()
    }

    /// Total rejections.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.iter().map(|c| c.load(Relaxed)).sum()
    }

    /// Latency of one query kind (`None`: status).
    pub fn query(&self, kind: Option<QueryKind>) -> &Latency {
        let i = kind.map_or(QueryKind::ALL.len(), |k| k as usize);
        &self.queries[i]
    }

    /// Status percentiles of every query kind.
    pub fn query_latencies(&self) -> QueryLatencies {
        QueryLatencies {
            elevation: self.query(Some(QueryKind::Elevation)).summary(),
            variance: self.query(Some(QueryKind::Variance)).summary(),
            ray: self.query(Some(QueryKind::Ray)).summary(),
            grid: self.query(Some(QueryKind::Grid)).summary(),
            view: self.query(Some(QueryKind::View)).summary(),
            slope: self.query(Some(QueryKind::Slope)).summary(),
            sources: self.query(Some(QueryKind::Sources)).summary(),
            status: self.query(None).summary(),
        }
    }

    /// Seconds since start.
    pub fn uptime_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}

/// Adds `n` to a counter, stopping at `u64::MAX` instead of wrapping.
pub fn add_saturating(counter: &AtomicU64, n: u64) {
    let _ = counter.fetch_update(Relaxed, Relaxed, |v| Some(v.saturating_add(n)));
}

/// Gives freed heap memory back to the OS (glibc keeps it in its arenas otherwise), so that a
/// burst of large requests does not stay in the resident set.
#[allow(unsafe_code)]
pub fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks glibc's own arenas; it takes no pointer from us.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Resident set size of this process, MiB, from `/proc/self/status` (`None` off Linux).
pub fn rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// This machine's clock, nanoseconds since the Unix epoch (0 if it is set before 1970): the one
/// wall-clock reading of the daemon (scan ages, checkpoint and tile stamps).
pub fn unix_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}
