//! Format-4 checkpoints (before each scan of the history kept the departure weights it was
//! fused with), read on upgrade so that a daemon updated in place keeps its map: a format-4
//! daemon fused every window answer with its map's own variance alone, which is weights 0.

use super::Checkpoint;
use crate::map::aggregate::world::{Cell, ScanRef, WorldParams, WorldState};
use crate::map::scales::BINS;
use serde::{Deserialize, Serialize};

/// The layout version this module reads.
pub const VERSION: u32 = 4;

/// A format-4 [`Checkpoint`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointV4 {
    /// When it was taken, nanoseconds since the Unix epoch.
    pub created_unix_ns: u64,
    /// Kernel variance the fitter used, m².
    pub kernel_variance: f64,
    /// Kernel length scale the fitter used.
    pub length_scale: f64,
    /// The aggregate.
    pub world: WorldStateV4,
}

/// A format-4 [`WorldState`]: its history without departure weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldStateV4 {
    /// Settings.
    pub params: WorldParams,
    /// Cells by (column, row) index, sorted.
    pub cells: Vec<((i32, i32), Cell)>,
    /// Scans folded in since the aggregate was created.
    pub inserts: u64,
    /// The newest of them, oldest first.
    pub history: Vec<ScanRefV4>,
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

impl From<CheckpointV4> for Checkpoint {
    fn from(c: CheckpointV4) -> Self {
        Self {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: WorldState {
                params: c.world.params,
                cells: c.world.cells,
                inserts: c.world.inserts,
                history: c.world.history.into_iter().map(ScanRef::from).collect(),
                views: c.world.views,
                seen: Vec::new(),
            },
            scales: None,
        }
    }
}
