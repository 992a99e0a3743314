//! Gaussian-process machinery: kernels, the range sphere, Cholesky with jitter, exact GPs.
//!
//! Equations follow seed 000 §III-A and Rasmussen & Williams ch. 2 (docs/ARCHITECTURE.md "The
//! maps").
//! Numerical failure is a `Result`; misuse (mismatched lengths) is a panic at the caller.

pub mod cholesky;
pub mod exact;
pub mod hyper;
pub mod kernel;
pub mod likelihood;
pub mod points;
pub mod sphere;
pub mod vector;

pub use cholesky::{factor_with_jitter, CholeskyError, JitterPolicy};
pub use exact::ExactGp;
pub use kernel::{Kernel, KernelFamily};
pub use points::Points;
