//! A grid answer as the map messages ROS 2 planners take: grid_map_msgs/GridMap (every layer,
//! NaN where unknown) and nav_msgs/OccupancyGrid (the costmap, 0–100 and −1 unknown).
//!
//! The two messages index differently. OccupancyGrid is row-major from the cell at its origin
//! (the lowest x and y), x along a row, as the daemon's reply is. GridMap stores each layer
//! column-major with index (0, 0) at the corner of highest x and y, the row index running
//! towards −x and the column index towards −y (grid_map's convention, `GridMapRosConverter`).

use crate::msg::{Header, Pose, Quaternion, Time, Vector3};
use rangegp_proto::msg::{GridReply, Layer};
use serde::{Deserialize, Serialize};

/// std_msgs/MultiArrayDimension.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MultiArrayDimension {
    /// What the dimension indexes (`column_index`, `row_index` in a GridMap).
    pub label: String,
    /// Its length.
    pub size: u32,
    /// Elements spanned by one step of the dimension above it.
    pub stride: u32,
}

/// std_msgs/MultiArrayLayout.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MultiArrayLayout {
    /// Outermost dimension first.
    pub dim: Vec<MultiArrayDimension>,
    /// Elements before the first one.
    pub data_offset: u32,
}

/// std_msgs/Float32MultiArray.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Float32MultiArray {
    /// How `data` is laid out.
    pub layout: MultiArrayLayout,
    /// The values.
    pub data: Vec<f32>,
}

/// grid_map_msgs/GridMapInfo.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridMapInfo {
    /// Cell side, metres.
    pub resolution: f64,
    /// Extent along x, metres.
    pub length_x: f64,
    /// Extent along y, metres.
    pub length_y: f64,
    /// Pose of the grid's centre in the header's frame.
    pub pose: Pose,
}

/// grid_map_msgs/GridMap.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridMap {
    /// Stamp and frame.
    pub header: Header,
    /// Geometry.
    pub info: GridMapInfo,
    /// Layer names, in the order of `data`.
    pub layers: Vec<String>,
    /// Layers that must be valid for a cell to be valid.
    pub basic_layers: Vec<String>,
    /// One array per layer.
    pub data: Vec<Float32MultiArray>,
    /// Circular-buffer start row (always 0 here).
    pub outer_start_index: u16,
    /// Circular-buffer start column (always 0 here).
    pub inner_start_index: u16,
}

/// nav_msgs/MapMetaData.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapMetaData {
    /// When the map was made.
    pub map_load_time: Time,
    /// Cell side, metres.
    pub resolution: f32,
    /// Cells along x.
    pub width: u32,
    /// Cells along y.
    pub height: u32,
    /// Pose of the corner of cell (0, 0) in the header's frame.
    pub origin: Pose,
}

/// nav_msgs/OccupancyGrid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OccupancyGrid {
    /// Stamp and frame.
    pub header: Header,
    /// Geometry.
    pub info: MapMetaData,
    /// Row-major from the origin: 0 free to 100 lethal, −1 unknown.
    pub data: Vec<i8>,
}

/// The GridMap layer names of the height and its variance (elevation_mapping's names).
pub const ELEVATION: &str = "elevation";
/// See [`ELEVATION`].
pub const VARIANCE: &str = "variance";

/// A pose at (x, y, 0) without rotation.
fn flat_pose(x: f64, y: f64) -> Pose {
    Pose {
        position: Vector3 { x, y, z: 0.0 },
        orientation: Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        },
    }
}

/// `values` (the reply's order) as a GridMap layer.
fn layer_array(reply: &GridReply, value: impl Fn(usize) -> f32) -> Float32MultiArray {
    let (nx, ny) = (reply.cols as usize, reply.rows as usize);
    let mut data = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let (cx, cy) = (nx - 1 - i, ny - 1 - j);
            data.push(value(cy * nx + cx));
        }
    }
    let dim = |label: &str, size: usize, stride: usize| MultiArrayDimension {
        label: label.into(),
        size: size as u32,
        stride: stride as u32,
    };
    Float32MultiArray {
        layout: MultiArrayLayout {
            dim: vec![dim("column_index", ny, nx * ny), dim("row_index", nx, nx)],
            data_offset: 0,
        },
        data,
    }
}

/// The reply as a GridMap in `header`'s frame: `elevation` and `variance`, then each derived
/// layer it carries under its wire name, and `cost` (0–100) when the costmap came; NaN where a
/// cell is unknown.
pub fn grid_map(reply: &GridReply, header: Header) -> GridMap {
    let res = reply.resolution_m;
    let (nx, ny) = (f64::from(reply.cols), f64::from(reply.rows));
    let centre = [
        reply.origin_m[0] + 0.5 * (nx - 1.0) * res,
        reply.origin_m[1] + 0.5 * (ny - 1.0) * res,
    ];
    let of = |v: &[Option<f32>], k: usize| v.get(k).copied().flatten().unwrap_or(f32::NAN);
    let mut layers = vec![ELEVATION.to_owned(), VARIANCE.to_owned()];
    let mut data = vec![
        layer_array(reply, |k| of(&reply.elevation_m, k)),
        layer_array(reply, |k| of(&reply.variance_m2, k)),
    ];
    for l in &reply.layers {
        layers.push(l.layer.as_str().to_owned());
        data.push(layer_array(reply, |k| of(&l.values, k)));
    }
    if !reply.costmap.is_empty() {
        layers.push(Layer::Cost.as_str().to_owned());
        data.push(layer_array(reply, |k| match reply.costmap.get(k) {
            Some(&c) if c >= 0 => f32::from(c),
            _ => f32::NAN,
        }));
    }
    GridMap {
        header,
        info: GridMapInfo {
            resolution: res,
            length_x: nx * res,
            length_y: ny * res,
            pose: flat_pose(centre[0], centre[1]),
        },
        layers,
        basic_layers: vec![ELEVATION.to_owned()],
        data,
        outer_start_index: 0,
        inner_start_index: 0,
    }
}

/// The reply's costmap as an OccupancyGrid in `header`'s frame (`None` when the reply has no
/// costmap: `cost` was not asked for).
pub fn occupancy_grid(reply: &GridReply, header: Header) -> Option<OccupancyGrid> {
    if reply.costmap.is_empty() {
        return None;
    }
    let res = reply.resolution_m;
    Some(OccupancyGrid {
        info: MapMetaData {
            map_load_time: header.stamp,
            resolution: res as f32,
            width: reply.cols,
            height: reply.rows,
            origin: flat_pose(reply.origin_m[0] - 0.5 * res, reply.origin_m[1] - 0.5 * res),
        },
        header,
        data: reply.costmap.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rangegp_proto::msg::{GridLayer, RobotModel};

    /// A 3 × 2 reply whose elevation is 10 x + y at each cell centre, the cost its index.
    fn reply() -> GridReply {
        let (cols, rows, res, origin) = (3u32, 2u32, 0.5, [1.0, -2.0]);
        let cells = (cols * rows) as usize;
        let centre = |k: usize| {
            let (c, r) = ((k % 3) as f64, (k / 3) as f64);
            [origin[0] + c * res, origin[1] + r * res]
        };
        let mut elevation: Vec<Option<f32>> = (0..cells)
            .map(|k| Some((10.0 * centre(k)[0] + centre(k)[1]) as f32))
            .collect();
        elevation[4] = None;
        GridReply {
            version: rangegp_proto::PROTOCOL_VERSION,
            origin_m: origin,
            resolution_m: res,
            cols,
            rows,
            variance_m2: vec![Some(0.01); cells],
            elevation_m: elevation,
            provenance: Vec::new(),
            layers: vec![GridLayer {
                layer: Layer::Slope,
                values: vec![Some(0.1); cells],
            }],
            costmap: vec![0, 1, 2, 3, -1, 5],
            robot: RobotModel {
                footprint_radius_m: 0.3,
                max_slope_deg: 20.0,
                max_step_m: 0.15,
                lethal_risk: 0.5,
            },
        }
    }

    /// grid_map's position of index (row i, column j): from the centre, half the length less
    /// (index + ½) cells, along +x for rows and +y for columns.
    fn gm_position(m: &GridMap, i: usize, j: usize) -> [f64; 2] {
        let r = m.info.resolution;
        [
            m.info.pose.position.x + 0.5 * m.info.length_x - (i as f64 + 0.5) * r,
            m.info.pose.position.y + 0.5 * m.info.length_y - (j as f64 + 0.5) * r,
        ]
    }

    #[test]
    fn grid_map_cells_sit_where_grid_map_puts_them() {
        let rep = reply();
        let m = grid_map(&rep, Header::default());
        assert_eq!(m.layers, ["elevation", "variance", "slope", "cost"]);
        let el = &m.data[0];
        let (cols, rows) = (el.layout.dim[0].size as usize, el.layout.dim[1].size as usize);
        assert_eq!((rows, cols), (3, 2), "grid_map rows run along x");
        assert_eq!(el.layout.dim[0].label, "column_index");
        let mut seen_unknown = 0;
        for j in 0..cols {
            for i in 0..rows {
                let v = el.data[j * rows + i];
                let [x, y] = gm_position(&m, i, j);
                if v.is_nan() {
                    seen_unknown += 1;
                    assert!(
                        (x - 1.5).abs() < 1e-9 && (y + 1.5).abs() < 1e-9,
                        "cell 4 is unknown"
                    );
                } else {
                    assert!(
                        (f64::from(v) - (10.0 * x + y)).abs() < 1e-4,
                        "({i}, {j}) at ({x}, {y}): {v}"
                    );
                }
            }
        }
        assert_eq!(seen_unknown, 1);
        let cost = &m.data[3].data;
        assert_eq!(cost.iter().filter(|c| c.is_nan()).count(), 1);
        assert_eq!(cost[0], 5.0, "index (0, 0) is the cell of highest x and y");
    }

    #[test]
    fn occupancy_grid_is_the_costmap_from_the_lower_left_corner() {
        let rep = reply();
        let g = occupancy_grid(&rep, Header::default()).expect("costmap");
        assert_eq!((g.info.width, g.info.height), (3, 2));
        assert_eq!(g.data, rep.costmap);
        assert!((g.info.origin.position.x - 0.75).abs() < 1e-12);
        assert!((g.info.origin.position.y + 2.25).abs() < 1e-12);
        let mut none = rep.clone();
        none.costmap.clear();
        assert!(occupancy_grid(&none, Header::default()).is_none());
    }
}
