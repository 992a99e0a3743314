//! The bridge's configuration: TOML with defaults for every field, unknown fields refused, every
//! value checked by [`BridgeConfig::validate`] before anything starts.

use nalgebra::Isometry3;
use rangegp_proto::msg::Layer;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Why a configuration was refused.
#[derive(Debug, thiserror::Error)]
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
        /// The field, as written in the TOML (`grid.rate_hz`).
        field: &'static str,
        /// What it must be.
        reason: String,
    },
}

/// The whole bridge configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BridgeConfig {
    /// The daemon's map id (its keys are `rangegp/<map_id>/...`).
    pub map_id: String,
    /// Zenoh endpoints of the daemon (client mode, scouting off).
    pub connect: Vec<String>,
    /// Scans out to the daemon.
    pub scans: ScansConfig,
    /// The ROS 2 side.
    pub ros: RosConfig,
    /// Grids out to ROS 2.
    pub grid: GridConfig,
}

/// How clouds become scans.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScansConfig {
    /// The daemon's iceoryx2 scan service.
    pub service: String,
    /// Publisher id in the scan headers.
    pub publisher_id: u64,
    /// Largest cloud, in points.
    pub max_points: usize,
    /// Returns at or beyond this range are no-returns, metres.
    pub max_range_m: f64,
    /// Range noise σ per metre of range.
    pub range_noise_per_m: f64,
    /// The lidar's pose on the base: x, y, z (metres), roll, pitch, yaw (degrees).
    pub sensor_to_base: [f64; 6],
    /// Longest wait of a cloud for the odometry after its stamp, seconds.
    pub pose_wait_s: f64,
}

/// Reliability a subscription asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reliability {
    /// Matches every publisher; samples may be lost (ROS 2's sensor-data QoS).
    BestEffort,
    /// Matches only reliable publishers; lost fragments are sent again.
    Reliable,
}

/// ROS 2 (DDS) side.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RosConfig {
    /// DDS domain (ROS_DOMAIN_ID).
    pub domain_id: u16,
    /// Local addresses DDS may use (discovery, multicast joins, advertised locators); empty:
    /// every interface. `["127.0.0.1"]` keeps the bridge on this machine.
    pub only_networks: Vec<std::net::IpAddr>,
    /// Node name.
    pub node_name: String,
    /// sensor_msgs/PointCloud2 topic.
    pub cloud_topic: String,
    /// Reliability of the cloud subscription.
    pub cloud_reliability: Reliability,
    /// nav_msgs/Odometry topic (the base's pose in the map frame, REP-105).
    pub odom_topic: String,
    /// grid_map_msgs/GridMap topic.
    pub grid_map_topic: String,
    /// nav_msgs/OccupancyGrid topic (published when `cost` is among the grid layers).
    pub costmap_topic: String,
    /// Frame of the published grids; empty: the odometry's `header.frame_id`.
    pub map_frame: String,
}

/// The grids published around the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridConfig {
    /// Grids per second.
    pub rate_hz: f64,
    /// Side of the square around the robot, metres.
    pub size_m: f64,
    /// Cell side, metres.
    pub resolution_m: f64,
    /// Derived layers beside elevation and variance (wire names: `slope`, `risk`, `cost`, ...).
    pub layers: Vec<Layer>,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        Self {
            map_id: "default".into(),
            connect: vec!["tcp/127.0.0.1:7447".into()],
            scans: ScansConfig::default(),
            ros: RosConfig::default(),
            grid: GridConfig::default(),
        }
    }
}

impl Default for ScansConfig {
    fn default() -> Self {
        Self {
            service: "rangegp/default/scans".into(),
            publisher_id: 0x726f_7332,
            max_points: 262_144,
            max_range_m: 100.0,
            range_noise_per_m: 0.002,
            sensor_to_base: [0.0; 6],
            pose_wait_s: 0.5,
        }
    }
}

impl Default for RosConfig {
    fn default() -> Self {
        Self {
            domain_id: 0,
            only_networks: Vec::new(),
            node_name: "rangegp_bridge".into(),
            cloud_topic: "/points".into(),
            cloud_reliability: Reliability::BestEffort,
            odom_topic: "/odom".into(),
            grid_map_topic: "/rangegp/grid_map".into(),
            costmap_topic: "/rangegp/costmap".into(),
            map_frame: String::new(),
        }
    }
}

impl Default for GridConfig {
    fn default() -> Self {
        Self {
            rate_hz: 2.0,
            size_m: 20.0,
            resolution_m: 0.2,
            layers: vec![
                Layer::Slope,
                Layer::SlopeSigma,
                Layer::Step,
                Layer::Risk,
                Layer::Cost,
            ],
        }
    }
}

/// `name` (the value of `field`) as a ROS 2 topic name.
pub fn topic_name(field: &'static str, name: &str) -> Result<ros2_client::Name, ConfigError> {
    ros2_client::Name::parse(name).map_err(|_| ConfigError::Invalid {
        field,
        reason: "must be a valid ROS 2 topic name (e.g. /points)".into(),
    })
}

/// DDS domains ROS 2 can use (the RTPS port formula runs out above this).
const MAX_DOMAIN_ID: u16 = 232;

/// Most cells a published grid may hold.
const MAX_GRID_CELLS: f64 = 1_000_000.0;

impl BridgeConfig {
    /// Reads and validates `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml(&text)
    }

    /// Parses and validates TOML text.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let config: Self = toml::from_str(text)?;
        config.validate()?;
        Ok(config)
    }

    /// Checks every value; the first one out of its domain is the error.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &'static str, reason: &str| {
            Err(ConfigError::Invalid {
                field,
                reason: reason.into(),
            })
        };
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if self.map_id.is_empty() || self.map_id.contains(['/', '*', '$', '?', '#']) {
            return bad("map_id", "must be a non-empty key chunk (no / * $ ? #)");
        }
        if self.connect.is_empty() {
            return bad("connect", "must name at least one Zenoh endpoint");
        }
        if self.scans.service.is_empty() {
            return bad("scans.service", "must not be empty");
        }
        if self.scans.max_points == 0 {
            return bad("scans.max_points", "must be positive");
        }
        if !positive(self.scans.max_range_m) {
            return bad("scans.max_range_m", "must be a positive number of metres");
        }
        if !(self.scans.range_noise_per_m.is_finite() && self.scans.range_noise_per_m >= 0.0) {
            return bad("scans.range_noise_per_m", "must be finite and not negative");
        }
        if !self.scans.sensor_to_base.iter().all(|v| v.is_finite()) {
            return bad("scans.sensor_to_base", "must be six finite numbers");
        }
        if !(self.scans.pose_wait_s.is_finite() && (0.0..=10.0).contains(&self.scans.pose_wait_s)) {
            return bad("scans.pose_wait_s", "must be in [0, 10] seconds");
        }
        if self.ros.domain_id > MAX_DOMAIN_ID {
            return bad("ros.domain_id", "must be at most 232");
        }
        let topics = [
            ("ros.cloud_topic", &self.ros.cloud_topic),
            ("ros.odom_topic", &self.ros.odom_topic),
            ("ros.grid_map_topic", &self.ros.grid_map_topic),
            ("ros.costmap_topic", &self.ros.costmap_topic),
        ];
        for (field, topic) in topics {
            topic_name(field, topic)?;
        }
        self.node_name()?;
        if !(positive(self.grid.rate_hz) && self.grid.rate_hz <= 50.0) {
            return bad("grid.rate_hz", "must be in (0, 50]");
        }
        if !positive(self.grid.resolution_m) || !positive(self.grid.size_m) {
            return bad("grid", "size_m and resolution_m must be positive metres");
        }
        if (self.grid.size_m / self.grid.resolution_m).powi(2) > MAX_GRID_CELLS {
            return bad("grid.size_m", "holds more than 1e6 cells at this resolution");
        }
        Ok(())
    }

    /// The ROS 2 node name.
    pub fn node_name(&self) -> Result<ros2_client::NodeName, ConfigError> {
        ros2_client::NodeName::new("/", &self.ros.node_name).map_err(|_| ConfigError::Invalid {
            field: "ros.node_name",
            reason: "must be a valid ROS 2 node name".into(),
        })
    }

    /// The lidar's pose on the base.
    pub fn sensor_to_base(&self) -> Isometry3<f64> {
        rangegp_ros::poses::mount(self.scans.sensor_to_base)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_validate_and_bad_values_name_their_field() {
        BridgeConfig::default().validate().expect("defaults are valid");
        let c = BridgeConfig::from_toml(
            "map_id = \"rover\"\n[grid]\nlayers = [\"slope\", \"cost\"]\n[ros]\nonly_networks = [\"127.0.0.1\"]\n",
        )
        .expect("valid");
        assert_eq!(c.grid.layers, [Layer::Slope, Layer::Cost]);
        assert_eq!(c.ros.only_networks.len(), 1);
        assert!(matches!(
            BridgeConfig::from_toml("[grid]\nrate_hz = 0.0\n"),
            Err(ConfigError::Invalid {
                field: "grid.rate_hz",
                ..
            })
        ));
        assert!(matches!(
            BridgeConfig::from_toml("[ros]\ncloud_topic = \"no spaces\"\n"),
            Err(ConfigError::Invalid {
                field: "ros.cloud_topic",
                ..
            })
        ));
        assert!(matches!(
            BridgeConfig::from_toml("[grid]\nsize = 3.0\n"),
            Err(ConfigError::Parse(_))
        ));
    }
}
