//! The sections of the daemon configuration, each with its defaults.

use crate::gp::KernelFamily;
use crate::map::local::RangeTarget;
use rangegp_proto::msg::RobotModel;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// A daemon's part in a fleet (docs/FLEET.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FleetConfig {
    /// `robot` (a sensor; publishes its tiles when `site` is set) or `site` (no sensor: answers
    /// for every robot's tiles under `rangegp/<map_id>/tiles/**`).
    pub role: rangegp_proto::fleet::FleetRole,
    /// Robot: the site whose key space its aggregate tiles are published into (`rangegp/<site>/
    /// tiles/<map_id>/...`); empty: no fleet. A site daemon's site is its own `map_id`.
    pub site: String,
    /// Robot: a changed tile is published at most once per period, milliseconds.
    pub tile_period_ms: u64,
    /// Robot: tile bytes published per second at most, KiB; tiles beyond wait for the next period,
    /// oldest change first.
    pub max_kib_per_s: u64,
    /// Robot: tiles that left its radius with an unsent change and no page on disk (checkpoints
    /// off) wait with their cells, at most this many (about 3 KiB each); beyond, the oldest
    /// change is forgotten and counted (`status.fleet.tiles_dropped`).
    pub max_held_departed_tiles: u64,
    /// Site: how long the start waits for the storage's tiles, milliseconds.
    pub storage_wait_ms: u64,
    /// Site: robots it holds tiles of at most; a new robot's tiles beyond are refused and counted
    /// (`status.fleet.tiles_refused`).
    pub max_site_robots: u64,
    /// Site: tiles it holds at most, summed over robots (about 3 KiB each, and about 0.15 MB for
    /// each distinct tile's fitted expert); new tiles beyond are refused and counted, updates of
    /// held ones still go in.
    pub max_site_tiles: u64,
}

impl Default for FleetConfig {
    fn default() -> Self {
        Self {
            role: rangegp_proto::fleet::FleetRole::Robot,
            site: String::new(),
            tile_period_ms: 1000,
            max_kib_per_s: 512,
            max_held_departed_tiles: 16_384,
            storage_wait_ms: 3000,
            max_site_robots: 256,
            max_site_tiles: 65_536,
        }
    }
}

/// The robot model of the planner layers (docs/PROTOCOL.md "Planner layers").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LayersConfig {
    /// Radius of the disc the robot stands on, metres: slope, roughness and step are taken over it.
    pub footprint_radius_m: f64,
    /// Steepest slope the robot climbs, degrees.
    pub max_slope_deg: f64,
    /// Highest step the robot climbs, metres.
    pub max_step_m: f64,
    /// Risk at and above which a cell is lethal (costmap 100).
    pub lethal_risk: f64,
}

impl Default for LayersConfig {
    fn default() -> Self {
        Self {
            footprint_radius_m: 0.3,
            max_slope_deg: 20.0,
            max_step_m: 0.2,
            lethal_risk: 0.5,
        }
    }
}

impl LayersConfig {
    /// The robot model on the wire.
    pub fn robot(&self) -> RobotModel {
        RobotModel {
            footprint_radius_m: self.footprint_radius_m,
            max_slope_deg: self.max_slope_deg,
            max_step_m: self.max_step_m,
            lethal_risk: self.lethal_risk,
        }
    }
}

/// Durable checkpoints of the aggregate (docs/OPERATIONS.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckpointConfig {
    /// Keep the aggregate on disk: checkpoints of the tiles around the robot and the tiles it
    /// left behind (the site map). Off: the aggregate starts empty at every start and tiles
    /// beyond `aggregate.radius_m` are forgotten.
    pub enabled: bool,
    /// Directory of this map's files; unset: the state directory
    /// ([`default_state_dir`](super::default_state_dir)) joined with the map id.
    pub dir: Option<PathBuf>,
    /// A changed aggregate is written at most this often, milliseconds (and once at shutdown).
    pub interval_ms: u64,
    /// Generations kept; the older ones are the fallback when the newest is damaged.
    pub keep: usize,
}

impl Default for CheckpointConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            dir: None,
            interval_ms: 250,
            keep: 2,
        }
    }
}

/// Prometheus metrics endpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MetricsConfig {
    /// `host:port` serving `GET /metrics` (loopback by default; port 0 picks one); empty: off.
    /// A port that cannot be bound is logged and the daemon runs without metrics.
    pub listen: String,
}

impl Default for MetricsConfig {
    fn default() -> Self {
        Self {
            listen: "127.0.0.1:9464".into(),
        }
    }
}

/// Scan intake.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IngestConfig {
    /// iceoryx2 service name; empty means `rangegp/<map_id>/scans`.
    pub service_name: String,
    /// Scans with more points are rejected (`too_many_points`).
    pub max_points: usize,
    /// How often the ingest thread polls for samples, milliseconds.
    pub poll_interval_ms: u64,
    /// How often dead iceoryx2 nodes are cleaned up, seconds.
    pub cleanup_interval_s: u64,
    /// Scans waiting for the fitter; beyond it the oldest waiting scan is skipped (newest wins).
    pub queue_len: usize,
    /// Scans stamped later than this ahead of the daemon's clock are rejected
    /// (`future_timestamp`), milliseconds.
    pub max_future_ms: u64,
    /// A sequence number further than this from the source's last accepted one (either way)
    /// restarts its bookkeeping (counted as a publisher restart) instead of locking it out.
    pub sequence_restart_window: u64,
    /// Largest |x|, |y|, |z| of a sensor position, metres (`implausible_pose` beyond).
    pub map_bounds_m: f64,
    /// Fastest plausible motion between two scans of one publisher, m/s (`implausible_pose`).
    pub max_speed_mps: f64,
    /// Jump allowed on top of the speed limit (localisation noise), metres.
    pub pose_slack_m: f64,
    /// Consecutive scans that must agree on a new place before a relocalised publisher is
    /// followed there (the ones before it are rejected `implausible_pose`).
    pub pose_confirm_scans: u32,
    /// Longest wait between attempts to subscribe when the scan service cannot be opened
    /// (slots taken, incompatible settings), milliseconds.
    pub max_retry_interval_ms: u64,
    /// Measure each scan's range noise floor from its returns (second differences along its
    /// rings; needs ring and column indices): the noise a header's per-metre coefficient cannot
    /// state (a VLP-16's 3 cm at any range). Off: the header's model alone.
    pub learn_noise_floor: bool,
}

/// GP model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GpConfig {
    /// Kernel family: `{ family = "matern32" }` (default), `matern52`, `squared_exponential`,
    /// `rational_quadratic` (with `alpha`), `arc_sine`.
    pub kernel: KernelFamily,
    /// Kernel variance σ² of the amplitude-scaled residual, m² (`rangegp-eval local`: 5e-4).
    pub kernel_variance: f64,
    /// Length scale between kernel inputs (ground footprints under the flat-ground prior, points
    /// of the range sphere under the constant-range prior), metres (`rangegp-eval local`: 0.97).
    pub length_scale: f64,
    /// What the GP models along a ray: `range` (seed 000) or `inverse_range` (planes are linear).
    pub target: RangeTarget,
    /// Footprints are capped at this range, metres (seed 000: R_max = 10). Unset (the default):
    /// each scan's own maximum range, so kernel distances stay ground distances out to the
    /// sensor's reach (a 10 m cap made far rings look adjacent: σ at 20–40 m 3–10× too small).
    pub sphere_radius_m: Option<f64>,
    /// Noise variance added to every training ray on top of the sensor model, m².
    pub nugget_m2: f64,
    /// Training rays per scan at most (even stride over the returned rays).
    pub max_training_rays: usize,
    /// Training rays per local expert (tile) at most.
    pub max_rays_per_tile: usize,
    /// Overlap of neighbouring tiles, as a fraction of a tile's core on each side.
    pub tile_overlap: f64,
    /// Prior mean: `flat_ground` or `constant_range`.
    pub prior: PriorName,
    /// Sensor height above the ground for the flat-ground prior, metres.
    pub sensor_height_m: f64,
    /// Range of the constant-range prior, metres.
    pub constant_range_m: f64,
    /// Online hyperparameter learning.
    pub online: OnlineConfig,
    /// How each local expert's σ is tied to its own data: `local_leave_one_out` (default; scaled
    /// by the standardised leave-one-out residuals of the rays near each query),
    /// `leave_one_out` (one scale per expert) or `none` (docs/EVALUATION.md "Calibration").
    pub variance_calibration: crate::map::tiles::VarianceCalibration,
    /// Scale σ per source and range bin by how well the maps predicted each next scan's returns
    /// (default on; docs/EVALUATION.md "Calibration").
    pub prequential_calibration: bool,
    /// Add to window answers' σ the relief their data cannot see, learnt from each scan's own
    /// returns by the distance to the nearest datum (needs the prequential calibration, which
    /// learns it always: planner layers bound their σ with it). Off by default: it narrows
    /// window rays' σ on gentle terrain and widens the quick matrix's 68 % coverage
    /// (docs/EVALUATION.md "Calibration", step 6).
    pub unseen_relief: bool,
    /// Weight, in σ per metre of disagreement, of the other window maps' disagreement with a
    /// window answer that lies over 1 m from its map's data (the smallest distance, along
    /// another map's ray, between that map's surface and the answered point): a map's smooth
    /// continuation into a shadow is not what other views see there. 0 turns it off; needs the
    /// prequential calibration (docs/EVALUATION.md "Calibration", step 9).
    pub view_disagreement: f64,
    /// End each map's view half a ring above its scan's highest return in each azimuth, so that
    /// an answer a map would carry into the sky there (where its rays came back empty) is
    /// refused and the next map answers; it never moves an answer. On by default: window RMSE
    /// 0.234 → 0.207 m on the full calibration matrix, ground past a cliff that the maps answer
    /// 5 m off without it refused (docs/EVALUATION.md "Calibration", steps 29–30).
    pub view_ceiling: bool,
}

/// Online hyperparameter learning (a thread of its own, never on the ingest path).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OnlineConfig {
    /// Learn σ² and ℓ from the scans (starting from `kernel_variance` and `length_scale`). Off by
    /// default: the likelihood optimum is calibrated for the bulk of the surface but not for
    /// occluded ground, where elevation errors concentrate (docs/ARCHITECTURE.md).
    pub enabled: bool,
    /// L-BFGS iterations per scan.
    pub iterations: u64,
    /// Fraction of the way the estimate moves towards each scan's result (log space).
    pub smoothing: f64,
    /// Rays per scan used for an update (even stride).
    pub subset_rays: usize,
    /// Bounds of σ² (min, max).
    pub variance_bounds: [f64; 2],
    /// Bounds of ℓ (min, max), metres (the units of `gp.length_scale`).
    pub length_scale_bounds: [f64; 2],
}

impl Default for OnlineConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            iterations: 3,
            smoothing: 0.1,
            subset_rays: 128,
            variance_bounds: [1e-6, 1e1],
            length_scale_bounds: [0.05, 50.0],
        }
    }
}

/// Prior mean names in the configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PriorName {
    /// Flat ground below the sensor.
    FlatGround,
    /// Constant range.
    ConstantRange,
}

/// Rolling window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WindowConfig {
    /// Local maps kept.
    pub capacity: usize,
}

/// The world-frame aggregate (docs/ARCHITECTURE.md "Aggregates").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AggregateConfig {
    /// Fold fitted scans into the aggregate (its own thread) and answer from it where no window
    /// map sees a point.
    pub enabled: bool,
    /// Fitted scans waiting for the aggregate at most. It fuses every scan that waited in one
    /// insert, so this is reached only when it falls this many scans behind; then the oldest
    /// waiting scan is displaced and counted as not fused (the window still holds it).
    pub queue_len: usize,
    /// Tiles farther than this from the newest sensor position are evicted (bounds memory:
    /// about (2r / 2.5 m)² tiles of ≤ 0.15 MB each), metres.
    pub radius_m: f64,
    /// Share of one core the aggregate may spend fusing, in (0, 1]: each scan is fused out to
    /// the reach this allows at the sensor's rate (all of 10 m when it can; 3 m at least).
    pub cpu_share: f64,
    /// Memory for the ledger of each fused scan's cells, MiB: what a pose correction moves. A
    /// scan takes 8 bytes per cell of the square its reach spans (a 6 m reach: 18 KiB); the
    /// oldest leave first, and a correction naming a forgotten scan counts it not correctable.
    pub ledger_mib: usize,
    /// Detect moving objects and changes: cells whose returns disagree with what earlier
    /// returns measured beyond both σ are replaced, not averaged, and announced on
    /// `events/change`; predictions that disagree are left out. Off by default: under odometry
    /// drift the map disagrees with itself where the robot returns, and a later pose correction
    /// does not restore cells replaced then (docs/EVALUATION.md "World").
    pub change_detection: bool,
}

impl Default for AggregateConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            queue_len: 64,
            radius_m: 30.0,
            cpu_share: 0.5,
            ledger_mib: 128,
            change_detection: false,
        }
    }
}

/// Zenoh session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohConfig {
    /// `peer`, `client` or `router`.
    pub mode: String,
    /// Endpoints to listen on (loopback by default).
    pub listen: Vec<String>,
    /// Endpoints to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting (off by default: it reaches every interface).
    pub multicast_scouting: bool,
    /// A full Zenoh JSON5 configuration file; when set, the fields above are ignored.
    pub config_file: Option<PathBuf>,
}

/// Query limits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QueryConfig {
    /// Largest batch (points or rays) in one request.
    pub max_batch: usize,
    /// Longest ray, metres.
    pub max_ray_range_m: f64,
    /// Threads evaluating one large batch.
    pub threads: usize,
    /// A batch query that waited longer than this for a worker is answered `overloaded`,
    /// milliseconds.
    pub queue_deadline_ms: u64,
    /// Elevation and variance answers whose σ exceeds this are refused `too_uncertain`
    /// rather than given as a number, metres.
    pub max_sigma_m: f64,
}

impl Default for IngestConfig {
    fn default() -> Self {
        Self {
            service_name: String::new(),
            max_points: 262_144,
            poll_interval_ms: 2,
            cleanup_interval_s: 5,
            queue_len: 2,
            max_future_ms: 1000,
            sequence_restart_window: 100_000,
            map_bounds_m: 100_000.0,
            max_speed_mps: 20.0,
            pose_slack_m: 2.0,
            pose_confirm_scans: 3,
            max_retry_interval_ms: 10_000,
            learn_noise_floor: true,
        }
    }
}

impl Default for GpConfig {
    fn default() -> Self {
        Self {
            kernel: KernelFamily::Matern32,
            kernel_variance: 5e-4,
            length_scale: 0.97,
            target: RangeTarget::Range,
            sphere_radius_m: None,
            nugget_m2: 1e-6,
            max_training_rays: 8_192,
            max_rays_per_tile: 128,
            tile_overlap: 0.15,
            prior: PriorName::FlatGround,
            sensor_height_m: 0.75,
            constant_range_m: 10.0,
            online: OnlineConfig::default(),
            variance_calibration: crate::map::tiles::VarianceCalibration::LocalLeaveOneOut,
            prequential_calibration: true,
            unseen_relief: false,
            view_ceiling: true,
            view_disagreement: crate::map::calibration::DEFAULT_VIEW_DISAGREEMENT,
        }
    }
}

impl Default for WindowConfig {
    fn default() -> Self {
        Self { capacity: 16 }
    }
}

impl Default for ZenohConfig {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: Vec::new(),
            multicast_scouting: false,
            config_file: None,
        }
    }
}

impl Default for QueryConfig {
    fn default() -> Self {
        Self {
            max_batch: 65_536,
            max_ray_range_m: 200.0,
            threads: 2,
            queue_deadline_ms: 500,
            max_sigma_m: 1.0,
        }
    }
}
