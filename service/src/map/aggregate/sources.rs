//! Whose cells a site's answers fuse: every robot's latest tiles as `query/sources` reads them
//! (kept beside the aggregate, which the query side and the fleet's assembler both know).

use super::world::WorldParams;
use rangegp_proto::fleet::{RobotCell, TileUpdate};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Every robot's latest tiles, by robot id and tile index (shared: a copy for queries costs a
/// pointer per tile).
pub type Robots = BTreeMap<String, BTreeMap<(i32, i32), Arc<TileUpdate>>>;

/// Whose cells the site's answers fuse: every robot's latest tiles, as queries see them.
#[derive(Debug, Clone)]
pub struct SiteSources {
    params: WorldParams,
    robots: Robots,
}

impl SiteSources {
    /// The sources of `robots`' tiles, with the aggregate geometry `params`.
    pub fn new(params: WorldParams, robots: Robots) -> Self {
        Self { params, robots }
    }

    /// Each robot's own cell under map (x, y), in robot-id order.
    pub fn at(&self, x: f64, y: f64) -> Vec<RobotCell> {
        let (cell_m, n) = (self.params.cell_m, self.params.tile_cells);
        let c = ((x / cell_m).floor() as i32, (y / cell_m).floor() as i32);
        let key = (c.0.div_euclid(n), c.1.div_euclid(n));
        self.robots
            .iter()
            .filter_map(|(robot, tiles)| {
                let tile = tiles.get(&key)?;
                let cell = tile.cells.iter().find(|t| (t.column, t.row) == c)?;
                Some(RobotCell {
                    robot: robot.clone(),
                    z_m: cell.z_m,
                    var_m2: cell.var_m2,
                    scans: cell.scans,
                    newest_scan_ns: tile.newest_scan_ns,
                })
            })
            .collect()
    }
}
