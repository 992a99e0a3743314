//! The daemon's counters: what it took in, refused, answered and how fast.

use serde::{Deserialize, Serialize};

/// Ask for the daemon's counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
}

/// How many scans were rejected for one reason.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RejectionCount {
    /// Stable snake_case reason (see `docs/PROTOCOL.md`).
    pub reason: String,
    /// Scans rejected for it since start.
    pub count: u64,
}

/// Kernel hyperparameters in use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HyperparametersInfo {
    /// Kernel name.
    pub kernel: String,
    /// Kernel variance σ², square metres.
    pub variance: f64,
    /// Length scale on the range sphere, metres of chord.
    pub length_scale: f64,
    /// Noise variance added to every training ray on top of the sensor model, square metres.
    pub nugget: f64,
}

/// Percentiles of one latency over the daemon's most recent samples (a bounded ring).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LatencySummary {
    /// Samples since start.
    pub count: u64,
    /// Median of the recent samples, milliseconds.
    pub p50_ms: f64,
    /// 90th percentile, milliseconds.
    pub p90_ms: f64,
    /// 99th percentile, milliseconds.
    pub p99_ms: f64,
    /// Largest recent sample, milliseconds.
    pub max_ms: f64,
}

/// Server-side query latencies (receipt by a worker to reply sent), one per query kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct QueryLatencies {
    /// `query/elevation`.
    pub elevation: LatencySummary,
    /// `query/variance`.
    pub variance: LatencySummary,
    /// `query/ray`.
    pub ray: LatencySummary,
    /// `query/grid`.
    pub grid: LatencySummary,
    /// `query/view`.
    pub view: LatencySummary,
    /// `query/slope`.
    pub slope: LatencySummary,
    /// `query/sources`.
    pub sources: LatencySummary,
    /// `status`.
    pub status: LatencySummary,
}

/// The scan intake: whether it is subscribed, and what its bookkeeping did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct IngestInfo {
    /// Whether the daemon holds its iceoryx2 subscriber (false while it retries with back-off).
    pub connected: bool,
    /// Why the last attempt to subscribe failed (`None` once subscribed).
    pub error: Option<String>,
    /// Failed attempts to subscribe since start.
    pub retries: u64,
    /// Sources whose sequence number jumped beyond the restart window (counted anew, not
    /// locked out).
    pub publisher_restarts: u64,
    /// Publishers followed to a new place after agreeing scans (a relocalisation).
    pub relocations: u64,
}

/// The world aggregate's size and counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct AggregateInfo {
    /// Whether the daemon folds scans into an aggregate.
    pub enabled: bool,
    /// Fused cells held now.
    pub cells: u64,
    /// Fitted tiles held now.
    pub tiles: u64,
    /// Radius around the newest sensor position beyond which tiles are evicted, metres.
    pub radius_m: f64,
    /// Scans folded in since start.
    pub inserts: u64,
    /// Fitted scans displaced from the aggregate's queue, not fused (the window still has them).
    pub skipped: u64,
    /// Inserts that failed (the aggregate kept its previous state).
    pub failed: u64,
    /// Tiles evicted for being beyond `radius_m`.
    pub evicted_tiles: u64,
    /// Reach each scan is fused out to now, metres (shorter than 10 m when a fast sensor would
    /// otherwise outrun `aggregate.cpu_share`; 0 before the first insert).
    pub reach_m: f64,
    /// Tiles written to the site map on disk when they left the radius (checkpoints on).
    pub paged_out: u64,
    /// Tiles read back from the site map when the robot returned.
    pub paged_in: u64,
    /// Tile pages that could not be written or read.
    pub page_failures: u64,
    /// Fused scans whose cells the ledger keeps: what a pose correction can move.
    pub ledger_scans: u64,
    /// Memory the ledger holds, MiB (`aggregate.ledger_mib` bounds it).
    pub ledger_mb: f64,
    /// Cells replaced by scans that disagreed with them (published as change events).
    pub changed_cells: u64,
}

/// The daemon's state and counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Map id served.
    pub map_id: String,
    /// Seconds since the daemon started.
    pub uptime_s: f64,
    /// Scans taken from shared memory.
    pub scans_received: u64,
    /// Scans that passed validation and were fitted into the window.
    pub scans_accepted: u64,
    /// Scans rejected (sum over reasons).
    pub scans_rejected: u64,
    /// Rejections by reason (every reason listed, zeros included).
    pub rejections: Vec<RejectionCount>,
    /// Valid scans dropped because fitting fell behind (newest wins).
    pub scans_skipped: u64,
    /// Online hyperparameter updates applied since start.
    pub hyperparameter_updates: u64,
    /// Local experts whose Cholesky factorisation needed diagonal jitter since start.
    pub jittered_tiles: u64,
    /// Scans lost in transport (sequence numbers that never arrived), summed over publishers.
    pub sequence_gaps: u64,
    /// The scan intake.
    pub ingest: IngestInfo,
    /// Local maps in the window now.
    pub window_len: u32,
    /// Window capacity.
    pub window_capacity: u32,
    /// The world aggregate.
    pub aggregate: AggregateInfo,
    /// Pose corrections applied since start.
    pub corrections: u64,
    /// Hyperparameters in use.
    pub hyperparameters: HyperparametersInfo,
    /// Fit of one scan into its local map.
    pub fit_ms: LatencySummary,
    /// Scan taken from shared memory to its map answering queries.
    pub scan_to_queryable_ms: LatencySummary,
    /// One aggregate insert (cells, tile refits, eviction).
    pub aggregate_insert_ms: LatencySummary,
    /// Query handling per kind.
    pub query_ms: QueryLatencies,
    /// Queries answered successfully.
    pub queries_ok: u64,
    /// Queries answered with an error.
    pub queries_failed: u64,
    /// Batch queries answered `overloaded` after waiting past the queue deadline.
    pub queries_expired: u64,
    /// Replies dropped because too many were being sent at once (a client not reading).
    pub replies_dropped: u64,
    /// Resident set size of the daemon process, MiB (`None` where the OS does not say).
    pub rss_mb: Option<f64>,
    /// The daemon's part in a fleet: tiles published (robot) or assembled (site).
    pub fleet: crate::fleet::FleetInfo,
}
