//! Format-3 checkpoints (before the aggregate kept where its last scans stood), read on upgrade
//! so that a daemon updated in place keeps its map: the positions start empty, and the first
//! scan after the restart counts as a whole view.

use super::format4::ScanRefV4;
use super::OldCheckpoint;
use crate::map::aggregate::world::{Cell, ScanRef, WorldParams, WorldState};
use serde::{Deserialize, Serialize};

/// The layout version this module reads.
pub const VERSION: u32 = 3;

/// A format-3 [`Checkpoint`](super::Checkpoint).
pub type CheckpointV3 = OldCheckpoint<WorldStateV3>;

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

impl From<WorldStateV3> for WorldState {
    fn from(w: WorldStateV3) -> Self {
        Self {
            params: w.params,
            cells: w.cells,
            inserts: w.inserts,
            history: w.history.into_iter().map(ScanRef::from).collect(),
            views: Vec::new(),
            seen: Vec::new(),
        }
    }
}
