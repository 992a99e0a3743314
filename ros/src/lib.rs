//! ROS 2 messages for rangegp: the sensor and pose messages a robot records or publishes
//! (PointCloud2, Odometry, TF) decoded from CDR, turned into the daemon's scans, and the map
//! messages planners take (GridMap, OccupancyGrid) made from its grid answers. Shared by
//! `rangegp replay` (the lab) and the live bridge (`rangegp-ros2`); no transport here.

#![forbid(unsafe_code)]
#![deny(missing_docs)]

pub mod cloud;
pub mod grid;
pub mod msg;
pub mod poses;
pub mod scan;
