//! A robot's tiles into its site's key space: every period, the aggregate tiles whose cells
//! changed since they were last sent (each tile's cells hashed and compared with what was sent),
//! oldest change first, within a byte budget; tiles that leave the robot's radius are sent
//! from their pages if their last change was not. A departed tile waits as a key when its page
//! is on disk (read back when it goes), else with its cells, at most
//! [`TileSettings::max_held_departed`] of them: a robot off its site's network for hours holds
//! bounded memory, and counts what it had to forget.

use crate::checkpoint::PageReader;
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
    /// The aggregate's pages on disk (with checkpoints), where departed tiles are read back.
    pub pages: Option<PageReader>,
    /// Departed tiles with no page that may wait with their cells; beyond, the oldest change is
    /// forgotten (`fleet.max_held_departed_tiles`).
    pub max_held_departed: usize,
}

/// A tile that left the robot's radius, and whether its page is on disk.
pub type Departure = (TilePage, bool);

/// Tiles that left the robot's radius, handed over by the aggregate thread.
#[derive(Debug, Default)]
pub struct Departures(Mutex<Vec<Departure>>);

impl Departures {
    /// Hands departed tiles over, each with whether its page was written to the page store
    /// (their cells are sent if they changed since last sent).
    pub fn push(&self, departed: impl IntoIterator<Item = Departure>) {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .extend(departed);
    }

    fn take(&self) -> Vec<Departure> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

/// Where a waiting tile's cells are.
#[derive(Debug, Clone)]
enum Waiting {
    /// In the published aggregate.
    InWorld,
    /// It left the radius; its page on disk holds them.
    OnPage,
    /// It left the radius with no page; held here.
    Held(TileCells),
}

/// The publisher's memory: per tile what was sent, and the changes waiting.
#[derive(Debug)]
pub struct TileLedger {
    /// Per tile, the hash of the cells last sent.
    sent: HashMap<(i32, i32), u64>,
    /// Waiting tiles, since when, and where their cells are.
    pending: BTreeMap<(i32, i32), (Instant, Waiting)>,
    /// Where departed tiles' pages are read back, if anywhere.
    pages: Option<PageReader>,
    /// Departed tiles held with their cells at most.
    max_held: usize,
    /// Departed tiles whose unsent change was forgotten: over `max_held`, or a page unreadable.
    forgotten: u64,
}

impl TileLedger {
    /// A ledger with nothing sent; departed tiles are read back from `pages` when on disk, and
    /// at most `max_held` others wait with their cells.
    pub fn new(pages: Option<PageReader>, max_held: usize) -> Self {
        Self {
            sent: HashMap::new(),
            pending: BTreeMap::new(),
            pages,
            max_held,
            forgotten: 0,
        }
    }

    /// Departed tiles whose unsent change was forgotten since start.
    pub fn forgotten(&self) -> u64 {
        self.forgotten
    }

    /// Departed tiles waiting with their cells in memory.
    #[cfg(test)]
    fn held(&self) -> usize {
        self.pending
            .values()
            .filter(|(_, w)| matches!(w, Waiting::Held(_)))
            .count()
    }

    /// Sets where `key` waits from (keeping since when, if it waited already).
    fn wait(&mut self, key: (i32, i32), waiting: Waiting, now: Instant) {
        self.pending.entry(key).or_insert((now, Waiting::InWorld)).1 = waiting;
    }

    /// Forgets the oldest held departed tiles beyond `max_held` (a count over the waiting
    /// tiles, once a period).
    fn bound_held(&mut self) {
        let mut held: Vec<((i32, i32), Instant)> = self
            .pending
            .iter()
            .filter(|(_, (_, w))| matches!(w, Waiting::Held(_)))
            .map(|(&k, &(t, _))| (k, t))
            .collect();
        let Some(over) = held.len().checked_sub(self.max_held).filter(|&n| n > 0) else {
            return;
        };
        held.sort_by_key(|&(k, t)| (t, k));
        for &(key, _) in &held[..over] {
            self.pending.remove(&key);
        }
        self.forgotten += over as u64;
        warn!(
            tiles = over,
            held = self.max_held,
            "departed tiles waiting for the site exceed fleet.max_held_departed_tiles and have no \
             page on disk; their oldest unsent changes are forgotten"
        );
    }

    /// Notes the tiles of `world` whose cells differ from what was sent, and the departed
    /// `pages` whose do (each with whether its page is on disk).
    pub fn scan(&mut self, world: &WorldAggregate, pages: Vec<Departure>, now: Instant) {
        // Every tile's cells, hashed (a few ms a second for a full radius): a fit's identity would
        // be cheaper, but a freed fit's address can come back for the next one.
        // A tile that owns no cell here is never sent: cells leave a robot's memory by eviction
        // (its page keeps them) or stand in a neighbour's margin, neither of which is a deletion.
        for key in world.tile_keys().collect::<Vec<_>>() {
            let cells = world.tile_cells(key);
            if !cells.is_empty() && self.sent.get(&key).copied() != Some(hash(&cells)) {
                self.wait(key, Waiting::InWorld, now);
            }
        }
        for (page, on_disk) in pages {
            // A tile back in the published map (paged in again since it left) goes from there.
            if world.has_tile(page.key) {
                continue;
            }
            if !page.cells.is_empty() && self.sent.get(&page.key).copied() != Some(hash(&page.cells)) {
                let waiting = if on_disk && self.pages.is_some() {
                    Waiting::OnPage
                } else {
                    Waiting::Held(page.cells)
                };
                self.wait(page.key, waiting, now);
            }
        }
        self.bound_held();
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

    /// Puts `outgoing` back among the waiting tiles (its put failed), unless a newer change of
    /// it waits already.
    pub fn retry(&mut self, outgoing: Outgoing, now: Instant) {
        if !self.pending.contains_key(&outgoing.key) {
            self.wait(outgoing.key, outgoing.departed, now);
            self.bound_held();
        }
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
            let cells = match &departed {
                Waiting::InWorld => world.tile_cells(key),
                Waiting::Held(cells) => cells.clone(),
                Waiting::OnPage => match self.pages.as_ref().map(|p| p.read(key)) {
                    Some(Ok(page)) if !page.cells.is_empty() => page.cells,
                    // A page that holds no cell is not a deletion: nothing goes.
                    Some(Ok(_)) | None => continue,
                    Some(Err(e)) => {
                        self.forgotten += 1;
                        let e: &dyn std::error::Error = &e;
                        warn!(
                            error = e,
                            "a departed tile's page cannot be read; its change is not sent"
                        );
                        continue;
                    }
                },
            };
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
    /// Where its cells were (kept for a retry).
    departed: Waiting,
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
    let mut ledger = TileLedger::new(settings.pages.clone(), settings.max_held_departed);
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
        fleet.tiles_dropped = ledger.forgotten();
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
        let mut ledger = TileLedger::new(None, 16);
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
            seen: Vec::new(),
        };
        let emptied = TilePage {
            key: (3, 0),
            cells: Vec::new(),
            points: Vec::new(),
            noise_var: Vec::new(),
            seen: Vec::new(),
        };
        // Tiles (1, 0) and (3, 0) left the radius: the map holds only (0, 0) now.
        let left = world_with(&[((1, 1), 0.5)]);
        ledger.scan(&left, vec![(page.clone(), false), (emptied, false)], t0);
        let sent = ledger.take(&left, "r", u64::MAX, 9);
        assert_eq!(sent.len(), 1, "a page without cells is not a deletion");
        assert_eq!(sent[0].update.cells[0].z_m, 0.9);
        ledger.sent(&sent[0]);
        // A departure whose tile is back in the map by the time it is seen goes from the map.
        let mut again = page;
        again.cells[0].1.z = 0.7;
        ledger.scan(&changed, vec![(again, false)], t0);
        let sent = ledger.take(&changed, "r", u64::MAX, 10);
        let back: Vec<_> = sent.iter().filter(|o| o.key == (1, 0)).collect();
        assert_eq!(back.len(), 1);
        assert_eq!(
            back[0].update.cells[0].z_m, 0.2,
            "the map's cells, not the old page's"
        );
        for o in &sent {
            ledger.sent(o);
        }
        // After the subscribers were unreachable, every tile goes again.
        ledger.forget_sent();
        ledger.scan(&changed, Vec::new(), t0);
        assert_eq!(ledger.pending(), 3);
    }

    fn departed(key: (i32, i32), z: f64) -> TilePage {
        TilePage {
            key,
            cells: vec![(
                (key.0 * 10, key.1 * 10),
                Cell {
                    z,
                    var: 1e-4,
                    scans: 1,
                },
            )],
            points: Vec::new(),
            noise_var: Vec::new(),
            seen: Vec::new(),
        }
    }

    #[test]
    fn departed_tiles_without_pages_are_held_up_to_the_bound_and_the_oldest_forgotten() {
        let t0 = Instant::now();
        let w = WorldAggregate::new(WorldParams::default());
        let mut ledger = TileLedger::new(None, 3);
        let early: Vec<Departure> = (0..2).map(|i| (departed((i, 0), 0.1), false)).collect();
        ledger.scan(&w, early, t0);
        assert_eq!((ledger.held(), ledger.forgotten()), (2, 0));
        let later: Vec<Departure> = (2..5).map(|i| (departed((i, 0), 0.2), false)).collect();
        ledger.scan(&w, later, t0 + Duration::from_secs(1));
        assert_eq!(ledger.held(), 3, "held at the bound");
        assert_eq!(ledger.forgotten(), 2, "the two oldest forgotten and counted");
        let sent = ledger.take(&w, "r", u64::MAX, 1);
        let keys: Vec<_> = sent.iter().map(|o| o.key).collect();
        assert_eq!(keys, [(2, 0), (3, 0), (4, 0)], "the newest changes go");
        assert_eq!(ledger.held(), 0);
        // A failed put holds its cells again, within the bound.
        for o in sent {
            ledger.retry(o, t0);
        }
        assert_eq!((ledger.held(), ledger.pending()), (3, 3));
    }

    #[test]
    fn departed_tiles_on_disk_wait_without_their_cells_and_are_read_back() {
        let dir = std::env::temp_dir().join(format!("rangegp-departed-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut store = crate::checkpoint::PageStore::open(&dir, 11).expect("open");
        let on_disk = departed((1, 2), 0.7);
        store.write(&on_disk).expect("write");
        let t0 = Instant::now();
        let w = WorldAggregate::new(WorldParams::default());
        let mut ledger = TileLedger::new(Some(store.reader()), 1);
        // One tile on disk, one whose page could not be written: only the latter is held.
        ledger.scan(&w, vec![(on_disk, true), (departed((3, 4), 0.3), false)], t0);
        assert_eq!((ledger.pending(), ledger.held()), (2, 1));
        let sent = ledger.take(&w, "r", u64::MAX, 1);
        assert_eq!(sent.len(), 2);
        assert_eq!(sent[0].update.cells[0].z_m, 0.7, "read back from its page");
        assert_eq!(sent[1].update.cells[0].z_m, 0.3);
        // A page gone by the time it is sent: counted forgotten, not sent.
        for o in sent {
            ledger.retry(o, t0);
        }
        std::fs::remove_dir_all(&dir).expect("remove");
        let sent = ledger.take(&w, "r", u64::MAX, 2);
        assert_eq!(sent.len(), 1);
        assert_eq!(sent[0].key, (3, 4));
        assert_eq!(ledger.forgotten(), 1);
    }
}
