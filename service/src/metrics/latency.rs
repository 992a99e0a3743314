//! A latency recorder: a count since start and a bounded ring of the most recent samples, from
//! which status percentiles are read (recent behaviour, bounded memory), plus a Prometheus
//! histogram of every sample for scraping.

use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use rangegp_proto::msg::LatencySummary;
use std::collections::VecDeque;
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

/// Samples kept for percentiles.
pub const RECENT: usize = 1024;

/// One latency, recorded from any thread.
#[derive(Debug)]
pub struct Latency {
    recent: Mutex<(u64, VecDeque<f64>)>,
    histogram: Histogram,
}

impl Default for Latency {
    fn default() -> Self {
        Self {
            recent: Mutex::new((0, VecDeque::with_capacity(RECENT))),
            // 50 µs to ~3.3 s in 17 doublings.
            histogram: Histogram::new(exponential_buckets(5e-5, 2.0, 17)),
        }
    }
}

impl Latency {
    /// Records one sample.
    pub fn record(&self, took: Duration) {
        let ms = took.as_secs_f64() * 1e3;
        self.histogram.observe(took.as_secs_f64());
        let mut recent = self.recent.lock().unwrap_or_else(PoisonError::into_inner);
        recent.0 += 1;
        if recent.1.len() == RECENT {
            recent.1.pop_front();
        }
        recent.1.push_back(ms);
    }

    /// Count since start and percentiles of the recent samples (zeros before the first).
    pub fn summary(&self) -> LatencySummary {
        let (count, mut samples) = {
            let recent = self.recent.lock().unwrap_or_else(PoisonError::into_inner);
            (recent.0, recent.1.iter().copied().collect::<Vec<f64>>())
        };
        if samples.is_empty() {
            return LatencySummary::default();
        }
        let mut at = |q: f64| percentile(&mut samples, q).unwrap_or(0.0);
        LatencySummary {
            count,
            p50_ms: at(0.50),
            p90_ms: at(0.90),
            p99_ms: at(0.99),
            max_ms: at(1.0),
        }
    }

    /// The Prometheus histogram (seconds).
    pub fn histogram(&self) -> &Histogram {
        &self.histogram
    }
}

/// Nearest-rank percentile `q` ∈ [0, 1] of `v` (sorted in place), `None` when `v` is empty.
pub fn percentile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let rank = (q * v.len() as f64).ceil() as usize;
    Some(v[rank.clamp(1, v.len()) - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_come_from_the_most_recent_samples() {
        let l = Latency::default();
        assert_eq!(l.summary(), LatencySummary::default());
        for _ in 0..RECENT {
            l.record(Duration::from_secs(1));
        }
        for ms in 1..=100 {
            for _ in 0..RECENT / 100 {
                l.record(Duration::from_millis(ms));
            }
        }
        let s = l.summary();
        assert_eq!(s.count, (RECENT + RECENT / 100 * 100) as u64);
        // 1000 fresh samples 1..=100 ms and 24 of the old 1 s ones remain in the ring.
        assert!((s.p50_ms - 52.0).abs() < 2.0, "{s:?}");
        assert_eq!(s.max_ms, 1000.0);
        assert!(s.p90_ms < 100.5, "{s:?}");
    }

    #[test]
    fn nearest_rank() {
        let mut v = [4.0, 2.0, 3.0, 1.0];
        assert_eq!(percentile(&mut v, 0.5), Some(2.0));
        assert_eq!(percentile(&mut v, 0.99), Some(4.0));
        assert_eq!(percentile(&mut v, 0.0), Some(1.0));
        assert_eq!(percentile(&mut [], 0.5), None);
    }
}
