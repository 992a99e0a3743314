//! Format-5 checkpoints (before the aggregate kept how each cell was seen and the checkpoint
//! the learnt σ scales), read on upgrade so that a daemon updated in place keeps its map: its
//! cells answer as seen squarely from the newest sensor until scans fuse them again, and σ is
//! relearnt from the next scans.

use super::format4::WorldStateV4;
use super::OldCheckpoint;
use crate::map::aggregate::world::ScanRef;

/// The layout version this module reads.
pub const VERSION: u32 = 5;

/// A format-5 [`Checkpoint`](super::Checkpoint).
pub type CheckpointV5 = OldCheckpoint<WorldStateV5>;

/// A format-5 [`WorldState`](crate::map::aggregate::world::WorldState): the same without
/// `seen`.
pub type WorldStateV5 = WorldStateV4<ScanRef>;
