//! Fleets: the aggregate tiles robots publish into a site's key space, and what status says of
//! them. Tiles travel on `rangegp/<site>/tiles/<robot>/<column>_<row>` (bincode, like events);
//! a Zenoh storage keeps the latest of each, and a site daemon assembles them (docs/FLEET.md).

use crate::keys::MapKeys;
use serde::{Deserialize, Serialize};

/// One fused cell of a tile, as the robot's aggregate holds it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TileCell {
    /// Cell column (world index: x = (column + 0.5) × cell side).
    pub column: i32,
    /// Cell row.
    pub row: i32,
    /// Fused height, metres.
    pub z_m: f64,
    /// Its variance, m².
    pub var_m2: f64,
    /// Scans fused into it.
    pub scans: u32,
}

/// The whole content of one aggregate tile of one robot: the latest replaces what came before.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileUpdate {
    /// Protocol version of the message ([`crate::PROTOCOL_VERSION`]).
    pub version: u32,
    /// The robot's map id.
    pub robot: String,
    /// Tile column (tile index: cells column / tile_cells, rounded down).
    pub tile_column: i32,
    /// Tile row.
    pub tile_row: i32,
    /// Cell side, metres (a site refuses tiles of another geometry).
    pub cell_m: f64,
    /// Tile side, cells.
    pub tile_cells: i32,
    /// The robot's aggregate inserts when the tile was taken: later is newer within one run.
    pub revision: u64,
    /// Wall-clock time the tile was published, ns since the Unix epoch: newer across runs.
    pub published_ns: u64,
    /// Acquisition time of the newest scan the robot had fused, ns since the Unix epoch.
    pub newest_scan_ns: u64,
    /// The tile's cells (empty: the robot no longer holds any cell here).
    pub cells: Vec<TileCell>,
}

impl TileUpdate {
    /// Whether `self` supersedes `other` (same robot and tile): published later, then the
    /// higher revision.
    pub fn newer_than(&self, other: &TileUpdate) -> bool {
        (self.published_ns, self.revision) > (other.published_ns, other.revision)
    }
}

/// `rangegp/<site>/tiles/<robot>/<column>_<row>`: where a robot's tile is published and stored.
pub fn tile_key(site: &MapKeys, robot: &MapKeys, tile: (i32, i32)) -> String {
    format!(
        "rangegp/{}/tiles/{}/{}_{}",
        site.map_id(),
        robot.map_id(),
        tile.0,
        tile.1
    )
}

/// `rangegp/<site>/tiles/**`: every robot's tiles of a site (the storage's and the site's key).
pub fn site_tiles(site: &MapKeys) -> String {
    format!("rangegp/{}/tiles/**", site.map_id())
}

/// The robot and tile a tile key names, if it is one under `site`.
pub fn parse_tile_key(site: &MapKeys, key: &str) -> Option<(String, (i32, i32))> {
    let rest = key.strip_prefix(&format!("rangegp/{}/tiles/", site.map_id()))?;
    let (robot, tile) = rest.split_once('/')?;
    let (column, row) = tile.split_once('_')?;
    MapKeys::new(robot).ok()?;
    Some((robot.to_owned(), (column.parse().ok()?, row.parse().ok()?)))
}

/// `query/sources`: whose cells stand behind the aggregate's answers at map (x, y) points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourcesRequest {
    /// Protocol version of the request.
    pub version: u32,
    /// Map (x, y) points, metres.
    pub points: Vec<[f64; 2]>,
}

/// One robot's own cell under a point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotCell {
    /// The robot's map id.
    pub robot: String,
    /// Its fused height there, metres.
    pub z_m: f64,
    /// Its variance, m².
    pub var_m2: f64,
    /// Scans it fused there.
    pub scans: u32,
    /// The newest scan its tile reflects, ns since the Unix epoch.
    pub newest_scan_ns: u64,
}

/// Per request point, the robots' cells the answer there fuses (a site: every robot's; a robot:
/// its own; empty where no cell is held).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourcesReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// One list per request point, in robot-id order.
    pub items: Vec<Vec<RobotCell>>,
}

/// What a daemon does in a fleet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FleetRole {
    /// A robot with a sensor (publishes its tiles when a site is configured).
    #[default]
    Robot,
    /// A site daemon: no sensor; assembles every robot's tiles of its site and answers for them.
    Site,
}

/// A robot's tiles as a site daemon holds them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotTiles {
    /// The robot's map id.
    pub robot: String,
    /// Tiles held from it.
    pub tiles: u64,
    /// Cells in them.
    pub cells: u64,
    /// The newest scan any of its tiles reflects, ns since the Unix epoch.
    pub newest_scan_ns: u64,
    /// Whether its daemon's liveliness token is seen now.
    pub alive: bool,
}

/// Fleet state in a status reply.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct FleetInfo {
    /// Robot or site.
    pub role: FleetRole,
    /// The site whose key space tiles go to (robot) or come from (site); `None`: no fleet.
    pub site: Option<String>,
    /// Robot: tiles published since start.
    pub tiles_published: u64,
    /// Robot: bytes of tile messages published since start.
    pub tile_bytes_published: u64,
    /// Robot: changed tiles waiting for the next period or the byte budget.
    pub tiles_pending: u64,
    /// Site: tiles recovered from the storage at start.
    pub tiles_from_storage: u64,
    /// Site: whether a storage answered the start's query.
    pub storage_answered: bool,
    /// Site: tile messages received live since start, counted once the site map answers with
    /// them.
    pub tiles_received: u64,
    /// Site: tile messages refused (bad bytes, another version or geometry, older than held).
    pub tiles_refused: u64,
    /// Site: tile messages dropped because the assembler's queue was full (the storage keeps
    /// them: a restart of the site recovers them). Robot: tiles that left its radius whose unsent
    /// change was forgotten (more than `fleet.max_held_departed_tiles` waited with no page on
    /// disk, or a page could not be read back).
    pub tiles_dropped: u64,
    /// Site: the robots whose tiles it holds.
    pub robots: Vec<RobotTiles>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_keys_round_trip_and_foreign_keys_are_refused() {
        let site = MapKeys::new("yard").expect("valid");
        let robot = MapKeys::new("r-2").expect("valid");
        let key = tile_key(&site, &robot, (-3, 12));
        assert_eq!(key, "rangegp/yard/tiles/r-2/-3_12");
        assert_eq!(parse_tile_key(&site, &key), Some(("r-2".into(), (-3, 12))));
        assert_eq!(site_tiles(&site), "rangegp/yard/tiles/**");
        for bad in [
            "rangegp/other/tiles/r-2/1_2",
            "rangegp/yard/tiles/r-2/1",
            "rangegp/yard/tiles/r-2/a_2",
            "rangegp/yard/tiles/r*/1_2",
        ] {
            assert_eq!(parse_tile_key(&site, bad), None, "{bad}");
        }
    }
}
