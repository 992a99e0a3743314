//! A robot's tiles into its site's key space: every period, the aggregate tiles whose cells
//! changed since they were last sent (each tile's cells hashed and compared with what was sent),
//! oldest change first, within a byte budget; tiles that leave the robot's radius are sent
//! from their pages if their last change was not.

use crate::map::aggregate::world::{Cell, TileCells, TilePage, WorldAggregate};
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use rangegp_proto::codec::{encode, Encoding};
use rangegp_proto::fleet::{tile_key, TileCell, TileUpdate};
use rangegp_proto::keys::MapKeys;
use rangegp_proto::PROTOCOL_VERSION;
use std::collections::hash_map::DefaultHasher;
use std::collections::{BTreeMap, HashMap};
use std::hash::{Hash, Hasher};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};
use tracing::{debug, info_span, warn};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

/// How the robot publishes (`[fleet]`).
#[derive(Debug, Clone)]
pub struct TileSettings {
    /// The site's keys.
    pub site: MapKeys,
    /// A changed tile is sent at most once per period.
    pub period: Duration,
    /// Bytes per second at most.
    pub max_bytes_per_s: u64,
}

/// Tiles that left the robot's radius, handed over by the aggregate thread.
#[derive(Debug, Default)]
pub struct Departures(Mutex<Vec<TilePage>>);

impl Departures {
    /// Hands `pages` over (their cells are sent if they changed since last sent).
    pub fn push(&self, pages: &[TilePage]) {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .extend(pages.iter().cloned());
    }

    fn take(&self) -> Vec<TilePage> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

/// The publisher's memory: per tile what was sent, and the changes waiting.
#[derive(Debug, Default)]
pub struct TileLedger {
    /// Per tile, the hash of the cells last sent.
    sent: HashMap<(i32, i32), u64>,
    /// Waiting tiles and since when, with their cells when they left the radius.
    pending: BTreeMap<(i32, i32), (Instant, Option<TileCells>)>,
}

impl TileLedger {
    /// Notes the tiles of `world` whose cells differ from what was sent, and the departed
    /// `pages` whose do.
    pub fn scan(&mut self, world: &WorldAggregate, pages: Vec<TilePage>, now: Instant) {
        // Every tile's cells, hashed (a few ms a second for a full radius): a fit's identity would
        // be cheaper, but a freed fit's address can come back for the next one.
        for key in world.tile_keys().collect::<Vec<_>>() {
            let cells = world.tile_cells(key);
            let sent = self.sent.get(&key).copied();
            if sent != Some(hash(&cells)) && !(cells.is_empty() && sent.is_none()) {
                self.pending.entry(key).or_insert((now, None)).1 = None;
            }
        }
        for page in pages {
            if self.sent.get(&page.key).copied() != Some(hash(&page.cells)) {
                self.pending.entry(page.key).or_insert((now, None)).1 = Some(page.cells);
            }
        }
    }

    /// Tiles waiting.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// The waiting tiles as messages, oldest change first, until `budget` bytes are spent (at
    /// least one is taken); each taken tile counts as sent.
    pub fn take(
        &mut self,
        world: &WorldAggregate,
        robot: &str,
        budget: u64,
        published_ns: u64,
    ) -> Vec<(TileUpdate, Vec<u8>)> {
        let mut order: Vec<((i32, i32), Instant)> = self.pending.iter().map(|(&k, &(t, _))| (k, t)).collect();
        order.sort_by_key(|&(k, t)| (t, k));
        let newest_scan_ns = world.newest_scan().map_or(0, |s| s.stamp_ns);
        let mut out = Vec::new();
        let mut spent = 0u64;
        for (key, _) in order {
            if spent >= budget && !out.is_empty() {
                break;
            }
            let Some((_, departed)) = self.pending.remove(&key) else {
                continue;
            };
            let cells = departed.unwrap_or_else(|| world.tile_cells(key));
            let update = TileUpdate {
                version: PROTOCOL_VERSION,
                robot: robot.to_owned(),
                tile_column: key.0,
                tile_row: key.1,
                cell_m: world.params().cell_m,
                tile_cells: world.params().tile_cells,
                revision: world.inserts(),
                published_ns,
                newest_scan_ns,
                cells: cells
                    .iter()
                    .map(|&((column, row), c)| TileCell {
                        column,
                        row,
                        z_m: c.z,
                        var_m2: c.var,
                        scans: c.scans,
                    })
                    .collect(),
            };
            match encode(Encoding::Bincode, &update) {
                Ok(bytes) => {
                    spent += bytes.len() as u64;
                    self.sent.insert(key, hash(&cells));
                    out.push((update, bytes));
                }
                Err(e) => warn!(error = %e, "a tile cannot be encoded; it is not sent"),
            }
        }
        out
    }
}

/// Wall-clock now, ns since the Unix epoch (0 before it).
pub(crate) fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Hash of a tile's cells, bit for bit.
fn hash(cells: &[((i32, i32), Cell)]) -> u64 {
    let mut h = DefaultHasher::new();
    for ((i, j), c) in cells {
        (i, j, c.z.to_bits(), c.var.to_bits(), c.scans).hash(&mut h);
    }
    h.finish()
}

/// Every period until `shutdown`: sends the changed tiles of the published aggregate (and the
/// departed ones) on the site's keys, within the byte budget; counts into the fleet status.
pub fn publish_loop(
    session: &zenoh::Session,
    state: &DaemonState,
    settings: &TileSettings,
    departures: &Departures,
    shutdown: &Shutdown,
) {
    let robot = state.keys.clone();
    let mut ledger = TileLedger::default();
    let budget = (settings.max_bytes_per_s as f64 * settings.period.as_secs_f64()).ceil() as u64;
    let encoding = rangegp_transport::zenoh_encoding(Encoding::Bincode);
    while !shutdown.sleep_until(Instant::now() + settings.period) {
        let Some(world) = state.snapshot.load().aggregate.clone() else {
            continue;
        };
        let _span = info_span!("tiles", site = settings.site.map_id()).entered();
        ledger.scan(&world, departures.take(), Instant::now());
        let (mut tiles, mut bytes) = (0u64, 0u64);
        for (update, payload) in ledger.take(&world, robot.map_id(), budget, wall_ns()) {
            let key = tile_key(&settings.site, &robot, (update.tile_column, update.tile_row));
            let size = payload.len() as u64;
            match session
                .put(&key, payload)
                .encoding(encoding.clone())
                .congestion_control(CongestionControl::Block)
                .wait()
            {
                Ok(()) => {
                    tiles += 1;
                    bytes += size;
                }
                Err(e) => debug!(error = %e, key, "a tile was not published"),
            }
        }
        let mut fleet = state.fleet.lock().unwrap_or_else(PoisonError::into_inner);
        fleet.tiles_published += tiles;
        fleet.tile_bytes_published += bytes;
        fleet.tiles_pending = ledger.pending() as u64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::aggregate::world::WorldParams;

    fn world_with(cells: &[((i32, i32), f64)]) -> WorldAggregate {
        let mut w = WorldAggregate::new(WorldParams::default());
        let mut tiles: BTreeMap<(i32, i32), TileCells> = BTreeMap::new();
        for &(c, z) in cells {
            tiles
                .entry((c.0.div_euclid(10), c.1.div_euclid(10)))
                .or_default()
                .push((
                    c,
                    Cell {
                        z,
                        var: 1e-4,
                        scans: 1,
                    },
                ));
        }
        w.replace_tiles(&tiles).expect("fits");
        w
    }

    #[test]
    fn only_changed_tiles_are_sent_oldest_first_within_the_budget() {
        let t0 = Instant::now();
        let mut ledger = TileLedger::default();
        let w = world_with(&[((1, 1), 0.1), ((15, 1), 0.2), ((31, 1), 0.3)]);
        ledger.scan(&w, Vec::new(), t0);
        // Tiles (0,0), (1,0), (3,0) own cells; tiles fitted to margin cells alone own none and
        // are not sent.
        assert_eq!(ledger.pending(), 3);
        let first = ledger.take(&w, "r", 1, 7);
        assert_eq!(first.len(), 1, "a budget of one byte still sends one tile");
        let rest = ledger.take(&w, "r", u64::MAX, 7);
        assert_eq!(rest.len(), 2);
        assert_eq!(ledger.pending(), 0);
        // Nothing changed: nothing to send, even after a refit of the same cells.
        let mut same = w.clone();
        same.replace_tiles(&BTreeMap::from([((0, 0), vec![((1, 1), w.cells()[&(1, 1)])])]))
            .expect("fits");
        ledger.scan(&same, Vec::new(), t0);
        assert_eq!(ledger.pending(), 0);
        // One cell changes: its tile alone goes, with the new height.
        let changed = world_with(&[((1, 1), 0.5), ((15, 1), 0.2), ((31, 1), 0.3)]);
        ledger.scan(&changed, Vec::new(), t0);
        let sent = ledger.take(&changed, "r", u64::MAX, 8);
        assert_eq!(sent.len(), 1);
        assert_eq!((sent[0].0.tile_column, sent[0].0.tile_row), (0, 0));
        assert_eq!(sent[0].0.cells[0].z_m, 0.5);
        // A tile that left the radius with a change not yet sent goes from its page.
        let page = TilePage {
            key: (1, 0),
            cells: vec![(
                (15, 1),
                Cell {
                    z: 0.9,
                    var: 1e-4,
                    scans: 2,
                },
            )],
            points: Vec::new(),
            noise_var: Vec::new(),
        };
        ledger.scan(&changed, vec![page], t0);
        let sent = ledger.take(&changed, "r", u64::MAX, 9);
        assert_eq!(sent.len(), 1);
        assert_eq!(sent[0].0.cells[0].z_m, 0.9);
    }
}
