//! Aggregate maps: everything seen, in one model (ARCHITECTURE.md "Aggregate").
//!
//! - [`pose_gp::PoseAugmentedGp`]: seed 000 §III-B, one GP over (θ, φ, x, y, z, γ), kept to
//!   reproduce the paper's number.
//! - [`world::WorldAggregate`]: the project's map, tiled elevation-GP experts over fused
//!   per-cell heights predicted by each scan's range GP, updated incrementally.
//! - [`sources::SiteSources`]: on a site daemon, whose cells (which robots') its answers fuse.

pub mod ledger;
pub mod pose_gp;
pub mod returns;
pub mod sources;
pub mod world;

use super::local::{HeightEstimate, LocalRangeMap};
use crate::gp::CholeskyError;
use crate::scan::ScanInput;
use thiserror::Error;

/// Why a scan could not be folded into an aggregate.
#[derive(Debug, Error, PartialEq)]
pub enum AggregateError {
    /// A covariance matrix could not be factored.
    #[error(transparent)]
    Cholesky(#[from] CholeskyError),
    /// The aggregate holds its configured maximum.
    #[error("aggregate is full: {limit} points")]
    Full {
        /// The limit, points.
        limit: usize,
    },
}

/// A map of everything seen so far, fed one scan at a time.
pub trait Aggregate {
    /// Short name for logs and tables.
    fn name(&self) -> &'static str;
    /// Folds in one scan: its validated rays and the local range map fitted to them.
    fn insert(&mut self, scan: &ScanInput, local: &LocalRangeMap) -> Result<(), AggregateError>;
    /// Surface height at map (x, y), or `None` where the aggregate has seen nothing.
    fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate>;
    /// Points (training rays or fused cells) it holds.
    fn len(&self) -> usize;
    /// Whether it holds nothing yet.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
