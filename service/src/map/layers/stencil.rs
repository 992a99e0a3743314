//! The cells of a robot's footprint on a grid, and how their height errors correlate.

use super::{footprint_reach, plane_weights, terrain_gradient, LayerModel, MAX_FOOTPRINT_REACH};
use crate::map::scales::ErrorCorrelation;

/// The cells of a footprint on a grid and the correlation of their height errors.
#[derive(Debug, Clone)]
pub struct Stencil {
    /// Cell offsets (column, row) from the centre, within the footprint.
    pub(super) offsets: Vec<(i32, i32)>,
    /// Offsets in metres.
    pub(super) uv: Vec<(f64, f64)>,
    /// Error correlation between offsets a and b at `a * n + b`.
    pub(super) corr: Vec<f64>,
    /// The terrain's semivariogram γ at the distance between offsets a and b, at `a * n + b`
    /// (zero where it is not learnt).
    pub(super) gamma: Vec<f64>,
    /// Whether γ is learnt at every distance of the footprint (the bounds apply).
    pub(super) bounded: bool,
    /// The terrain's own gradient covariance (xx, xy, yy) with every footprint cell answered
    /// (most cells' case; see [`cell_layers`]).
    pub(super) terrain_gradient: [f64; 3],
    /// The terrain's mean square difference across the footprint's diameter, 2γ(2r), m².
    pub(super) step_bound: f64,
    /// Largest |offset| along either axis, cells.
    pub(super) reach: i32,
}

impl Stencil {
    /// The footprint of `model` sampled at `resolution_m` (positive, and at least the radius
    /// over [`MAX_FOOTPRINT_REACH`]; panics otherwise: callers validate requests first).
    pub fn new(model: &LayerModel, resolution_m: f64) -> Self {
        assert!(
            resolution_m > 0.0 && model.robot.footprint_radius_m / resolution_m <= MAX_FOOTPRINT_REACH,
            "a footprint of at most {MAX_FOOTPRINT_REACH} cells' radius"
        );
        let r = model.robot.footprint_radius_m;
        let reach = footprint_reach(r, resolution_m) as i32;
        let mut offsets = Vec::new();
        for dj in -reach..=reach {
            for di in -reach..=reach {
                let d2 = f64::from(di * di + dj * dj) * resolution_m * resolution_m;
                if d2 <= r * r * (1.0 + 1e-9) {
                    offsets.push((di, dj));
                }
            }
        }
        let uv: Vec<(f64, f64)> = offsets
            .iter()
            .map(|&(di, dj)| (f64::from(di) * resolution_m, f64::from(dj) * resolution_m))
            .collect();
        let n = uv.len();
        let correlation = ErrorCorrelation {
            length_m: model.error_length_m,
        };
        let mut corr = vec![0.0; n * n];
        let variogram = model.relief.semivariogram(2.0 * r);
        let gamma_at = |d: f64| variogram.map_or(0.0, |v| v.at(d));
        let mut gamma = vec![0.0; n * n];
        for a in 0..n {
            for b in 0..n {
                let d = (uv[a].0 - uv[b].0).hypot(uv[a].1 - uv[b].1);
                corr[a * n + b] = correlation.at(d);
                gamma[a * n + b] = gamma_at(d);
            }
        }
        let all: Vec<usize> = (0..n).collect();
        let mut w = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
        let [w0, wx, wy] = &mut w;
        let full_gradient = match plane_weights(&uv, &all, [&mut w0[..], &mut wx[..], &mut wy[..]]) {
            Some(()) => terrain_gradient(wx, wy, &all, &gamma, n),
            None => [0.0; 3],
        };
        Self {
            offsets,
            uv,
            corr,
            gamma,
            bounded: variogram.is_some(),
            terrain_gradient: full_gradient,
            step_bound: 2.0 * gamma_at(2.0 * r),
            reach,
        }
    }

    /// Cells the grid needs beyond each side of the box for the footprints of its edge cells.
    pub fn reach(&self) -> i32 {
        self.reach
    }

    /// Cells in the footprint.
    pub fn len(&self) -> usize {
        self.offsets.len()
    }

    /// Whether the footprint is empty (never: the centre is always in it).
    pub fn is_empty(&self) -> bool {
        self.offsets.is_empty()
    }
}
