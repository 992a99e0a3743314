//! The state every thread of the daemon shares, named for what it is.

use crate::gp::Kernel;
use crate::map::correction::{Correction, CorrectionLog};
use crate::map::MapSnapshot;
use crate::metrics::Metrics;
use arc_swap::ArcSwap;
use rangegp_proto::keys::MapKeys;
use rangegp_proto::msg::{CorrectionReply, RobotModel};
use std::collections::VecDeque;
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The daemon's shared state: the maps queries see, counters, and the settings the query side
/// and status need. The fitter and aggregate threads publish into it, the query server, the
/// checkpoint writer and the metrics exporter read it.
#[derive(Debug)]
pub struct DaemonState {
    /// Current maps, swapped atomically by the fitter.
    pub snapshot: ArcSwap<MapSnapshot>,
    /// Shared counters.
    pub metrics: Arc<Metrics>,
    /// Map id served.
    pub keys: MapKeys,
    /// Largest batch accepted.
    pub max_batch: usize,
    /// Longest ray accepted, metres.
    pub max_ray_range_m: f64,
    /// Threads for one large batch.
    pub batch_threads: usize,
    /// Window capacity (for status).
    pub window_capacity: usize,
    /// Kernel the fitter uses now (updated by online learning).
    pub kernel: Arc<ArcSwap<Kernel>>,
    /// Noise variance added to every training ray (for status).
    pub nugget_m2: f64,
    /// Eviction radius of the aggregate when it is enabled (for status).
    pub aggregate_radius_m: Option<f64>,
    /// Longest wait of a batch query for a worker before it is answered `overloaded`.
    pub queue_deadline: Duration,
    /// Pose corrections: applied so far, and waiting.
    pub corrections: CorrectionDesk,
    /// The robot the planner layers judge by when a request names none (`[layers]`).
    pub robot: RobotModel,
    /// The daemon's part in a fleet, for status (the tile publisher or the site assembler
    /// updates it).
    pub fleet: Mutex<rangegp_proto::fleet::FleetInfo>,
    /// A site daemon's record of whose cells its answers fuse (`None` on a robot: its own
    /// aggregate's cells are its sources).
    pub site_sources: arc_swap::ArcSwapOption<crate::map::aggregate::sources::SiteSources>,
}

/// A correction waiting for the aggregate thread.
#[derive(Debug)]
pub struct CorrectionJob {
    /// The validated correction.
    pub correction: Arc<Correction>,
    /// When its request arrived.
    pub arrived: Instant,
    /// Where the outcome goes (the query worker waiting to reply; an error says why nothing
    /// changed).
    pub reply: SyncSender<Result<CorrectionReply, String>>,
}

/// Corrections waiting at most; a request beyond is answered `overloaded`.
pub const CORRECTIONS_WAITING: usize = 8;

/// Pose corrections: the log every publisher of maps brings them up with, and the queue to the
/// aggregate thread, which applies them (`None` without an aggregate: the window is corrected
/// by the query worker itself).
#[derive(Debug, Default)]
pub struct CorrectionDesk {
    /// Corrections applied (or being applied), numbered.
    pub log: Mutex<CorrectionLog>,
    /// Waiting for the aggregate thread.
    pub waiting: Option<Mutex<VecDeque<CorrectionJob>>>,
}
