//! Maps built from scans: the per-scan local range map, its prior, the rolling window, queries.

pub mod aggregate;
pub mod calibration;
pub mod correction;
pub mod correlation;
pub mod data_index;
pub mod elevation_gp;
pub mod embedding;
pub mod fov;
pub mod grid;
pub mod layers;
pub mod local;
pub mod plane;
pub mod prior;
pub mod query;
pub mod relief;
pub mod root;
pub mod scales;
#[cfg(test)]
mod test_support;
pub mod tiles;
pub mod view;
pub mod window;

pub use local::{FitError, LocalRangeMap};
pub use prior::Prior;
pub use window::{MapSnapshot, Window};
