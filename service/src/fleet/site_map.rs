//! The site map: every robot's latest tiles, fused cell by cell by inverse variance, held as a
//! world aggregate so that a site answers with the same code (and the same numbers) as a robot.

use crate::map::aggregate::sources::{Robots, SiteSources};
use crate::map::aggregate::world::{Cell, TileCells, WorldAggregate, WorldParams};
use crate::map::aggregate::AggregateError;
use rangegp_proto::fleet::{RobotTiles, TileUpdate};
use rangegp_proto::keys::MapKeys;
use rangegp_proto::PROTOCOL_VERSION;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use thiserror::Error;

/// Why a tile update was not taken.
#[derive(Debug, Error, PartialEq)]
pub enum TileRefusal {
    /// Another protocol version.
    #[error("tile of protocol version {0}, this site speaks {PROTOCOL_VERSION}")]
    Version(u32),
    /// Another cell or tile size than the site's.
    #[error("tile geometry {cell_m} m × {tile_cells} cells differs from the site's")]
    Geometry {
        /// Its cell side, metres.
        cell_m: f64,
        /// Its tile side, cells.
        tile_cells: i32,
    },
    /// The robot id is not a valid map id.
    #[error("robot id {0:?} is not a valid map id")]
    Robot(String),
    /// The tile index is beyond [`MAX_TILE_INDEX`], or a cell lies outside the tile, repeats, or
    /// holds a height beyond [`MAX_ABS_Z_M`] (or not finite) or a variance below [`MIN_VAR_M2`]
    /// (or not finite).
    #[error("tile ({0}, {1}) is out of range or holds a cell outside it, twice, or with an invalid height or variance")]
    Cell(i32, i32),
    /// The site holds a newer version of this tile.
    #[error("an older version of a tile the site holds")]
    Stale,
    /// A new robot or a new tile beyond the site's limits ([`SiteLimits`]).
    #[error("the site holds {held} {what}, its limit (fleet.max_site_{what})")]
    Full {
        /// `robots` or `tiles`.
        what: &'static str,
        /// How many it holds.
        held: usize,
    },
}

/// How much a site holds at most: robots, and tiles summed over robots. A peer that may put
/// under the site's key space cannot grow it beyond; updates of tiles it holds still go in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SiteLimits {
    /// Robots (`fleet.max_site_robots`).
    pub robots: usize,
    /// Tiles over all robots (`fleet.max_site_tiles`): about 3 KiB each, plus about 0.15 MB
    /// for each distinct tile's fitted expert.
    pub tiles: usize,
}

/// Tile indices beyond this (either axis) are refused: 10⁶ tiles of 2.5 m is 2 500 km, far
/// beyond any site, and far from where cell and tile arithmetic could overflow.
pub const MAX_TILE_INDEX: i32 = 1_000_000;
/// Heights beyond this are refused, metres (higher than any mountain above any sea floor).
pub const MAX_ABS_Z_M: f64 = 20_000.0;
/// Variances below this are refused, m² (a micrometre: no sensor measures ground better; a
/// smaller one would let one robot's cell outweigh every other's, and a subnormal one overflows
/// the fused precision).
pub const MIN_VAR_M2: f64 = 1e-12;

/// Every robot's latest tiles and the aggregate fused from them.
#[derive(Debug, Clone)]
pub struct SiteMap {
    params: WorldParams,
    limits: SiteLimits,
    robots: Robots,
    /// Tiles held, summed over robots.
    tiles: usize,
    world: WorldAggregate,
}

impl SiteMap {
    /// An empty site map with the robots' aggregate geometry, holding at most `limits`.
    pub fn new(params: WorldParams, limits: SiteLimits) -> Self {
        Self {
            params,
            limits,
            robots: BTreeMap::new(),
            tiles: 0,
            world: WorldAggregate::new(params),
        }
    }

    /// The fused aggregate queries are answered from.
    pub fn world(&self) -> &WorldAggregate {
        &self.world
    }

    /// Checks `update` against the site's geometry and what it holds.
    pub fn check(&self, update: &TileUpdate) -> Result<(), TileRefusal> {
        if update.version != PROTOCOL_VERSION {
            return Err(TileRefusal::Version(update.version));
        }
        if update.cell_m != self.params.cell_m || update.tile_cells != self.params.tile_cells {
            return Err(TileRefusal::Geometry {
                cell_m: update.cell_m,
                tile_cells: update.tile_cells,
            });
        }
        MapKeys::new(&update.robot).map_err(|_| TileRefusal::Robot(update.robot.clone()))?;
        let key = (update.tile_column, update.tile_row);
        if key.0.unsigned_abs() > MAX_TILE_INDEX.unsigned_abs()
            || key.1.unsigned_abs() > MAX_TILE_INDEX.unsigned_abs()
        {
            return Err(TileRefusal::Cell(key.0, key.1));
        }
        let n = self.params.tile_cells;
        let mut seen = BTreeSet::new();
        for c in &update.cells {
            let inside = (c.column.div_euclid(n), c.row.div_euclid(n)) == key;
            let valid = c.z_m.abs() <= MAX_ABS_Z_M && c.var_m2.is_finite() && c.var_m2 >= MIN_VAR_M2;
            if !inside || !valid || !seen.insert((c.column, c.row)) {
                return Err(TileRefusal::Cell(key.0, key.1));
            }
        }
        let robot = self.robots.get(&update.robot);
        let held = robot.and_then(|t| t.get(&key));
        if held.is_some_and(|h| !update.newer_than(h)) {
            return Err(TileRefusal::Stale);
        }
        if robot.is_none() && self.robots.len() >= self.limits.robots {
            return Err(TileRefusal::Full {
                what: "robots",
                held: self.robots.len(),
            });
        }
        if held.is_none() && self.tiles >= self.limits.tiles {
            return Err(TileRefusal::Full {
                what: "tiles",
                held: self.tiles,
            });
        }
        Ok(())
    }

    /// Takes in every update that passes [`Self::check`] (in order; a later one of the same tile
    /// supersedes an earlier), refuses the rest with their reasons, and refits the tiles they
    /// changed once. On a failed refit the updates are held and the aggregate keeps its old fits
    /// where it could not refit.
    pub fn offer(
        &mut self,
        updates: Vec<TileUpdate>,
    ) -> Result<Vec<TileRefusal>, (AggregateError, Vec<TileRefusal>)> {
        let mut refused = Vec::new();
        let mut touched = BTreeSet::new();
        for update in updates {
            if let Err(why) = self.check(&update) {
                refused.push(why);
                continue;
            }
            let key = (update.tile_column, update.tile_row);
            touched.insert(key);
            let replaced = self
                .robots
                .entry(update.robot.clone())
                .or_default()
                .insert(key, Arc::new(update));
            self.tiles += usize::from(replaced.is_none());
        }
        let fused: BTreeMap<(i32, i32), TileCells> = touched
            .into_iter()
            .map(|key| (key, self.fused_tile(key)))
            .collect();
        if fused.is_empty() {
            return Ok(refused);
        }
        match self.world.replace_tiles(&fused) {
            Ok(()) => Ok(refused),
            Err(e) => Err((e, refused)),
        }
    }

    /// Tile `key`'s cells fused across robots (in robot-id order, so the sums are the same on
    /// every site): precision-weighted heights, summed precisions and scans.
    fn fused_tile(&self, key: (i32, i32)) -> TileCells {
        let mut sums: BTreeMap<(i32, i32), (f64, f64, u32)> = BTreeMap::new();
        for tiles in self.robots.values() {
            let Some(held) = tiles.get(&key) else { continue };
            for c in &held.cells {
                let s = sums.entry((c.column, c.row)).or_insert((0.0, 0.0, 0));
                s.0 += 1.0 / c.var_m2;
                s.1 += c.z_m / c.var_m2;
                s.2 = s.2.saturating_add(c.scans);
            }
        }
        sums.into_iter()
            .map(|(c, (precision, weighted, scans))| {
                let cell = if precision.is_finite() && precision > 0.0 {
                    Cell {
                        z: weighted / precision,
                        var: 1.0 / precision,
                        scans,
                    }
                } else {
                    Cell {
                        z: weighted,
                        var: 0.0,
                        scans,
                    }
                };
                (c, cell)
            })
            .filter(|(_, cell)| cell.var > 0.0 && cell.z.is_finite())
            .collect()
    }

    /// Whose cells the answers fuse, for `query/sources`.
    pub fn sources(&self) -> SiteSources {
        SiteSources::new(self.params, self.robots.clone())
    }

    /// Per robot: tiles and cells held, and the newest scan they reflect (`alive` false: the
    /// caller knows liveliness).
    pub fn robots(&self) -> Vec<RobotTiles> {
        self.robots
            .iter()
            .map(|(robot, tiles)| RobotTiles {
                robot: robot.clone(),
                tiles: tiles.len() as u64,
                cells: tiles.values().map(|h| h.cells.len() as u64).sum(),
                newest_scan_ns: tiles.values().map(|h| h.newest_scan_ns).max().unwrap_or(0),
                alive: false,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::aggregate::Aggregate;
    use rangegp_proto::fleet::TileCell;

    fn update(robot: &str, published_ns: u64, cells: &[(i32, i32, f64, f64)]) -> TileUpdate {
        let p = WorldParams::default();
        TileUpdate {
            version: PROTOCOL_VERSION,
            robot: robot.into(),
            tile_column: 0,
            tile_row: 0,
            cell_m: p.cell_m,
            tile_cells: p.tile_cells,
            revision: 1,
            published_ns,
            newest_scan_ns: published_ns,
            cells: cells
                .iter()
                .map(|&(column, row, z_m, var_m2)| TileCell {
                    column,
                    row,
                    z_m,
                    var_m2,
                    scans: 1,
                })
                .collect(),
        }
    }

    const ROOMY: SiteLimits = SiteLimits {
        robots: 16,
        tiles: 1024,
    };

    #[test]
    fn overlapping_robots_fuse_by_inverse_variance_and_the_latest_tile_wins() {
        let mut site = SiteMap::new(WorldParams::default(), ROOMY);
        let refused = site
            .offer(vec![
                update("a", 1, &[(1, 1, 0.10, 1e-4), (2, 1, 0.0, 1e-4)]),
                update("b", 1, &[(1, 1, 0.20, 3e-4)]),
            ])
            .expect("fits");
        assert!(refused.is_empty());
        let cell = site.world().cells()[&(1, 1)];
        assert!((cell.var - 0.75e-4).abs() < 1e-15);
        assert!((cell.z - (0.10 / 1e-4 + 0.20 / 3e-4) * 0.75e-4).abs() < 1e-12);
        assert!(site.world().elevation(0.3, 0.3).is_some());
        let under: Vec<String> = site.sources().at(0.3, 0.3).into_iter().map(|c| c.robot).collect();
        assert_eq!(under, ["a", "b"]);
        // A newer tile from a replaces its cells; an older one is refused.
        let refused = site
            .offer(vec![update("a", 2, &[(2, 1, 0.05, 1e-4)]), update("a", 1, &[])])
            .expect("fits");
        assert_eq!(refused, vec![TileRefusal::Stale]);
        assert_eq!(site.world().cells()[&(1, 1)].z, 0.20);
        assert_eq!(site.world().cells()[&(2, 1)].z, 0.05);
        assert_eq!(site.robots()[0].cells, 1);
    }

    #[test]
    fn bad_tiles_are_refused_with_their_reason() {
        let site = SiteMap::new(WorldParams::default(), ROOMY);
        let mut t = update("a", 1, &[(1, 1, 0.1, 1e-4)]);
        t.version = PROTOCOL_VERSION - 1;
        assert!(matches!(site.check(&t), Err(TileRefusal::Version(_))));
        let mut t = update("a", 1, &[(1, 1, 0.1, 1e-4)]);
        t.cell_m = 0.5;
        assert!(matches!(site.check(&t), Err(TileRefusal::Geometry { .. })));
        for bad in [
            update("a", 1, &[(11, 1, 0.1, 1e-4)]),
            update("a", 1, &[(1, 1, f64::NAN, 1e-4)]),
            update("a", 1, &[(1, 1, 0.1, 0.0)]),
            update("a", 1, &[(1, 1, 0.1, 1e-4), (1, 1, 0.2, 1e-4)]),
            update("a", 1, &[(1, 1, 0.1, 1e-300)]),
            update("a", 1, &[(1, 1, 3e4, 1e-4)]),
        ] {
            assert_eq!(site.check(&bad), Err(TileRefusal::Cell(0, 0)));
        }
        for index in [i32::MAX, i32::MIN, -MAX_TILE_INDEX - 1] {
            let mut far = update("a", 1, &[]);
            far.tile_row = index;
            assert_eq!(site.check(&far), Err(TileRefusal::Cell(0, index)));
        }
        assert!(matches!(
            site.check(&update("a/b", 1, &[])),
            Err(TileRefusal::Robot(_))
        ));
    }

    #[test]
    fn a_site_holds_no_more_robots_and_tiles_than_its_limits_but_updates_what_it_holds() {
        let limits = SiteLimits { robots: 2, tiles: 3 };
        let mut site = SiteMap::new(WorldParams::default(), limits);
        let at = |robot: &str, ns: u64, column: i32| {
            let mut u = update(robot, ns, &[(column * 10 + 1, 1, 0.1, 1e-4)]);
            u.tile_column = column;
            u
        };
        let refused = site
            .offer(vec![at("a", 1, 0), at("a", 1, 1), at("b", 1, 0)])
            .expect("fits");
        assert!(refused.is_empty(), "{refused:?}");
        let refused = site
            .offer(vec![at("c", 1, 0), at("b", 1, 1), at("a", 2, 1)])
            .expect("fits");
        assert_eq!(
            refused,
            vec![
                TileRefusal::Full {
                    what: "robots",
                    held: 2
                },
                TileRefusal::Full {
                    what: "tiles",
                    held: 3
                },
            ],
            "a third robot and a fourth tile refused; a newer version of a held tile taken"
        );
        assert_eq!(site.robots().len(), 2);
        assert_eq!(site.robots().iter().map(|r| r.tiles).sum::<u64>(), 3);
        assert!(
            refused[0].to_string().contains("fleet.max_site_robots"),
            "{}",
            refused[0]
        );
    }
}
