//! Format-3 checkpoints (before the aggregate kept where its last scans stood), read on upgrade
//! so that a daemon updated in place keeps its map: the positions start empty, and the first
//! scan after the restart counts as a whole view.

use super::format4::ScanRefV4;
use super::Checkpoint;
use crate::map::aggregate::world::{Cell, ScanRef, WorldParams, WorldState};
use serde::{Deserialize, Serialize};

/// The layout version this module reads.
pub const VERSION: u32 = 3;

/// A format-3 [`Checkpoint`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointV3 {
    /// When it was taken, nanoseconds since the Unix epoch.
    pub created_unix_ns: u64,
    /// Kernel variance the fitter used, m².
    pub kernel_variance: f64,
    /// Kernel length scale the fitter used.
    pub length_scale: f64,
    /// The aggregate.
    pub world: WorldStateV3,
}

/// A format-3 [`WorldState`]: the same without `views`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldStateV3 {
    /// Settings.
    pub params: WorldParams,
    /// Cells by (column, row) index, sorted.
    pub cells: Vec<((i32, i32), Cell)>,
    /// Scans folded in since the aggregate was created.
    pub inserts: u64,
    /// The newest of them, oldest first.
    pub history: Vec<ScanRefV4>,
}

impl From<CheckpointV3> for Checkpoint {
    fn from(c: CheckpointV3) -> Self {
        Self {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: WorldState {
                params: c.world.params,
                cells: c.world.cells,
                inserts: c.world.inserts,
                history: c.world.history.into_iter().map(ScanRef::from).collect(),
                views: Vec::new(),
                seen: Vec::new(),
            },
            scales: None,
        }
    }
}
