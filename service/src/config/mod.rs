//! Daemon configuration: TOML with defaults for every field and unknown fields refused.

mod sections;
mod validate;

pub use sections::{
    AggregateConfig, CheckpointConfig, FleetConfig, GpConfig, IngestConfig, LayersConfig, MetricsConfig,
    OnlineConfig, PriorName, QueryConfig, WindowConfig, ZenohConfig,
};

use crate::gp::hyper::{HyperBounds, OnlineHyperparameters};
use crate::gp::{JitterPolicy, Kernel};
use crate::map::local::{MapParams, PriorKind};
use crate::map::tiles::Tiling;
use rangegp_proto::keys::MapKeys;
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
            view_ceiling: g.view_ceiling,
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
        assert_eq!(field("[gp]\nview_disagreement = -0.1"), "gp.view_disagreement");
        assert_eq!(field("[gp]\nview_disagreement = 11.0"), "gp.view_disagreement");
        assert_eq!(field("map_id = \"a/b\""), "map_id");
        // Once passed validation and panicked at start.
        assert_eq!(
            field("[gp]\nkernel = { family = \"rational_quadratic\", alpha = 0.0 }"),
            "gp.kernel.alpha"
        );
        assert_eq!(field("[ingest]\npoll_interval_ms = 0"), "ingest.poll_interval_ms");
        assert_eq!(field("[checkpoint]\nkeep = 1"), "checkpoint.keep");
        assert_eq!(field("[layers]\nmax_slope_deg = 95.0"), "layers");
        assert_eq!(field("[layers]\nfootprint_radius_m = 5e-324"), "layers");
        // Once passed validation and aborted at start on an allocation of that size.
        assert_eq!(field("[window]\ncapacity = 1000000000000"), "window.capacity");
        assert_eq!(field("[ingest]\nqueue_len = 1000000000000"), "ingest.queue_len");
        assert_eq!(field("[query]\nmax_batch = 1000000000000"), "query.max_batch");
        assert_eq!(field("[query]\nthreads = 100000"), "query.threads");
        for (field_name, value) in [("max_site_robots", "0"), ("max_site_tiles", "100000000")] {
            assert_eq!(
                field(&format!("[fleet]\n{field_name} = {value}")),
                "fleet.max_site_robots / fleet.max_site_tiles"
            );
        }
        for held in ["0", "2000000"] {
            assert_eq!(
                field(&format!("[fleet]\nmax_held_departed_tiles = {held}")),
                "fleet.max_held_departed_tiles"
            );
        }
        assert_eq!(
            field("[zenoh]\nlisten = [\"not an endpoint\"]"),
            "zenoh.listen / zenoh.connect"
        );
    }

    #[test]
    fn the_shipped_deploy_config_is_valid() {
        Config::from_toml(include_str!("../../../deploy/rangegpd.toml")).expect("deploy config");
    }
}
