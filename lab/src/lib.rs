//! rangegp-lab: everything around the daemon that does not ship to a robot.
//!
//! - [`demo`]: the daemon on embedded defaults with a simulated rover and planner.
//! - [`eval`]: accuracy and calibration against simulated ground truth (`rangegp-eval`).
//! - [`bench`](mod@bench): GP, hyperparameter and query benchmarks (`rangegp-bench`).
//! - [`load`]: the load test behind `rangegp load` (scan generator + planners + echo baseline).
//! - [`scangen`]: simulated scans in the wire layout.
//! - [`cli`]: number parsers the command lines share.
//! - [`dem`]: terrains from digital elevation model files (`--dem`), for the evaluations and
//!   the scan generator.
//! - [`certs`]: a CA and certificates for trying the shipped mutual-TLS configuration.
//! - [`plot`]: the one renderer of every picture (demo, grid, evaluation).
//! - [`pictures`]: a grid's layers and a view's ranges as pictures (`rangegp query ... --png`).
//! - [`fleet`]: a Zenoh router with a memory storage of a site's tiles (fleet test and simulation).
//! - [`heap`]: the live heap bytes of a process whose binary installs the counting allocator.

#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod bench;
pub mod certs;
pub mod cli;
pub mod dem;
pub mod demo;
pub mod eval;
pub mod fleet;
pub mod heap;
pub mod load;
pub mod pictures;
pub mod plot;
pub mod replay;
pub mod scangen;
