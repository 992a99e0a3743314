//! What the map tells its listeners (map updates, changed cells) and pose corrections.

use serde::{Deserialize, Serialize};

/// Published on `rangegp/<map>/events/map` each time a scan's map starts answering queries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapUpdate {
    /// Protocol version of the event.
    pub version: u32,
    /// Publisher of the scan.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Its acquisition time, ns since the Unix epoch.
    pub stamp_ns: u64,
    /// Scan taken from shared memory to queryable, milliseconds (daemon clock).
    pub latency_ms: f64,
    /// Local maps in the window now.
    pub window_len: u32,
}

/// One aggregate cell replaced because new scans disagreed with it beyond both σ.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChangedCell {
    /// The cell's centre in the map frame, metres.
    pub x_m: f64,
    /// The cell's centre y, metres.
    pub y_m: f64,
    /// Height before, metres.
    pub old_z_m: f64,
    /// Its σ, metres.
    pub old_sigma_m: f64,
    /// Height now, metres (`None`: the cell left the map: rays passed below what it held and
    /// the scan has no height of its own there; the next scan that does fills it).
    pub new_z_m: Option<f64>,
    /// Its σ, metres.
    pub new_sigma_m: Option<f64>,
}

/// Published on `rangegp/<map>/events/change` when a scan's evidence replaced aggregate cells
/// (something appeared, left or moved there).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeEvent {
    /// Protocol version of the event.
    pub version: u32,
    /// Publisher of the scan that confirmed the change.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Its acquisition time, ns since the Unix epoch.
    pub stamp_ns: u64,
    /// The cell side, metres.
    pub cell_m: f64,
    /// The cells replaced.
    pub cells: Vec<ChangedCell>,
}

/// A rigid transform of the map frame: `p ↦ rotation · p + translation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rigid {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation, unit quaternion (x, y, z, w).
    pub rotation_xyzw: [f64; 4],
}

/// One correction of past scans' poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseCorrection {
    /// The corrected pose of one scan, named by its publisher and sequence.
    Scan {
        /// Publisher id of the scan.
        publisher_id: u64,
        /// Its sequence number.
        sequence: u64,
        /// The sensor's corrected pose in the map frame.
        pose: Rigid,
    },
    /// A loop closure or a relocalisation: `transform` applied on the left (in the map frame)
    /// to the pose of every scan taken in `[from_stamp_ns, until_stamp_ns]`, of one publisher
    /// or of all.
    Transform {
        /// Only this publisher's scans (`None`: every publisher's).
        publisher_id: Option<u64>,
        /// First acquisition time moved, ns since the Unix epoch.
        from_stamp_ns: u64,
        /// Last acquisition time moved, ns (`u64::MAX`: every scan since `from_stamp_ns`).
        until_stamp_ns: u64,
        /// The correction: a pose `P` becomes `transform · P`.
        transform: Rigid,
    },
}

/// Corrected poses for past scans, applied in order (`rangegp/<map>/corrections`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CorrectionRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// The corrections.
    pub corrections: Vec<PoseCorrection>,
}

/// What a correction changed; sent once queries see the corrected map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CorrectionReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Corrections applied since the daemon started, this one included.
    pub generation: u64,
    /// Window maps moved.
    pub window_maps_moved: u32,
    /// Scans moved in the aggregate.
    pub aggregate_scans_moved: u32,
    /// Scans the corrections name that the aggregate fused but no longer keeps the data to move
    /// (older than its ledger, or fused before a restart): their cells stay where they were.
    pub not_correctable: u32,
    /// Aggregate cells whose height changed, added or removed (in memory and on disk).
    pub cells_changed: u64,
    /// Aggregate tiles refitted in memory.
    pub tiles_refitted: u32,
    /// Tiles rewritten in the site map on disk.
    pub pages_rewritten: u32,
    /// From the request's arrival to the corrected map answering queries, milliseconds.
    pub apply_ms: f64,
}
