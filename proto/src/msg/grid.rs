//! Grids of elevation and planner layers, and point slopes.

use super::{Provenance, Refusal};
use serde::{Deserialize, Serialize};

/// Elevation and variance layers over a regular grid (grid_map style), and the planner layers
/// derived from them when asked for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Lower-left corner (x, y) of the box in the map frame, metres.
    pub min_m: [f64; 2],
    /// Upper-right corner (x, y), metres; each coordinate above `min_m`'s.
    pub max_m: [f64; 2],
    /// Cell side, metres (positive; at most the robot's footprint radius when a derived layer
    /// is asked for).
    pub resolution_m: f64,
    /// Derived layers wanted in [`GridReply::layers`], in this order (elevation and variance
    /// always come); empty: none.
    #[serde(default)]
    pub layers: Vec<Layer>,
    /// The robot the risk and cost layers are for; `None`: the daemon's configured one.
    #[serde(default)]
    pub robot: Option<RobotModel>,
}

/// A layer derived from the map over a robot's footprint (a disc of `footprint_radius_m` around
/// each cell centre, sampled at the grid's resolution), each value with the σ the GP gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// Slope angle of the plane fitted over the footprint, radians.
    Slope,
    /// σ of `slope`, radians.
    SlopeSigma,
    /// Direction the slope faces (downhill), radians counter-clockwise from +x.
    Aspect,
    /// RMS deviation of the surface from the footprint's plane, metres.
    Roughness,
    /// σ of `roughness`, metres.
    RoughnessSigma,
    /// Largest height difference across the footprint, metres.
    Step,
    /// σ of `step`, metres.
    StepSigma,
    /// P(slope > the robot's max slope).
    SlopeRisk,
    /// P(step > the robot's max step).
    StepRisk,
    /// Share of the footprint unknown: no map answers, or the answer's σ is wider than the
    /// robot's max step.
    UnknownRisk,
    /// P(the terrain stops the robot): P(slope or step over its limit), the larger of the two
    /// (both follow from the same height errors, so they rise and fall together).
    Risk,
    /// Traversability cost in [0, 1]: `risk` and `unknown_risk` combined as independent,
    /// 1 − (1 − risk)(1 − unknown).
    TraversalCost,
    /// The traversal cost as a ROS costmap value in [`GridReply::costmap`] (0–100, 100 lethal,
    /// −1 unknown).
    Cost,
}

impl Layer {
    /// Every layer, in wire order.
    pub const ALL: [Layer; 13] = [
        Layer::Slope,
        Layer::SlopeSigma,
        Layer::Aspect,
        Layer::Roughness,
        Layer::RoughnessSigma,
        Layer::Step,
        Layer::StepSigma,
        Layer::SlopeRisk,
        Layer::StepRisk,
        Layer::UnknownRisk,
        Layer::Risk,
        Layer::TraversalCost,
        Layer::Cost,
    ];

    /// The layer's wire name (`slope_sigma`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            Layer::Slope => "slope",
            Layer::SlopeSigma => "slope_sigma",
            Layer::Aspect => "aspect",
            Layer::Roughness => "roughness",
            Layer::RoughnessSigma => "roughness_sigma",
            Layer::Step => "step",
            Layer::StepSigma => "step_sigma",
            Layer::SlopeRisk => "slope_risk",
            Layer::StepRisk => "step_risk",
            Layer::UnknownRisk => "unknown_risk",
            Layer::Risk => "risk",
            Layer::TraversalCost => "traversal_cost",
            Layer::Cost => "cost",
        }
    }

    /// The layer named `name` ([`Layer::as_str`]).
    pub fn parse(name: &str) -> Option<Layer> {
        Layer::ALL.into_iter().find(|l| l.as_str() == name)
    }
}

/// What the risk and cost layers judge by: the robot's footprint and limits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RobotModel {
    /// Radius of the disc the robot stands on, metres (slope, roughness and step are taken over it).
    pub footprint_radius_m: f64,
    /// Steepest slope the robot climbs, degrees.
    pub max_slope_deg: f64,
    /// Highest step the robot climbs, metres.
    pub max_step_m: f64,
    /// Traversal cost at and above which a cell is lethal (costmap 100).
    pub lethal_risk: f64,
}

impl RobotModel {
    /// Footprint radii a model may have, metres: below a centimetre the footprint's grid would be
    /// finer than any map resolves (and a subnormal radius divides to a zero resolution).
    pub const FOOTPRINT_RADIUS_M: (f64, f64) = (0.01, 100.0);

    /// Why this model cannot be used (`None`: it can): every field finite, the radius within
    /// [`Self::FOOTPRINT_RADIUS_M`], the limits positive, the slope below 90° and the lethal risk
    /// in (0, 1].
    pub fn problem(&self) -> Option<&'static str> {
        let (least, most) = Self::FOOTPRINT_RADIUS_M;
        if !(least..=most).contains(&self.footprint_radius_m) {
            Some("footprint_radius_m must be in [0.01, 100] m")
        } else if !(self.max_slope_deg > 0.0 && self.max_slope_deg < 90.0) {
            Some("max_slope_deg must be in (0, 90)")
        } else if !(self.max_step_m.is_finite() && self.max_step_m > 0.0) {
            Some("max_step_m must be finite and positive")
        } else if !(self.lethal_risk > 0.0 && self.lethal_risk <= 1.0) {
            Some("lethal_risk must be in (0, 1]")
        } else {
            None
        }
    }
}

/// One derived layer of a [`GridReply`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridLayer {
    /// Which layer.
    pub layer: Layer,
    /// One value per cell, in the reply's cell order; `None` where it is unknown.
    pub values: Vec<Option<f32>>,
}

/// The layers of a [`GridRequest`]: `cols × rows` cells, row-major from the lower-left cell,
/// each value taken at its cell's centre; `None` where no map observed the cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Centre (x, y) of cell (0, 0), metres.
    pub origin_m: [f64; 2],
    /// Cell side, metres.
    pub resolution_m: f64,
    /// Cells along x.
    pub cols: u32,
    /// Cells along y.
    pub rows: u32,
    /// Surface height per cell, metres.
    pub elevation_m: Vec<Option<f32>>,
    /// Variance of the height per cell, square metres.
    pub variance_m2: Vec<Option<f32>>,
    /// How much data stands behind each cell's answer.
    pub provenance: Vec<Provenance>,
    /// The derived layers asked for, in request order (`cost` comes as [`GridReply::costmap`]).
    pub layers: Vec<GridLayer>,
    /// ROS `nav_msgs/OccupancyGrid` values when `cost` was asked for (else empty): 0 free to
    /// 100 lethal (traversal cost × 100, 100 at and above the robot's lethal risk), −1 unknown.
    pub costmap: Vec<i8>,
    /// The robot the risk and cost layers judged by.
    pub robot: RobotModel,
}

impl GridRequest {
    /// Cells along x and y the box holds at its resolution (`ceil` of extent / resolution), or
    /// `None` when the box or resolution is not a finite, positive size.
    pub fn shape(&self) -> Option<(u64, u64)> {
        let ext = [self.max_m[0] - self.min_m[0], self.max_m[1] - self.min_m[1]];
        let ok = self.resolution_m.is_finite()
            && self.resolution_m > 0.0
            && ext.iter().all(|e| e.is_finite() && *e > 0.0);
        let cells = |e: f64| (e / self.resolution_m).ceil();
        let (c, r) = (cells(ext[0]), cells(ext[1]));
        (ok && c < 1e9 && r < 1e9).then_some((c as u64, r as u64))
    }
}

impl GridReply {
    /// Centre (x, y) of cell (col, row), metres.
    pub fn centre(&self, col: u32, row: u32) -> [f64; 2] {
        [
            self.origin_m[0] + col as f64 * self.resolution_m,
            self.origin_m[1] + row as f64 * self.resolution_m,
        ]
    }

    /// The values of `layer`, when the reply carries it.
    pub fn layer(&self, layer: Layer) -> Option<&[Option<f32>]> {
        self.layers
            .iter()
            .find(|l| l.layer == layer)
            .map(|l| l.values.as_slice())
    }
}

/// Slope at map-frame (x, y) points: the `slope` layers of a grid cell centred on each point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Query points (x, y) in the map frame, metres.
    pub points: Vec<[f64; 2]>,
    /// The robot whose footprint the slope is taken over; `None`: the daemon's configured one.
    #[serde(default)]
    pub robot: Option<RobotModel>,
}

/// One slope answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeItem {
    /// Slope angle of the footprint's plane, radians (absent when unknown).
    pub slope_rad: Option<f64>,
    /// σ of `slope_rad`, radians.
    pub slope_sigma_rad: Option<f64>,
    /// Direction the slope faces (downhill), radians counter-clockwise from +x.
    pub aspect_rad: Option<f64>,
    /// Unit surface normal (x, y, z) of the footprint's plane.
    pub normal: Option<[f64; 3]>,
    /// P(slope > the robot's max slope).
    pub slope_risk: Option<f64>,
    /// Why there is no value (`None` when there is one).
    pub refusal: Option<Refusal>,
}

/// Slope answers, one per request point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Grid resolution the footprint was sampled at, metres (a grid at this resolution with a
    /// cell centred on the point gives the same values).
    pub resolution_m: f64,
    /// The robot the slope was judged for.
    pub robot: RobotModel,
    /// Answers in request order.
    pub items: Vec<SlopeItem>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(min_m: [f64; 2], max_m: [f64; 2], resolution_m: f64) -> GridRequest {
        GridRequest {
            version: crate::PROTOCOL_VERSION,
            min_m,
            max_m,
            resolution_m,
            layers: Vec::new(),
            robot: None,
        }
    }

    #[test]
    fn layer_names_round_trip() {
        for layer in Layer::ALL {
            assert_eq!(Layer::parse(layer.as_str()), Some(layer));
            let json = serde_json::to_string(&layer).expect("a layer encodes");
            assert_eq!(json, format!("\"{}\"", layer.as_str()));
        }
        assert_eq!(Layer::parse("slopes"), None);
    }

    #[test]
    fn grid_shape_rounds_up_and_refuses_empty_or_non_finite_boxes() {
        assert_eq!(grid([0.0, 0.0], [10.0, 5.0], 0.5).shape(), Some((20, 10)));
        assert_eq!(grid([0.0, 0.0], [10.1, 5.0], 0.5).shape(), Some((21, 10)));
        assert_eq!(grid([0.0, 0.0], [0.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([1.0, 0.0], [0.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([0.0, 0.0], [10.0, 5.0], 0.0).shape(), None);
        assert_eq!(grid([0.0, f64::NAN], [10.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([0.0, 0.0], [1e300, 5.0], 1e-300).shape(), None);
    }
}
