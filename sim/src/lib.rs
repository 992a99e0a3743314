//! Simulation for rangegp: seeded cratered terrain and a family of other terrains (fractal
//! relief, boulders, terraces), an exact ray caster, an overhang scene, LiDAR presets with
//! their noise models, paths and A* trajectories.
//!
//! Everything is deterministic given a seed (PCG64 generators), so tests, the demo and the
//! evaluation see the same worlds on every machine.

#![forbid(unsafe_code)]
#![deny(missing_docs)]

pub mod dem;
pub mod drift;
pub mod family;
pub mod path;
pub mod scene;
pub mod sensor;
pub mod terrain;
pub mod trajectory;

pub use dem::{Dem, DemError};
pub use drift::OdometryDrift;
pub use family::{family, TerrainKind, TerrainSpec};
pub use path::{chassis_pose, level_pose, Path};
pub use scene::{Surface, Tunnel};
pub use sensor::{simulate_scan, simulate_sweep, ScannerPreset, SimRay, SweepMotion};
pub use terrain::{CraterParams, Heightmap};
pub use trajectory::{plan_trajectories, Trajectory, TrajectoryParams};
