//! rangegp-ros2: the bridge between a ROS 2 robot and the rangegp daemon, in one process.
//!
//! It subscribes `sensor_msgs/PointCloud2` and `nav_msgs/Odometry` over ROS 2's DDS transport
//! (ros2-client on RustDDS: pure Rust, no ROS installation), publishes each cloud as a scan to
//! the daemon over iceoryx2, and publishes the grid around the robot (elevation, variance and the
//! planner layers configured) as `grid_map_msgs/GridMap` and the costmap as
//! `nav_msgs/OccupancyGrid`. Topics, QoS and frames: docs/INTEROP.md "Live ROS 2".

#![forbid(unsafe_code)]
#![deny(missing_docs)]

pub mod bridge;
pub mod config;

pub use bridge::{Bridge, BridgeStats, StartError};
pub use config::{BridgeConfig, ConfigError};
