//! Simulation for rangegp: seeded cratered terrain, an exact ray caster, LiDAR presets, paths.
//!
//! Everything is deterministic given a seed (PCG64 generators), so tests, the demo and the
//! evaluation see the same worlds on every machine.

pub mod path;
pub mod sensor;
pub mod terrain;

pub use path::{level_pose, Path};
pub use sensor::{simulate_scan, ScannerPreset, SimRay};
pub use terrain::{CraterParams, Heightmap};
