//! The layers of a terrain's true heights: what the daemon's layers are scored against.

use super::{margin_box, share};
use rangegp_proto::msg::GridReply;
use rangegp_service::map::grid::GridBox;
use rangegp_service::map::layers::{cell_layers, HeightGrid, LayerModel, Stencil};
use rangegp_sim::Heightmap;

/// The true layers of one cell.
#[derive(Debug, Clone, Copy)]
pub struct Truth {
    /// Slope angle, radians.
    pub slope: f64,
    /// Step across the footprint, metres.
    pub step: f64,
    /// Roughness, metres.
    pub roughness: f64,
}

/// The layers of the terrain's true heights on a grid box's cells: what the daemon's layers are
/// scored against (the same cells, the same footprint, σ 0).
pub struct TruthLayers {
    /// One per cell of the box, row-major from the lower-left (`None` off the terrain).
    pub cells: Vec<Option<Truth>>,
    /// Cells the footprint reaches beyond the box.
    pub margin: usize,
}

impl TruthLayers {
    /// The true layers of `terrain` on `b`'s cells for `model`'s robot.
    pub fn new(terrain: &Heightmap, b: &GridBox, model: &LayerModel) -> Self {
        let stencil = Stencil::new(model, b.resolution_m);
        let margin = stencil.reach() as usize;
        let outer = margin_box(b, margin);
        let z: Vec<f64> = (0..outer.rows)
            .flat_map(|r| (0..outer.cols).map(move |c| (c, r)))
            .map(|(c, r)| {
                let x = outer.origin_m[0] + c as f64 * outer.resolution_m;
                let y = outer.origin_m[1] + r as f64 * outer.resolution_m;
                terrain.height(x, y).unwrap_or(f64::NAN)
            })
            .collect();
        let sd = vec![0.0; z.len()];
        let grid = HeightGrid {
            cols: outer.cols,
            rows: outer.rows,
            z: &z,
            sd: &sd,
            relief_sd: &[],
        };
        let cells = (0..b.rows)
            .flat_map(|r| (0..b.cols).map(move |c| (c, r)))
            .map(|(c, r)| {
                cell_layers(&grid, &stencil, model, c + margin, r + margin).map(|l| Truth {
                    slope: l.slope,
                    step: l.step,
                    roughness: l.roughness,
                })
            })
            .collect();
        Self { cells, margin }
    }
}

/// Slope 95 % coverage when the heights of `plain` (the box with the footprint margin) are
/// taken with other error correlation lengths.
pub(super) fn error_length_sweep(
    plain: &GridReply,
    truth: &TruthLayers,
    model: &LayerModel,
    n: usize,
) -> Vec<[f64; 2]> {
    let z: Vec<f64> = plain
        .elevation_m
        .iter()
        .map(|v| v.map_or(f64::NAN, f64::from))
        .collect();
    let sd: Vec<f64> = plain
        .variance_m2
        .iter()
        .map(|v| v.map_or(f64::NAN, |v| f64::from(v).max(0.0).sqrt()))
        .collect();
    let grid = HeightGrid {
        cols: plain.cols as usize,
        rows: plain.rows as usize,
        z: &z,
        sd: &sd,
        relief_sd: &[],
    };
    [0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5]
        .into_iter()
        .map(|length| {
            let m = LayerModel {
                error_length_m: length,
                ..*model
            };
            let stencil = Stencil::new(&m, plain.resolution_m);
            let inside: Vec<bool> = (0..n * n)
                .filter_map(|k| {
                    let t = truth.cells[k]?;
                    let (c, r) = (k % n + truth.margin, k / n + truth.margin);
                    let l = cell_layers(&grid, &stencil, &m, c, r)?;
                    Some((l.slope - t.slope).abs() <= 1.96 * l.slope_sd)
                })
                .collect();
            [length, share(&inside)]
        })
        .collect()
}
