//! Format-4 checkpoints (before each scan of the history kept the departure weights it was
//! fused with), read on upgrade so that a daemon updated in place keeps its map: a format-4
//! daemon fused every window answer with its map's own variance alone, which is weights 0.

use super::OldCheckpoint;
use crate::map::aggregate::world::{Cell, ScanRef, WorldParams, WorldState};
use crate::map::scales::BINS;
use serde::{Deserialize, Serialize};

/// The layout version this module reads.
pub const VERSION: u32 = 4;

/// A format-4 [`Checkpoint`](super::Checkpoint).
pub type CheckpointV4 = OldCheckpoint<WorldStateV4>;

/// A format-4 [`WorldState`]: its history without departure weights (`H` = [`ScanRefV4`]);
/// format 5's is the same with them (`H` = [`ScanRef`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldStateV4<H = ScanRefV4> {
    /// Settings.
    pub params: WorldParams,
    /// Cells by (column, row) index, sorted.
    pub cells: Vec<((i32, i32), Cell)>,
    /// Scans folded in since the aggregate was created.
    pub inserts: u64,
    /// The newest of them, oldest first.
    pub history: Vec<H>,
    /// Where the last scans' sensors stood, (x, y) in metres, oldest first.
    pub views: Vec<[f64; 2]>,
}

/// A format-3 and format-4 [`ScanRef`]: the same without departure weights.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScanRefV4 {
    /// Publisher id.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Acquisition time, nanoseconds since the Unix epoch.
    pub stamp_ns: u64,
    /// The insert it was fused in.
    pub insert: u64,
    /// How far from its sensor it was fused, metres.
    pub reach_m: f64,
}

impl From<ScanRefV4> for ScanRef {
    fn from(r: ScanRefV4) -> Self {
        Self {
            publisher_id: r.publisher_id,
            sequence: r.sequence,
            stamp_ns: r.stamp_ns,
            insert: r.insert,
            reach_m: r.reach_m,
            departure_weights: [0.0; BINS],
        }
    }
}

impl<H: Into<ScanRef>> From<WorldStateV4<H>> for WorldState {
    fn from(w: WorldStateV4<H>) -> Self {
        Self {
            params: w.params,
            cells: w.cells,
            inserts: w.inserts,
            history: w.history.into_iter().map(Into::into).collect(),
            views: w.views,
            seen: Vec::new(),
        }
    }
}
