//! Format-5 checkpoints (before the aggregate kept how each cell was seen and the checkpoint
//! the learnt σ scales), read on upgrade so that a daemon updated in place keeps its map: its
//! cells answer as seen squarely from the newest sensor until scans fuse them again, and σ is
//! relearnt from the next scans.

use super::Checkpoint;
use crate::map::aggregate::world::{Cell, ScanRef, WorldParams, WorldState};
use serde::{Deserialize, Serialize};

/// The layout version this module reads.
pub const VERSION: u32 = 5;

/// A format-5 [`Checkpoint`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointV5 {
    /// When it was taken, nanoseconds since the Unix epoch.
    pub created_unix_ns: u64,
    /// Kernel variance the fitter used, m².
    pub kernel_variance: f64,
    /// Kernel length scale the fitter used.
    pub length_scale: f64,
    /// The aggregate.
    pub world: WorldStateV5,
}

/// A format-5 [`WorldState`]: the same without `seen`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldStateV5 {
    /// Settings.
    pub params: WorldParams,
    /// Cells by (column, row) index, sorted.
    pub cells: Vec<((i32, i32), Cell)>,
    /// Scans folded in since the aggregate was created.
    pub inserts: u64,
    /// The newest of them, oldest first.
    pub history: Vec<ScanRef>,
    /// Where the last scans' sensors stood, (x, y) in metres, oldest first.
    pub views: Vec<[f64; 2]>,
}

impl From<CheckpointV5> for Checkpoint {
    fn from(c: CheckpointV5) -> Self {
        Self {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: WorldState {
                params: c.world.params,
                cells: c.world.cells,
                inserts: c.world.inserts,
                history: c.world.history,
                views: c.world.views,
                seen: Vec::new(),
            },
            scales: None,
        }
    }
}
