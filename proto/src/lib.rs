//! The wire contract of rangegp, shared by the daemon, the client and foreign-language peers.
//!
//! - [`scan`]: `#[repr(C)]` shared-memory types published over iceoryx2 (header + point slice).
//! - [`msg`]: serde request / reply types for the Zenoh queries, each carrying [`PROTOCOL_VERSION`].
//! - [`codec`]: the one encode / decode pair (bincode 2 by default, JSON on request).
//! - [`keys`]: key-expression and service-name builders.
//! - [`fleet`]: aggregate tiles in a site's key space, for site daemons and fleet status.
//!
//! The byte layout and the rules are written out in `docs/PROTOCOL.md`.

#![forbid(unsafe_code)]
#![deny(missing_docs)]

pub mod codec;
pub mod fleet;
pub mod keys;
pub mod msg;
pub mod scan;

/// Version of the whole contract (shared-memory layout and query messages); bumped on any change.
pub const PROTOCOL_VERSION: u32 = 9;

/// An error and its sources on one line, `: `-separated: what logs, status replies and C
/// callers show (a `Display` alone drops the cause a user can act on).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}
