//! rangegp-service: range-based GP maps fitted to LiDAR scans and served over Zenoh.
//!
//! - [`gp`]: kernels, range sphere, Cholesky with jitter, exact GP regression.
//! - [`map`]: local range maps, the window, query evaluation.
//! - [`ingest`]: the iceoryx2 subscriber thread and scan validation.
//! - [`server`]: Zenoh queryables and the query worker pool.
//! - [`checkpoint`]: durable, atomic, checksummed checkpoints of the aggregate.
//! - [`daemon`]: wiring of the above.
//! - [`config`], [`metrics`]: TOML configuration, counters, latencies, the Prometheus exporter.
//! - [`priority`]: background threads yield to the latency-critical ones.
//! - [`demo`], [`plot`]: the self-contained demo and its pictures.

pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod daemon;
pub mod demo;
pub mod eval;
pub mod gp;
pub mod ingest;
pub mod map;
pub mod metrics;
pub use rangegp_client::plot;
pub mod priority;
pub mod server;
mod sleep;
