//! The live heap bytes of a process whose binary installs the counting allocator: the system's
//! allocator wrapped by `cap`, which counts the bytes allocated and not yet freed.
//!
//! A memory bar that compares resident set sizes also measures the allocator: glibc keeps freed
//! memory in per-thread arenas and hands it back late or never, so RSS rises in steps of several
//! MiB that say nothing of what the program holds (docs/EVALUATION.md "Site map"). The bytes
//! allocated and not yet freed are what a leak grows. Only the binaries that need the figure
//! install it (`rangegp-eval`, the site map's test): the benchmarks time the daemon's own
//! allocator.
//!
//! ```
//! #[global_allocator]
//! static HEAP: rangegp_lab::heap::Counting = rangegp_lab::heap::counting();
//!
//! fn main() {
//!     rangegp_lab::heap::register(&HEAP);
//!     // This example runs as its own single-threaded process, so the count is exact.
//!     let before = rangegp_lab::heap::live_bytes().expect("registered");
//!     let block = vec![1u8; 64 << 20];
//!     assert_eq!(rangegp_lab::heap::live_bytes(), Some(before + (64 << 20)));
//!     drop(block);
//!     assert_eq!(rangegp_lab::heap::live_bytes(), Some(before));
//! }
//! ```

use cap::Cap;
use std::alloc::System;
use std::sync::OnceLock;

/// The system allocator, counted.
pub type Counting = Cap<System>;

/// A counting allocator with no limit, for a binary's `#[global_allocator]` static.
pub const fn counting() -> Counting {
    Cap::new(System, usize::MAX)
}

static REGISTERED: OnceLock<&'static Counting> = OnceLock::new();

/// Makes `allocator`, the binary's global allocator, the one [`live_bytes`] reads (the first
/// registration stands).
pub fn register(allocator: &'static Counting) {
    let _ = REGISTERED.set(allocator);
}

/// Bytes allocated and not yet freed by this process, or `None` when its binary registered no
/// counting allocator.
pub fn live_bytes() -> Option<usize> {
    REGISTERED.get().map(|a| a.allocated())
}

/// [`live_bytes`] in MiB.
pub fn live_mib() -> Option<f64> {
    live_bytes().map(|b| b as f64 / (1024.0 * 1024.0))
}
