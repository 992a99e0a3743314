//! Per-source sequence bookkeeping: refuses replays, tells lost scans from restarts, and never
//! locks a source out (every difference is taken with checked arithmetic).

use crate::scan::RejectReason;
use std::collections::HashMap;

/// Who sent a scan: the header's publisher id and the iceoryx2 port it came through. A driver
/// that restarts keeps its id but gets a new port, so its sequence numbers may start again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Source {
    /// `ScanHeader::publisher_id`.
    pub publisher_id: u64,
    /// iceoryx2's unique publisher-port id.
    pub port: u128,
}

/// What a scan's sequence number says, when it is not refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SequenceCheck {
    /// The next scan of a known source (or the first of a new one); `lost` scans of this source
    /// never arrived (sequence numbers neither accepted nor rejected since the last one seen).
    Next {
        /// Scans lost in transport.
        lost: u64,
    },
    /// The number jumped by more than the restart window (either way): the source counts anew.
    Restart,
}

/// Where a source stands.
#[derive(Debug, Clone, Copy)]
struct Track {
    /// Last accepted sequence number.
    accepted: u64,
    /// Highest number that arrived since (accepted or rejected), for counting losses.
    seen: u64,
}

/// Per-source sequence bookkeeping, bounded in size.
#[derive(Debug)]
pub struct SequenceTracker {
    sources: HashMap<Source, Track>,
    restart_window: u64,
}

/// Sources remembered at most; beyond it the table is cleared (a restart of bookkeeping).
const MAX_TRACKED_SOURCES: usize = 4096;

impl SequenceTracker {
    /// A tracker that treats a jump of more than `restart_window` numbers as a restart.
    pub fn new(restart_window: u64) -> Self {
        Self {
            sources: HashMap::new(),
            restart_window,
        }
    }

    /// Checks `sequence` against the source's last accepted one without recording it.
    pub fn check(&self, source: Source, sequence: u64) -> Result<SequenceCheck, RejectReason> {
        let Some(t) = self.sources.get(&source) else {
            return Ok(SequenceCheck::Next { lost: 0 });
        };
        let distance = sequence.abs_diff(t.accepted);
        if distance > self.restart_window {
            return Ok(SequenceCheck::Restart);
        }
        if sequence == t.accepted {
            return Err(RejectReason::DuplicateSequence);
        }
        if sequence < t.accepted {
            return Err(RejectReason::StaleSequence);
        }
        let lost = sequence.saturating_sub(t.seen.max(t.accepted)).saturating_sub(1);
        Ok(SequenceCheck::Next { lost })
    }

    /// Records an accepted scan.
    pub fn accept(&mut self, source: Source, sequence: u64) {
        if self.sources.len() >= MAX_TRACKED_SOURCES && !self.sources.contains_key(&source) {
            self.sources.clear();
        }
        let seen = match self.sources.get(&source) {
            Some(t) if sequence.abs_diff(t.accepted) <= self.restart_window => t.seen.max(sequence),
            _ => sequence,
        };
        self.sources.insert(
            source,
            Track {
                accepted: sequence,
                seen,
            },
        );
    }

    /// Records a scan that arrived but was rejected: its number is not lost, and nothing else
    /// changes (a later scan is judged against the last accepted one as before).
    pub fn saw(&mut self, source: Source, sequence: u64) {
        if let Some(t) = self.sources.get_mut(&source) {
            let ahead = sequence > t.seen && sequence - t.accepted <= self.restart_window;
            if ahead {
                t.seen = sequence;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: Source = Source {
        publisher_id: 1,
        port: 10,
    };

    #[test]
    fn sequences_refuse_replays_and_count_losses() {
        let mut t = SequenceTracker::new(1000);
        assert_eq!(t.check(A, 5), Ok(SequenceCheck::Next { lost: 0 }));
        t.accept(A, 5);
        assert_eq!(t.check(A, 5), Err(RejectReason::DuplicateSequence));
        assert_eq!(t.check(A, 4), Err(RejectReason::StaleSequence));
        assert_eq!(t.check(A, 8), Ok(SequenceCheck::Next { lost: 2 }));
        let other = Source {
            publisher_id: 2,
            port: 11,
        };
        assert_eq!(t.check(other, 0), Ok(SequenceCheck::Next { lost: 0 }));
        // The same driver restarted: same id, new port, sequences from 1 again.
        let restarted = Source { port: 12, ..A };
        assert_eq!(t.check(restarted, 1), Ok(SequenceCheck::Next { lost: 0 }));
    }

    #[test]
    fn rejected_scans_are_not_counted_as_lost() {
        let mut t = SequenceTracker::new(1000);
        t.accept(A, 1);
        t.saw(A, 2);
        t.saw(A, 3);
        assert_eq!(t.check(A, 4), Ok(SequenceCheck::Next { lost: 0 }));
        assert_eq!(t.check(A, 6), Ok(SequenceCheck::Next { lost: 2 }));
        // A rejected scan does not move the accepted number: 2 is still after 1.
        assert_eq!(t.check(A, 2), Ok(SequenceCheck::Next { lost: 0 }));
        // Accepting 2 does not forget that 3 arrived.
        t.accept(A, 2);
        assert_eq!(
            t.check(A, 5),
            Ok(SequenceCheck::Next { lost: 1 }),
            "only 4 is lost"
        );
    }

    #[test]
    fn extreme_numbers_restart_the_source_instead_of_locking_it_out() {
        let mut t = SequenceTracker::new(1000);
        t.accept(A, 5);
        assert_eq!(t.check(A, u64::MAX), Ok(SequenceCheck::Restart));
        t.accept(A, u64::MAX);
        assert_eq!(t.check(A, 6), Ok(SequenceCheck::Restart), "no lock-out");
        t.accept(A, 6);
        assert_eq!(t.check(A, 7), Ok(SequenceCheck::Next { lost: 0 }));
        t.accept(A, 7);
        t.saw(A, u64::MAX - 1);
        assert_eq!(
            t.check(A, 9),
            Ok(SequenceCheck::Next { lost: 1 }),
            "far rejected numbers ignored"
        );
        t.accept(A, 0);
        assert_eq!(t.check(A, u64::MAX), Ok(SequenceCheck::Restart));
    }
}
