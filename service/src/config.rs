//! Daemon configuration: TOML with defaults for every field and unknown fields refused.

use crate::gp::{JitterPolicy, Kernel, KernelFamily};
use crate::map::local::{MapParams, PriorKind};
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
    /// Zenoh session.
    pub zenoh: ZenohConfig,
    /// Query limits.
    pub query: QueryConfig,
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
}

/// GP model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GpConfig {
    /// Kernel family: `{ family = "matern32" }` (default), `matern52`, `squared_exponential`,
    /// `rational_quadratic` (with `alpha`), `arc_sine`.
    pub kernel: KernelFamily,
    /// Kernel variance σ² (seed 000 Table I: 2.302).
    pub kernel_variance: f64,
    /// Length scale on the range sphere, metres of chord (seed 000 Table I: 1.206).
    pub length_scale: f64,
    /// Radius of the range sphere, metres (seed 000: R_max = 10).
    pub sphere_radius_m: f64,
    /// Noise variance added to every training ray on top of the sensor model, m².
    pub nugget_m2: f64,
    /// Training rays per scan at most (even stride over the returned rays).
    pub max_training_rays: usize,
    /// Prior mean: `flat_ground` or `constant_range`.
    pub prior: PriorName,
    /// Sensor height above the ground for the flat-ground prior, metres.
    pub sensor_height_m: f64,
    /// Range of the constant-range prior, metres.
    pub constant_range_m: f64,
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
}

impl Default for Config {
    fn default() -> Self {
        Self {
            map_id: "default".into(),
            ingest: IngestConfig::default(),
            gp: GpConfig::default(),
            window: WindowConfig::default(),
            zenoh: ZenohConfig::default(),
            query: QueryConfig::default(),
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
        }
    }
}

impl Default for GpConfig {
    fn default() -> Self {
        Self {
            kernel: KernelFamily::Matern32,
            kernel_variance: 2.302,
            length_scale: 1.206,
            sphere_radius_m: 10.0,
            nugget_m2: 1e-6,
            max_training_rays: 400,
            prior: PriorName::FlatGround,
            sensor_height_m: 0.75,
            constant_range_m: 10.0,
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
        if !positive(g.kernel_variance) || !positive(g.length_scale) || !positive(g.sphere_radius_m) {
            return bad("gp.kernel_variance, gp.length_scale and gp.sphere_radius_m must be positive");
        }
        if !(g.nugget_m2.is_finite() && g.nugget_m2 >= 0.0) {
            return bad("gp.nugget_m2 must be finite and non-negative");
        }
        if !(1..=4096).contains(&g.max_training_rays) {
            return bad("gp.max_training_rays must be in 1..=4096");
        }
        if !positive(g.sensor_height_m) || !positive(g.constant_range_m) {
            return bad("gp.sensor_height_m and gp.constant_range_m must be positive");
        }
        if self.window.capacity == 0 {
            return bad("window.capacity must be positive");
        }
        if self.ingest.max_points == 0 || self.ingest.queue_len == 0 {
            return bad("ingest.max_points and ingest.queue_len must be positive");
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

    /// Parameters for fitting local maps.
    pub fn map_params(&self) -> MapParams {
        let g = &self.gp;
        MapParams {
            kernel: Kernel::new(g.kernel, g.kernel_variance, g.length_scale),
            sphere_radius_m: g.sphere_radius_m,
            nugget_m2: g.nugget_m2,
            max_training_rays: g.max_training_rays,
            prior: match g.prior {
                PriorName::FlatGround => PriorKind::FlatGround {
                    sensor_height_m: g.sensor_height_m,
                },
                PriorName::ConstantRange => PriorKind::ConstantRange {
                    range_m: g.constant_range_m,
                },
            },
            jitter: JitterPolicy::default(),
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
