//! Scan intake: the iceoryx2 subscriber thread, validation, and the queue to the fitter.

pub mod queue;
pub mod subscriber;
pub mod validate;

pub use queue::LatestQueue;
pub use subscriber::{spawn_ingest, IngestError, IngestHandle};
pub use validate::{RejectReason, SequenceTracker, ValidationLimits};
