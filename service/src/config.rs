//! Daemon configuration: TOML with defaults for every field and unknown fields refused.

use crate::gp::hyper::{HyperBounds, OnlineHyperparameters};
use crate::gp::{JitterPolicy, Kernel, KernelFamily};
use crate::map::local::{MapParams, PriorKind, RangeTarget};
use crate::map::tiles::Tiling;
use rangegp_proto::keys::MapKeys;
use rangegp_proto::msg::RobotModel;
use rangegp_transport::zenoh_config;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a configuration could not be used.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}")]
    Read {
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// The TOML is malformed or has unknown fields.
    #[error("invalid configuration")]
    Parse(#[from] toml::de::Error),
    /// A value is out of its domain.
    #[error("invalid configuration: {field} {reason}")]
    Invalid {
        /// The field, as written in the TOML (`gp.length_scale`).
        field: &'static str,
        /// What it must be.
        reason: String,
    },
}

/// The whole daemon configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Map id: names the Zenoh keys (`rangegp/<map_id>/...`) and the default scan service.
    pub map_id: String,
    /// Scan intake over iceoryx2.
    pub ingest: IngestConfig,
    /// GP model.
    pub gp: GpConfig,
    /// Rolling window of local maps.
    pub window: WindowConfig,
    /// The world-frame aggregate of everything seen.
    pub aggregate: AggregateConfig,
    /// Zenoh session.
    pub zenoh: ZenohConfig,
    /// Query limits.
    pub query: QueryConfig,
    /// Prometheus metrics.
    pub metrics: MetricsConfig,
    /// Durable checkpoints of the aggregate.
    pub checkpoint: CheckpointConfig,
    /// The robot the planner layers (risk, cost) judge by, when a request names none.
    pub layers: LayersConfig,
    /// Fleets: a robot's tiles into a site's key space, or a site daemon (docs/FLEET.md).
    pub fleet: FleetConfig,
}

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
    /// Site: how long the start waits for the storage's tiles, milliseconds.
    pub storage_wait_ms: u64,
}

impl Default for FleetConfig {
    fn default() -> Self {
        Self {
            role: rangegp_proto::fleet::FleetRole::Robot,
            site: String::new(),
            tile_period_ms: 1000,
            max_kib_per_s: 512,
            storage_wait_ms: 3000,
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
    /// Directory of this map's files; unset: the state directory ([`default_state_dir`]) joined
    /// with the map id.
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

impl Default for Config {
    fn default() -> Self {
        Self {
            map_id: "default".into(),
            ingest: IngestConfig::default(),
            gp: GpConfig::default(),
            window: WindowConfig::default(),
            aggregate: AggregateConfig::default(),
            zenoh: ZenohConfig::default(),
            query: QueryConfig::default(),
            metrics: MetricsConfig::default(),
            checkpoint: CheckpointConfig::default(),
            layers: LayersConfig::default(),
            fleet: FleetConfig::default(),
        }
    }
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

impl Config {
    /// Parses and validates TOML text.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let config: Config = toml::from_str(text)?;
        config.validate()?;
        Ok(config)
    }

    /// Reads, parses and validates a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml(&text)
    }

    /// Checks every value's domain; the error names the first field out of it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        let ordered = |b: [f64; 2]| b[0] > 0.0 && b[1] > b[0] && b[1].is_finite();
        let (g, o, i, q, a) = (
            &self.gp,
            &self.gp.online,
            &self.ingest,
            &self.query,
            &self.aggregate,
        );
        let alpha_ok = match g.kernel {
            KernelFamily::RationalQuadratic { alpha } => positive(alpha),
            _ => true,
        };
        let service_ok =
            i.service_name.is_empty() || iceoryx2::prelude::ServiceName::new(&i.service_name).is_ok();
        let listen_ok =
            self.metrics.listen.is_empty() || self.metrics.listen.parse::<std::net::SocketAddr>().is_ok();
        let checks: [(bool, &'static str, &str); 41] = [
            (
                MapKeys::new(&self.map_id).is_ok(),
                "map_id",
                "must be a non-empty key-expression chunk (no '/', '*', '$', '?', '#')",
            ),
            (
                self.fleet.site.is_empty() || MapKeys::new(&self.fleet.site).is_ok(),
                "fleet.site",
                "must be empty (no fleet) or a key-expression chunk like map_id",
            ),
            (
                (10..=600_000).contains(&self.fleet.tile_period_ms),
                "fleet.tile_period_ms",
                "must be in 10..=600000",
            ),
            (
                self.fleet.max_kib_per_s > 0 && self.fleet.storage_wait_ms <= 600_000,
                "fleet.max_kib_per_s / fleet.storage_wait_ms",
                "must be positive / at most 600000",
            ),
            (
                service_ok,
                "ingest.service_name",
                "must be empty (the default) or a valid iceoryx2 service name",
            ),
            (i.max_points > 0, "ingest.max_points", "must be positive"),
            (
                i.poll_interval_ms > 0,
                "ingest.poll_interval_ms",
                "must be positive",
            ),
            (
                i.cleanup_interval_s > 0,
                "ingest.cleanup_interval_s",
                "must be positive",
            ),
            (i.queue_len > 0, "ingest.queue_len", "must be positive"),
            (
                i.sequence_restart_window > 0,
                "ingest.sequence_restart_window",
                "must be positive",
            ),
            (
                positive(i.map_bounds_m),
                "ingest.map_bounds_m",
                "must be a positive number of metres",
            ),
            (
                positive(i.max_speed_mps),
                "ingest.max_speed_mps",
                "must be positive",
            ),
            (
                non_negative(i.pose_slack_m),
                "ingest.pose_slack_m",
                "must be finite and non-negative",
            ),
            (
                i.pose_confirm_scans >= 2,
                "ingest.pose_confirm_scans",
                "must be at least 2",
            ),
            (
                i.max_retry_interval_ms > 0,
                "ingest.max_retry_interval_ms",
                "must be positive",
            ),
            (alpha_ok, "gp.kernel.alpha", "must be positive and finite"),
            (
                positive(g.kernel_variance),
                "gp.kernel_variance",
                "must be positive",
            ),
            (positive(g.length_scale), "gp.length_scale", "must be positive"),
            (
                g.sphere_radius_m.is_none_or(positive),
                "gp.sphere_radius_m",
                "must be positive when set",
            ),
            (
                non_negative(g.nugget_m2),
                "gp.nugget_m2",
                "must be finite and non-negative",
            ),
            (
                g.max_training_rays > 0,
                "gp.max_training_rays",
                "must be positive",
            ),
            (
                (8..=4096).contains(&g.max_rays_per_tile),
                "gp.max_rays_per_tile",
                "must be in 8..=4096",
            ),
            (
                (0.01..=0.45).contains(&g.tile_overlap),
                "gp.tile_overlap",
                "must be in [0.01, 0.45]",
            ),
            (
                positive(g.sensor_height_m),
                "gp.sensor_height_m",
                "must be positive",
            ),
            (
                positive(g.constant_range_m),
                "gp.constant_range_m",
                "must be positive",
            ),
            (o.iterations > 0, "gp.online.iterations", "must be at least 1"),
            (
                o.smoothing > 0.0 && o.smoothing <= 1.0,
                "gp.online.smoothing",
                "must be in (0, 1]",
            ),
            (o.subset_rays >= 8, "gp.online.subset_rays", "must be at least 8"),
            (
                ordered(o.variance_bounds),
                "gp.online.variance_bounds",
                "must be [min, max] with 0 < min < max",
            ),
            (
                ordered(o.length_scale_bounds),
                "gp.online.length_scale_bounds",
                "must be [min, max] with 0 < min < max",
            ),
            (self.window.capacity > 0, "window.capacity", "must be positive"),
            (a.queue_len > 0, "aggregate.queue_len", "must be positive"),
            (
                a.cpu_share > 0.0 && a.cpu_share <= 1.0,
                "aggregate.cpu_share",
                "must be in (0, 1]",
            ),
            (
                (1..=65_536).contains(&a.ledger_mib),
                "aggregate.ledger_mib",
                "must be 1 to 65536",
            ),
            (
                positive(a.radius_m),
                "aggregate.radius_m",
                "must be a positive number of metres",
            ),
            (
                matches!(self.zenoh.mode.as_str(), "peer" | "client" | "router"),
                "zenoh.mode",
                "must be peer, client or router",
            ),
            (
                q.max_batch > 0 && q.threads > 0,
                "query.max_batch and query.threads",
                "must be positive",
            ),
            (
                positive(q.max_ray_range_m),
                "query.max_ray_range_m",
                "must be a positive number of metres",
            ),
            (
                q.queue_deadline_ms > 0,
                "query.queue_deadline_ms",
                "must be positive",
            ),
            (
                positive(q.max_sigma_m),
                "query.max_sigma_m",
                "must be a positive number of metres",
            ),
            (
                listen_ok,
                "metrics.listen",
                "must be host:port with an IP host, or empty to disable",
            ),
        ];
        let invalid = |field: &'static str, reason: &str| ConfigError::Invalid {
            field,
            reason: reason.to_owned(),
        };
        if let Some((_, field, reason)) = checks.iter().find(|(ok, _, _)| !ok) {
            return Err(invalid(field, reason));
        }
        if let Some(reason) = self.layers.robot().problem() {
            return Err(invalid("layers", reason));
        }
        if !self.fleet.site.is_empty() && !self.aggregate.enabled {
            return Err(invalid(
                "fleet.site",
                "needs aggregate.enabled: the tiles a robot publishes are its aggregate's",
            ));
        }
        if self.checkpoint.interval_ms == 0 {
            return Err(invalid("checkpoint.interval_ms", "must be positive"));
        }
        if self.checkpoint.keep < 2 {
            return Err(invalid("checkpoint.keep", "must be at least 2"));
        }
        // The endpoints are checked by building the session configuration they describe.
        if self.zenoh.config_file.is_none() {
            zenoh_config(
                &self.zenoh.mode,
                &self.zenoh.listen,
                &self.zenoh.connect,
                self.zenoh.multicast_scouting,
            )
            .map_err(|e| ConfigError::Invalid {
                field: "zenoh.listen / zenoh.connect",
                reason: format!("are not valid endpoints ({})", e.source),
            })?;
        }
        Ok(())
    }

    /// The directory of this map's checkpoints and paged tiles, `None` when they are off (or
    /// no state directory can be named: no `$STATE_DIRECTORY`, `$XDG_STATE_HOME` nor `$HOME`).
    pub fn checkpoint_dir(&self) -> Option<PathBuf> {
        if !self.checkpoint.enabled {
            return None;
        }
        self.checkpoint
            .dir
            .clone()
            .or_else(|| default_state_dir().map(|d| d.join(&self.map_id)))
    }

    /// The validated keys of this map.
    pub fn keys(&self) -> MapKeys {
        MapKeys::new(&self.map_id).unwrap_or_else(|e| panic!("config not validated: {e}"))
    }

    /// The site this daemon's tiles go to (robot) or come from (site), when in a fleet.
    pub fn fleet_site(&self) -> Option<MapKeys> {
        match self.fleet.role {
            rangegp_proto::fleet::FleetRole::Site => Some(self.keys()),
            rangegp_proto::fleet::FleetRole::Robot => MapKeys::new(&self.fleet.site).ok(),
        }
    }

    /// The iceoryx2 scan service name.
    pub fn scan_service_name(&self) -> String {
        if self.ingest.service_name.is_empty() {
            self.keys().scan_service()
        } else {
            self.ingest.service_name.clone()
        }
    }

    /// The bounds `[ingest]` sets on every scan it validates.
    pub fn validation_limits(&self) -> crate::ingest::ValidationLimits {
        let i = &self.ingest;
        crate::ingest::ValidationLimits {
            max_points: i.max_points,
            max_future_ns: i.max_future_ms.saturating_mul(1_000_000),
            learn_noise_floor: i.learn_noise_floor,
        }
    }

    /// The pose plausibility limits of `[ingest]`.
    pub fn pose_limits(&self) -> crate::ingest::PoseLimits {
        let i = &self.ingest;
        crate::ingest::PoseLimits {
            bounds_m: i.map_bounds_m,
            max_speed_mps: i.max_speed_mps,
            slack_m: i.pose_slack_m,
            confirm_scans: i.pose_confirm_scans,
        }
    }

    /// Online hyperparameter learner starting from the configured kernel.
    pub fn online_hyperparameters(&self) -> OnlineHyperparameters {
        let o = &self.gp.online;
        let bounds = HyperBounds {
            variance: (o.variance_bounds[0], o.variance_bounds[1]),
            length_scale: (o.length_scale_bounds[0], o.length_scale_bounds[1]),
        };
        OnlineHyperparameters::new(self.map_params().kernel, bounds, o.iterations, o.smoothing)
    }

    /// Parameters for fitting local maps.
    pub fn map_params(&self) -> MapParams {
        let g = &self.gp;
        MapParams {
            kernel: Kernel::new(g.kernel, g.kernel_variance, g.length_scale),
            sphere_radius_m: g.sphere_radius_m,
            nugget_m2: g.nugget_m2,
            max_training_rays: g.max_training_rays,
            tiling: Tiling {
                max_rays_per_tile: g.max_rays_per_tile,
                overlap: g.tile_overlap,
            },
            prior: match g.prior {
                PriorName::FlatGround => PriorKind::FlatGround {
                    sensor_height_m: g.sensor_height_m,
                },
                PriorName::ConstantRange => PriorKind::ConstantRange {
                    range_m: g.constant_range_m,
                },
            },
            target: g.target,
            jitter: JitterPolicy::default(),
            variance_calibration: g.variance_calibration,
            index_data: g.prequential_calibration,
        }
    }
}

/// Where the daemon keeps its state when `checkpoint.dir` is unset: systemd's
/// `$STATE_DIRECTORY` (the unit's `StateDirectory=`), else `$XDG_STATE_HOME/rangegp`, else
/// `$HOME/.local/state/rangegp`.
pub fn default_state_dir() -> Option<PathBuf> {
    let var = |name: &str| {
        std::env::var_os(name)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    var("STATE_DIRECTORY")
        .or_else(|| var("XDG_STATE_HOME").map(|d| d.join("rangegp")))
        .or_else(|| var("HOME").map(|h| h.join(".local/state/rangegp")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_through_toml() {
        let text = toml::to_string(&Config::default()).expect("serialise");
        assert_eq!(Config::from_toml(&text).expect("parse"), Config::default());
        assert_eq!(
            Config::from_toml("").expect("empty is defaults"),
            Config::default()
        );
    }

    #[test]
    fn unknown_fields_and_bad_values_are_refused() {
        assert!(matches!(
            Config::from_toml("mapid = \"x\""),
            Err(ConfigError::Parse(_))
        ));
        let field = |toml: &str| match Config::from_toml(toml) {
            Err(ConfigError::Invalid { field, .. }) => field,
            other => panic!("{toml:?} gave {other:?}"),
        };
        assert_eq!(field("[gp]\nlength_scale = -1.0"), "gp.length_scale");
        assert_eq!(field("map_id = \"a/b\""), "map_id");
        // Once passed validation and panicked at start.
        assert_eq!(
            field("[gp]\nkernel = { family = \"rational_quadratic\", alpha = 0.0 }"),
            "gp.kernel.alpha"
        );
        assert_eq!(field("[ingest]\npoll_interval_ms = 0"), "ingest.poll_interval_ms");
        assert_eq!(field("[checkpoint]\nkeep = 1"), "checkpoint.keep");
        assert_eq!(field("[layers]\nmax_slope_deg = 95.0"), "layers");
        assert_eq!(
            field("[zenoh]\nlisten = [\"not an endpoint\"]"),
            "zenoh.listen / zenoh.connect"
        );
    }

    #[test]
    fn the_shipped_deploy_config_is_valid() {
        Config::from_toml(include_str!("../../deploy/rangegpd.toml")).expect("deploy config");
    }
}
