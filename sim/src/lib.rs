//! Simulation for rangegp: seeded cratered terrain, an exact ray caster, an overhang scene,
//! LiDAR presets, paths and A* trajectories.
//!
//! Everything is deterministic given a seed (PCG64 generators), so tests, the demo and the
//! evaluation see the same worlds on every machine.

pub mod path;
pub mod scene;
pub mod sensor;
pub mod terrain;
pub mod trajectory;

pub use path::{level_pose, Path};
pub use scene::{Surface, Tunnel};
pub use sensor::{simulate_scan, ScannerPreset, SimRay};
pub use terrain::{CraterParams, Heightmap};
pub use trajectory::{plan_trajectories, Trajectory, TrajectoryParams};
