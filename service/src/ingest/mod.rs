//! Scan intake: the iceoryx2 subscriber thread, validation, sequence and pose bookkeeping, and
//! the queue to the fitter.

pub mod deskew;
pub mod noise;
pub mod plausibility;
pub mod queue;
pub mod sequence;
pub mod subscriber;
pub mod validate;

pub use queue::LatestQueue;

use crate::scan::ScanInput;
use std::time::Instant;

/// A validated scan on its way to the fitter, with when it was taken from shared memory.
#[derive(Debug)]
pub struct Arrival {
    /// The scan.
    pub scan: ScanInput,
    /// When the ingest thread received it (start of scan-to-queryable latency).
    pub received: Instant,
}
pub use plausibility::PoseLimits;
pub use subscriber::{spawn_ingest, IngestError, IngestHandle};
pub use validate::ValidationLimits;
