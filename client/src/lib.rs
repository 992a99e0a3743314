//! rangegp-client: what a planner or a scan driver links to talk to the rangegp daemon.
//!
//! - [`Client`]: typed, timed queries over Zenoh (feature `query`, on by default).
//! - [`fleet`]: one query to every robot and site at once, fused by inverse variance.
//! - [`ScanPublisher`]: zero-copy scan publishing over iceoryx2 (always; no Zenoh needed).

#![deny(missing_docs)]
#![forbid(unsafe_code)]

#[cfg(feature = "query")]
pub mod client;
#[cfg(feature = "query")]
pub mod fleet;
pub mod publisher;

#[cfg(feature = "query")]
pub use client::{Client, ClientBuilder, ClientError};
pub use publisher::{PublishError, ScanPublisher};
