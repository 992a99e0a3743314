//! Counters and timings the status query reports; lock-free, shared by all threads.

use crate::ingest::validate::RejectReason;
use rangegp_proto::msg::RejectionCount;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

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
    /// Missing sequence numbers, all publishers.
    pub sequence_gaps: AtomicU64,
    /// Online hyperparameter updates applied.
    pub hyper_updates: AtomicU64,
    /// Local experts that needed Cholesky jitter.
    pub jittered_tiles: AtomicU64,
    /// Fitted scans folded into the aggregate.
    pub aggregate_inserts: AtomicU64,
    /// Fitted scans the aggregate skipped because it fell behind (newest wins).
    pub aggregate_skipped: AtomicU64,
    /// Fitted scans the aggregate could not fold in (its tile fit failed; the map keeps its state).
    pub aggregate_failed: AtomicU64,
    fit_count: AtomicU64,
    fit_ns_total: AtomicU64,
    fit_ns_last: AtomicU64,
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
            hyper_updates: AtomicU64::new(0),
            jittered_tiles: AtomicU64::new(0),
            aggregate_inserts: AtomicU64::new(0),
            aggregate_skipped: AtomicU64::new(0),
            aggregate_failed: AtomicU64::new(0),
            fit_count: AtomicU64::new(0),
            fit_ns_total: AtomicU64::new(0),
            fit_ns_last: AtomicU64::new(0),
            queries_ok: AtomicU64::new(0),
            queries_failed: AtomicU64::new(0),
        }
    }
}

impl Metrics {
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

    /// Records one fit's duration.
    pub fn record_fit(&self, took: Duration) {
        let ns = took.as_nanos().min(u64::MAX as u128) as u64;
        self.fit_count.fetch_add(1, Relaxed);
        self.fit_ns_total.fetch_add(ns, Relaxed);
        self.fit_ns_last.store(ns, Relaxed);
    }

    /// (last, mean) fit duration in milliseconds.
    pub fn fit_ms(&self) -> (f64, f64) {
        let n = self.fit_count.load(Relaxed).max(1) as f64;
        (
            self.fit_ns_last.load(Relaxed) as f64 / 1e6,
            self.fit_ns_total.load(Relaxed) as f64 / n / 1e6,
        )
    }

    /// Seconds since start.
    pub fn uptime_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}
