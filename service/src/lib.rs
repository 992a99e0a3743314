//! rangegp-service: range-based GP maps fitted to LiDAR scans and served over Zenoh.
//!
//! - [`gp`]: kernels, range sphere, Cholesky with jitter, exact GP regression.
//! - [`map`]: local range maps, the window, query evaluation.
//! - [`ingest`]: the iceoryx2 subscriber thread and scan validation.
//! - [`server`]: Zenoh queryables.
//! - [`daemon`]: wiring of the above with configuration and shutdown.

pub mod gp;
pub mod map;
