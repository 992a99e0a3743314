//! Daemon configuration: TOML with defaults for every field and unknown fields refused.

use crate::gp::hyper::{HyperBounds, OnlineHyperparameters};
use crate::gp::{JitterPolicy, Kernel, KernelFamily};
use crate::map::local::{MapParams, PriorKind, RangeTarget};
use crate::map::tiles::Tiling;
use rangegp_proto::keys::MapKeys;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a configuration could not be used.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// The TOML is malformed or has unknown fields.
    #[error("invalid configuration: {0}")]
    Parse(#[from] toml::de::Error),
    /// A value is out of its domain.
    #[error("invalid configuration: {0}")]
    Invalid(String),
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
}

/// Durable checkpoints of the aggregate (docs/OPERATIONS.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckpointConfig {
    /// Directory of the checkpoint files (one directory per map); unset: no checkpoints, the
    /// aggregate starts empty at every start.
    pub dir: Option<PathBuf>,
    /// A changed aggregate is written at most this often, milliseconds (and once at shutdown).
    pub interval_ms: u64,
    /// Generations kept; the older ones are the fallback when the newest is damaged.
    pub keep: usize,
}

impl Default for CheckpointConfig {
    fn default() -> Self {
        Self {
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
    /// How each local expert's σ is tied to its own data: `leave_one_out` (default; scaled by
    /// its standardised leave-one-out residuals, docs/EVALUATION.md "Calibration") or `none`.
    pub variance_calibration: crate::map::tiles::VarianceCalibration,
    /// Scale σ per source and range bin by how well the maps predicted each next scan's returns
    /// (default on; docs/EVALUATION.md "Calibration").
    pub prequential_calibration: bool,
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
    /// Fitted scans waiting for the aggregate at most; when it falls behind, the newest wins and
    /// the displaced ones are counted (the window still holds them).
    pub queue_len: usize,
    /// Tiles farther than this from the newest sensor position are evicted (bounds memory:
    /// about (2r / 2.5 m)² tiles of ≤ 0.15 MB each), metres.
    pub radius_m: f64,
    /// At most one insert per this interval, milliseconds: the aggregate takes the newest fitted
    /// scan at its own pace so that it never competes with the fitter for a whole core.
    pub min_interval_ms: u64,
}

impl Default for AggregateConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            queue_len: 1,
            radius_m: 30.0,
            min_interval_ms: 1000,
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
            variance_calibration: crate::map::tiles::VarianceCalibration::LeaveOneOut,
            prequential_calibration: true,
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

    /// Checks every value's domain.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: &str| Err(ConfigError::Invalid(m.to_owned()));
        MapKeys::new(&self.map_id).map_err(|e| ConfigError::Invalid(e.to_string()))?;
        let g = &self.gp;
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(g.kernel_variance)
            || !positive(g.length_scale)
            || !g.sphere_radius_m.is_none_or(positive)
        {
            return bad(
                "gp.kernel_variance, gp.length_scale and gp.sphere_radius_m (when set) must be positive",
            );
        }
        if !(g.nugget_m2.is_finite() && g.nugget_m2 >= 0.0) {
            return bad("gp.nugget_m2 must be finite and non-negative");
        }
        if g.max_training_rays == 0 || !(8..=4096).contains(&g.max_rays_per_tile) {
            return bad("gp.max_training_rays must be positive and gp.max_rays_per_tile in 8..=4096");
        }
        if !(0.01..=0.45).contains(&g.tile_overlap) {
            return bad("gp.tile_overlap must be in [0.01, 0.45]");
        }
        if !positive(g.sensor_height_m) || !positive(g.constant_range_m) {
            return bad("gp.sensor_height_m and gp.constant_range_m must be positive");
        }
        let o = &g.online;
        let ordered = |b: [f64; 2]| b[0] > 0.0 && b[1] > b[0] && b[1].is_finite();
        if o.iterations == 0 || o.subset_rays < 8 || !(o.smoothing > 0.0 && o.smoothing <= 1.0) {
            return bad("gp.online needs iterations ≥ 1, subset_rays ≥ 8 and smoothing in (0, 1]");
        }
        if !ordered(o.variance_bounds) || !ordered(o.length_scale_bounds) {
            return bad("gp.online bounds must be 0 < min < max");
        }
        if self.aggregate.queue_len == 0 || !positive(self.aggregate.radius_m) {
            return bad("aggregate.queue_len and aggregate.radius_m must be positive");
        }
        if !self.metrics.listen.is_empty() && self.metrics.listen.parse::<std::net::SocketAddr>().is_err() {
            return bad("metrics.listen must be host:port with an IP host (or empty to disable)");
        }
        if self.checkpoint.interval_ms == 0 || self.checkpoint.keep < 2 {
            return bad("checkpoint.interval_ms must be positive and checkpoint.keep at least 2");
        }
        if self.window.capacity == 0 {
            return bad("window.capacity must be positive");
        }
        let i = &self.ingest;
        if i.max_points == 0 || i.queue_len == 0 {
            return bad("ingest.max_points and ingest.queue_len must be positive");
        }
        if i.sequence_restart_window == 0 || i.pose_confirm_scans < 2 || i.max_retry_interval_ms == 0 {
            return bad("ingest.sequence_restart_window and ingest.max_retry_interval_ms must be positive, ingest.pose_confirm_scans at least 2");
        }
        if !(positive(i.map_bounds_m)
            && positive(i.max_speed_mps)
            && i.pose_slack_m.is_finite()
            && i.pose_slack_m >= 0.0)
        {
            return bad("ingest.map_bounds_m and ingest.max_speed_mps must be positive, ingest.pose_slack_m finite and non-negative");
        }
        if self.query.queue_deadline_ms == 0 {
            return bad("query.queue_deadline_ms must be positive");
        }
        if !positive(self.query.max_sigma_m) {
            return bad("query.max_sigma_m must be a positive number of metres");
        }
        if self.query.max_batch == 0 || self.query.threads == 0 || !positive(self.query.max_ray_range_m) {
            return bad("query.max_batch, query.threads and query.max_ray_range_m must be positive");
        }
        if !matches!(self.zenoh.mode.as_str(), "peer" | "client" | "router") {
            return bad("zenoh.mode must be peer, client or router");
        }
        Ok(())
    }

    /// The validated keys of this map.
    pub fn keys(&self) -> MapKeys {
        MapKeys::new(&self.map_id).unwrap_or_else(|e| panic!("config not validated: {e}"))
    }

    /// The iceoryx2 scan service name.
    pub fn scan_service_name(&self) -> String {
        if self.ingest.service_name.is_empty() {
            self.keys().scan_service()
        } else {
            self.ingest.service_name.clone()
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
        }
    }
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
        assert!(matches!(
            Config::from_toml("[gp]\nlength_scale = -1.0"),
            Err(ConfigError::Invalid(_))
        ));
        assert!(matches!(
            Config::from_toml("map_id = \"a/b\""),
            Err(ConfigError::Invalid(_))
        ));
    }

    #[test]
    fn the_shipped_deploy_config_is_valid() {
        Config::from_toml(include_str!("../../deploy/rangegpd.toml")).expect("deploy config");
    }
}
