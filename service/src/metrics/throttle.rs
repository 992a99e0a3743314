//! A log line per interval instead of one per event: per-scan events at sensor rate (skipped
//! scans, sequence restarts) would otherwise flood the journal with hundreds of lines a second.

use std::time::{Duration, Instant};

/// Counts events and says when a summary line is due.
#[derive(Debug)]
pub struct Throttle {
    interval: Duration,
    last: Option<Instant>,
    pending: u64,
}

impl Throttle {
    /// At most one summary per `interval`.
    pub fn new(interval: Duration) -> Self {
        Self {
            interval,
            last: None,
            pending: 0,
        }
    }

    /// Counts one event at `now`; returns how many events to report when a line is due (the
    /// first event is reported at once, later ones at most once per interval).
    pub fn hit(&mut self, now: Instant) -> Option<u64> {
        self.pending = self.pending.saturating_add(1);
        let due = self.last.is_none_or(|t| now.duration_since(t) >= self.interval);
        if !due {
            return None;
        }
        self.last = Some(now);
        Some(std::mem::take(&mut self.pending))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_per_interval_with_the_count_since_the_last() {
        let mut t = Throttle::new(Duration::from_secs(5));
        let t0 = Instant::now();
        assert_eq!(t.hit(t0), Some(1));
        let reported: Vec<_> = (1..=669)
            .filter_map(|i| t.hit(t0 + Duration::from_millis(9 * i)))
            .collect();
        assert_eq!(reported, vec![556], "the 556 events up to 5 s in one line");
        assert_eq!(t.hit(t0 + Duration::from_secs(11)), Some(114));
    }
}
