//! rangegp-service: the rangegp daemon. Range-based GP maps fitted to LiDAR scans taken from
//! iceoryx2 shared memory, answered over Zenoh.
//!
//! - [`scan`]: what a scan is inside the daemon, and why one is refused.
//! - [`gp`]: kernels, range sphere, Cholesky with jitter, exact GP regression.
//! - [`map`]: local range maps, the window, the aggregate, σ calibration, query evaluation.
//! - [`ingest`]: the iceoryx2 subscriber thread and scan validation.
//! - [`state`]: what every thread shares (snapshot, counters, query settings).
//! - [`server`]: Zenoh queryables and the query worker pool.
//! - [`checkpoint`]: durable, atomic, checksummed checkpoints of the aggregate.
//! - [`exporter`]: Prometheus metrics over HTTP.
//! - [`fleet`]: tiles into a site's key space; the site daemon's map of every robot's tiles.
//! - [`daemon`]: starts and stops the threads of the above.
//! - [`config`], [`metrics`]: TOML configuration, counters and latencies.
//! - [`priority`], [`shutdown`]: background threads yield; one stop signal for all.

#![deny(missing_docs)]

pub mod checkpoint;
pub mod config;
pub mod daemon;
pub mod exporter;
pub mod fleet;
pub mod gp;
pub mod ingest;
pub mod map;
pub mod metrics;
pub mod priority;
pub mod scan;
pub mod server;
pub mod shutdown;
pub mod state;
