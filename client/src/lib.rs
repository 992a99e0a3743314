//! rangegp-client: talk to the rangegp daemon.
//!
//! - [`Client`]: typed, timed queries over Zenoh (blocking and async).
//! - [`ScanPublisher`]: zero-copy scan publishing over iceoryx2.
//! - [`stats`]: percentiles shared by the load test, the demo and the daemon.
//! - [`transport`]: Zenoh configuration shared with the daemon.
//! - [`load`]: the load test behind `rangegp load` (scan generator + planners + echo baseline).
//! - [`plot`]: heat-map PNGs (grid layers here, the daemon's demo and evaluation pictures).

pub mod client;
pub mod load;
pub mod plot;
pub mod publisher;
pub mod scangen;
pub mod stats;
pub mod transport;

pub use client::{Client, ClientBuilder, ClientError};
pub use publisher::{PublishError, ScanPublisher};
