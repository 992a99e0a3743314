//! What one aggregate cell's returns measured, read through their planes
//! ([`crate::map::plane`]).

use super::ledger::Cell;

/// What returns measured in a cell: their planes' heights at its centre fused, and the newest
/// plane's slope (a ray's height is compared with the plane where it crosses the cell).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured {
    /// Fused height at the centre.
    pub cell: Cell,
    /// Rise over run along x and y.
    pub slope: [f64; 2],
}

impl Measured {
    /// Height at offset (dx, dy) from the cell's centre, metres.
    pub fn at(&self, dx: f64, dy: f64) -> f64 {
        self.cell.z + self.slope[0] * dx + self.slope[1] * dy
    }
}
