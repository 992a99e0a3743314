//! Scan intake: the iceoryx2 subscriber thread, validation, and the queue to the fitter.

pub mod queue;
pub mod subscriber;
pub mod validate;

pub use queue::LatestQueue;

use crate::map::ScanInput;
use std::time::Instant;

/// A validated scan on its way to the fitter, with when it was taken from shared memory.
#[derive(Debug)]
pub struct Arrival {
    /// The scan.
    pub scan: ScanInput,
    /// When the ingest thread received it (start of scan-to-queryable latency).
    pub received: Instant,
}
pub use subscriber::{spawn_ingest, IngestError, IngestHandle};
pub use validate::{RejectReason, SequenceTracker, ValidationLimits};
