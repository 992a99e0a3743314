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
        // A tile that owns no cell here is never sent: cells leave a robot's memory by eviction
        // (its page keeps them) or stand in a neighbour's margin, neither of which is a deletion.
        for key in world.tile_keys().collect::<Vec<_>>() {
            let cells = world.tile_cells(key);
            if !cells.is_empty() && self.sent.get(&key).copied() != Some(hash(&cells)) {
                self.pending.entry(key).or_insert((now, None)).1 = None;
            }
        }
        for page in pages {
            if !page.cells.is_empty() && self.sent.get(&page.key).copied() != Some(hash(&page.cells)) {
                self.pending.entry(page.key).or_insert((now, None)).1 = Some(page.cells);
            }
        }
    }

    /// Forgets what was sent, so that every tile goes again (the site's subscribers were
    /// unreachable: what was put meanwhile reached no one).
    pub fn forget_sent(&mut self) {
        self.sent.clear();
    }

    /// Records that `outgoing` reached Zenoh.
    pub fn sent(&mut self, outgoing: &Outgoing) {
        self.sent.insert(outgoing.key, outgoing.hash);
    }

    /// Puts `outgoing` back among the waiting tiles (its put failed).
    pub fn retry(&mut self, outgoing: Outgoing, now: Instant) {
        self.pending
            .entry(outgoing.key)
            .or_insert((now, outgoing.departed));
    }

    /// Tiles waiting.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// The waiting tiles as messages, oldest change first, until `budget` bytes are spent (at
    /// least one is taken); they leave the waiting list, and count as sent once
    /// [`Self::sent`] says so.
    pub fn take(
        &mut self,
        world: &WorldAggregate,
        robot: &str,
        budget: u64,
        published_ns: u64,
    ) -> Vec<Outgoing> {
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
            let cells = departed.clone().unwrap_or_else(|| world.tile_cells(key));
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
                    out.push(Outgoing {
                        key,
                        hash: hash(&cells),
                        departed,
                        update,
                        bytes,
                    });
                }
                Err(e) => warn!(error = %e, "a tile cannot be encoded; it is not sent"),
            }
        }
        out
    }
}

/// One tile on its way out.
#[derive(Debug)]
pub struct Outgoing {
    /// Tile index.
    pub key: (i32, i32),
    /// Hash of its cells.
    hash: u64,
    /// Its cells when it left the robot's radius (kept for a retry).
    departed: Option<TileCells>,
    /// The message.
    pub update: TileUpdate,
    /// The message's bytes.
    pub bytes: Vec<u8>,
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
/// While nothing subscribes to the site's tiles (no storage, no site reachable) tiles wait; when
/// a subscriber comes back, every tile goes again.
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
    // A publisher on a key under this robot's tiles that is never put to (no tile index parses
    // from it): its matching status says whether a storage or a site subscribes.
    let probe_key = format!(
        "rangegp/{}/tiles/{}/reach",
        settings.site.map_id(),
        robot.map_id()
    );
    let probe = match session.declare_publisher(probe_key).wait() {
        Ok(p) => p,
        Err(e) => {
            warn!(error = %e, "cannot watch the site's subscribers; no tile will be published");
            return;
        }
    };
    let mut reachable = false;
    while !shutdown.sleep_until(Instant::now() + settings.period) {
        let Some(world) = state.snapshot.load().aggregate.clone() else {
            continue;
        };
        let _span = info_span!("tiles", site = settings.site.map_id()).entered();
        let now_reachable = probe.matching_status().wait().is_ok_and(|m| m.matching());
        if now_reachable && !reachable {
            ledger.forget_sent();
        }
        reachable = now_reachable;
        ledger.scan(&world, departures.take(), Instant::now());
        let (mut tiles, mut bytes) = (0u64, 0u64);
        if reachable {
            for outgoing in ledger.take(&world, robot.map_id(), budget, crate::metrics::unix_now_ns()) {
                if shutdown.is_triggered() {
                    ledger.retry(outgoing, Instant::now());
                    continue;
                }
                let key = tile_key(&settings.site, &robot, outgoing.key);
                let put = session
                    .put(&key, outgoing.bytes.clone())
                    .encoding(encoding.clone())
                    .congestion_control(CongestionControl::Block)
                    .wait();
                match put {
                    Ok(()) => {
                        tiles += 1;
                        bytes += outgoing.bytes.len() as u64;
                        ledger.sent(&outgoing);
                    }
                    Err(e) => {
                        debug!(error = %e, key, "a tile was not published; it waits");
                        ledger.retry(outgoing, Instant::now());
                    }
                }
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
        // A failed put waits again; a successful one counts as sent.
        for o in first {
            ledger.retry(o, t0);
        }
        assert_eq!(ledger.pending(), 3);
        for o in ledger.take(&w, "r", u64::MAX, 7) {
            ledger.sent(&o);
        }
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
        assert_eq!((sent[0].update.tile_column, sent[0].update.tile_row), (0, 0));
        assert_eq!(sent[0].update.cells[0].z_m, 0.5);
        ledger.sent(&sent[0]);
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
        let emptied = TilePage {
            key: (3, 0),
            cells: Vec::new(),
            points: Vec::new(),
            noise_var: Vec::new(),
        };
        ledger.scan(&changed, vec![page, emptied], t0);
        let sent = ledger.take(&changed, "r", u64::MAX, 9);
        assert_eq!(sent.len(), 1, "a page without cells is not a deletion");
        assert_eq!(sent[0].update.cells[0].z_m, 0.9);
        ledger.sent(&sent[0]);
        // After the subscribers were unreachable, every tile goes again.
        ledger.forget_sent();
        ledger.scan(&changed, Vec::new(), t0);
        assert_eq!(ledger.pending(), 3);
    }
}
