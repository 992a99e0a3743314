//! Grids and slopes over a [`MapSnapshot`]: cell centres answered like elevation queries, and
//! the planner layers ([`super::layers`]) over the robot's footprint around each.

use super::layers::{cell_layers, footprint_reach, CellLayers, HeightGrid, LayerModel, Stencil};
use super::query;
use super::window::MapSnapshot;
use rangegp_proto::msg::{ElevationItem, GridLayer, GridReply, Layer, Refusal, SlopeItem, SlopeReply};
use rangegp_proto::PROTOCOL_VERSION;

/// Footprint samples per radius of a point slope query: its grid's resolution is the radius
/// over this.
pub const SLOPE_SAMPLES_PER_RADIUS: f64 = 3.0;

/// A grid box in cells: the centre of cell (0, 0), the resolution and the shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridBox {
    /// Centre (x, y) of cell (0, 0), metres.
    pub origin_m: [f64; 2],
    /// Cell side, metres.
    pub resolution_m: f64,
    /// Cells along x.
    pub cols: usize,
    /// Cells along y.
    pub rows: usize,
}

/// The reply to a grid over `grid_box` (validated by the caller: positive resolution, at most
/// the robot's footprint radius when `layers` is not empty), on up to `threads` threads.
pub fn grid(
    snapshot: &MapSnapshot,
    grid_box: &GridBox,
    layers: &[Layer],
    model: &LayerModel,
    threads: usize,
) -> GridReply {
    let res = grid_box.resolution_m;
    let stencil = (!layers.is_empty()).then(|| Stencil::new(model, res));
    let margin = stencil.as_ref().map_or(0, |s| s.reach() as usize);
    let (cols, rows) = (grid_box.cols + 2 * margin, grid_box.rows + 2 * margin);
    // Each centre as origin + offset × resolution, the offset counted from the box's first
    // cell: a box cell's centre is the same number with or without the margin.
    let o = grid_box.origin_m;
    let m = margin as f64;
    let centres: Vec<[f64; 2]> = (0..rows)
        .flat_map(|r| (0..cols).map(move |c| [o[0] + (c as f64 - m) * res, o[1] + (r as f64 - m) * res]))
        .collect();
    let (items, relief): (Vec<ElevationItem>, Vec<f64>) = query::par_map(&centres, threads, |p| {
        query::elevation_with_relief(snapshot, p[0], p[1])
    })
    .into_iter()
    .unzip();
    let inner: Vec<(usize, usize)> = (0..grid_box.rows)
        .flat_map(|r| (0..grid_box.cols).map(move |c| (c + margin, r + margin)))
        .collect();
    let pick = |f: &dyn Fn(&ElevationItem) -> Option<f32>| -> Vec<Option<f32>> {
        inner.iter().map(|&(c, r)| f(&items[r * cols + c])).collect()
    };
    let mut reply = GridReply {
        version: PROTOCOL_VERSION,
        origin_m: grid_box.origin_m,
        resolution_m: res,
        cols: grid_box.cols as u32,
        rows: grid_box.rows as u32,
        elevation_m: pick(&|i| i.z_m.map(|z| z as f32)),
        variance_m2: pick(&|i| i.z_var_m2.map(|v| v as f32)),
        provenance: inner
            .iter()
            .map(|&(c, r)| items[r * cols + c].provenance)
            .collect(),
        layers: Vec::new(),
        costmap: Vec::new(),
        robot: model.robot,
    };
    let Some(stencil) = stencil else {
        return reply;
    };
    let (z, sd) = heights(&items);
    let relief_sd = relief_sds(&relief);
    let heights = HeightGrid {
        cols,
        rows,
        z: &z,
        sd: &sd,
        relief_sd: &relief_sd,
    };
    let cells = query::par_map(&inner, threads, |&(c, r)| {
        cell_layers(&heights, &stencil, model, c, r)
    });
    for &layer in layers {
        if layer == Layer::Cost {
            reply.costmap = cells
                .iter()
                .map(|l| l.map_or(-1, |l| l.cost(model.robot.lethal_risk)))
                .collect();
        } else {
            reply.layers.push(GridLayer {
                layer,
                values: cells.iter().map(|l| l.map(|l| value(&l, layer) as f32)).collect(),
            });
        }
    }
    reply
}

/// Heights and σ of elevation answers, NaN where refused.
fn heights(items: &[ElevationItem]) -> (Vec<f64>, Vec<f64>) {
    items
        .iter()
        .map(|i| match (i.z_m, i.z_var_m2) {
            (Some(z), Some(v)) => (z, v.max(0.0).sqrt()),
            _ => (f64::NAN, f64::NAN),
        })
        .unzip()
}

/// The σ of the unseen relief's share of each answer's variance.
fn relief_sds(relief_var: &[f64]) -> Vec<f64> {
    relief_var.iter().map(|v| v.max(0.0).sqrt()).collect()
}

/// The value of `layer` (not `cost`, which is the costmap) in `l`.
fn value(l: &CellLayers, layer: Layer) -> f64 {
    match layer {
        Layer::Slope => l.slope,
        Layer::SlopeSigma => l.slope_sd,
        Layer::Aspect => l.aspect,
        Layer::Roughness => l.roughness,
        Layer::RoughnessSigma => l.roughness_sd,
        Layer::Step => l.step,
        Layer::StepSigma => l.step_sd,
        Layer::SlopeRisk => l.slope_risk,
        Layer::StepRisk => l.step_risk,
        Layer::UnknownRisk => l.unknown_risk,
        Layer::Risk => l.risk,
        Layer::TraversalCost | Layer::Cost => l.traversal_cost,
    }
}

/// Elevation answers one point slope query takes (its footprint grid).
pub fn samples_per_point(model: &LayerModel) -> usize {
    let radius = model.robot.footprint_radius_m;
    let side = 2 * footprint_reach(radius, radius / SLOPE_SAMPLES_PER_RADIUS) + 1;
    side * side
}

/// Slope answers at `points`: each the layers of the centre cell of a grid at the footprint
/// radius over [`SLOPE_SAMPLES_PER_RADIUS`] centred on the point.
pub fn slopes(snapshot: &MapSnapshot, points: &[[f64; 2]], model: &LayerModel, threads: usize) -> SlopeReply {
    let res = model.robot.footprint_radius_m / SLOPE_SAMPLES_PER_RADIUS;
    let stencil = Stencil::new(model, res);
    let reach = stencil.reach() as usize;
    let side = 2 * reach + 1;
    let items = query::par_map(points, threads, |p| {
        let (answers, relief): (Vec<ElevationItem>, Vec<f64>) = (0..side * side)
            .map(|k| {
                let (c, r) = ((k % side) as f64, (k / side) as f64);
                let x = p[0] + (c - reach as f64) * res;
                let y = p[1] + (r - reach as f64) * res;
                query::elevation_with_relief(snapshot, x, y)
            })
            .unzip();
        let centre = &answers[reach * side + reach];
        let (z, sd) = heights(&answers);
        let relief_sd = relief_sds(&relief);
        let grid = HeightGrid {
            cols: side,
            rows: side,
            z: &z,
            sd: &sd,
            relief_sd: &relief_sd,
        };
        match cell_layers(&grid, &stencil, model, reach, reach) {
            Some(l) => SlopeItem {
                slope_rad: Some(l.slope),
                slope_sigma_rad: Some(l.slope_sd),
                aspect_rad: Some(l.aspect),
                normal: Some(l.normal),
                slope_risk: Some(l.slope_risk),
                refusal: None,
            },
            None => SlopeItem {
                slope_rad: None,
                slope_sigma_rad: None,
                aspect_rad: None,
                normal: None,
                slope_risk: None,
                refusal: Some(centre.refusal.unwrap_or(Refusal::Unobserved)),
            },
        }
    });
    SlopeReply {
        version: PROTOCOL_VERSION,
        resolution_m: res,
        robot: model.robot,
        items,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{family_terrain, layer_model, params, scan_at_centre};
    use crate::map::{LocalRangeMap, Window};
    use rangegp_proto::msg::Provenance;
    use std::sync::Arc;

    /// Cells some map answered.
    fn observed(reply: &GridReply) -> usize {
        reply
            .provenance
            .iter()
            .filter(|p| **p != Provenance::None)
            .count()
    }

    #[test]
    fn layers_leave_elevation_alone_and_a_point_slope_equals_its_grid_cell() {
        let scan = scan_at_centre(&family_terrain("fbm-h05-16deg", 3, 60.0));
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        let mut window = Window::new(4);
        window.push(Arc::new(map));
        let snap = window.snapshot();
        let m = layer_model();
        let res = m.robot.footprint_radius_m / SLOPE_SAMPLES_PER_RADIUS;
        let b = GridBox {
            origin_m: [2.0, -1.0],
            resolution_m: res,
            cols: 12,
            rows: 9,
        };
        let plain = grid(&snap, &b, &[], &m, 2);
        let full = grid(&snap, &b, &Layer::ALL, &m, 2);
        assert_eq!(plain.elevation_m, full.elevation_m);
        assert_eq!(plain.variance_m2, full.variance_m2);
        assert!(observed(&full) > 50, "the box lies in the scan's view");
        assert_eq!(full.layers.len(), Layer::ALL.len() - 1);
        assert_eq!(full.costmap.len(), 12 * 9);
        let (c, r) = (5u32, 4u32);
        let p = full.centre(c, r);
        let s = slopes(&snap, &[p], &m, 1);
        let k = (r * full.cols + c) as usize;
        let slope = full.layer(Layer::Slope).expect("asked for")[k].expect("answered");
        let sd = full.layer(Layer::SlopeSigma).expect("asked for")[k].expect("answered");
        let item = &s.items[0];
        assert!((f64::from(slope) - item.slope_rad.expect("answered")).abs() < 1e-6);
        assert!((f64::from(sd) - item.slope_sigma_rad.expect("answered")).abs() < 1e-6);
        let far = slopes(&snap, &[[500.0, 500.0]], &m, 1);
        assert_eq!(far.items[0].refusal, Some(Refusal::Unobserved));
    }
}
