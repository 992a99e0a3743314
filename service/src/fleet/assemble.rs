//! The site daemon's assembler thread: the storage's tiles at start, then every robot's tiles
//! as they are published, into the [`SiteMap`] whose aggregate the site's queries answer from.

use super::site_map::{SiteLimits, SiteMap};
use crate::map::aggregate::world::WorldParams;
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use rangegp_proto::codec::{decode, Encoding};
use rangegp_proto::fleet::{parse_tile_key, site_tiles, TileUpdate};
use rangegp_proto::keys::MapKeys;
use std::collections::BTreeSet;
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant};
use tracing::{info, info_span, warn};
use zenoh::Wait;

/// Tile messages waiting for the assembler at most (about 2 KiB each); beyond, one is dropped
/// and counted (the storage still has it: a restart recovers it).
pub const TILE_QUEUE: usize = 16_384;

/// The largest tile message of `params`' geometry, bytes: every cell of a tile (at most 40 bytes
/// each in any encoding a robot sends, bincode's varints or JSON's shortest floats aside) and a
/// header with the robot's name. A larger message is refused in the callback, unread, so that the
/// queue holds at most [`TILE_QUEUE`] such messages, not as many of the codec's 64 MiB.
pub fn max_tile_bytes(params: &WorldParams) -> usize {
    let cells = usize::try_from(params.tile_cells).unwrap_or(0).pow(2);
    4096 + cells * 160
}

/// How the site assembles (`[fleet]` and the robots' aggregate geometry).
#[derive(Debug, Clone)]
pub struct SiteSettings {
    /// The site's keys (its map id).
    pub site: MapKeys,
    /// How long the start waits for a storage, then for its tiles.
    pub storage_wait: Duration,
    /// The robots' aggregate geometry and experts.
    pub params: WorldParams,
    /// How much the site holds at most.
    pub limits: SiteLimits,
}

/// A tile message as received: its key and its bytes.
pub type Arrival = (String, Vec<u8>);

/// Declares the live subscription to every robot's tiles of the site, feeding `tx` (declared
/// before the storage is asked, so that nothing published in between is missed). Messages over
/// `max_bytes` ([`max_tile_bytes`]) are refused and counted without a copy.
pub fn subscribe(
    session: &zenoh::Session,
    site: &MapKeys,
    tx: SyncSender<Arrival>,
    max_bytes: usize,
    state: Arc<DaemonState>,
) -> zenoh::Result<zenoh::pubsub::Subscriber<()>> {
    session
        .declare_subscriber(site_tiles(site))
        .callback(move |sample| {
            if sample.payload().len() > max_bytes {
                state
                    .fleet
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .tiles_refused += 1;
                return;
            }
            let arrival = (
                sample.key_expr().as_str().to_owned(),
                sample.payload().to_bytes().into_owned(),
            );
            if let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) = tx.try_send(arrival) {
                state
                    .fleet
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .tiles_dropped += 1;
            }
        })
        .wait()
}

/// The site map as the storage holds it: waits (bounded by the settings) for a storage of the
/// site's tiles, takes them all in and publishes the result, before the site answers anything.
pub fn recover(
    session: &zenoh::Session,
    state: &DaemonState,
    settings: &SiteSettings,
    shutdown: &Shutdown,
) -> SiteMap {
    let mut site = SiteMap::new(settings.params, settings.limits);
    let (stored, answered) = from_storage(session, &settings.site, settings.storage_wait, shutdown);
    {
        let mut fleet = state.fleet.lock().unwrap_or_else(PoisonError::into_inner);
        fleet.storage_answered = answered;
        fleet.tiles_from_storage = stored.len() as u64;
    }
    let recovered = stored.len();
    offer(state, &mut site, &settings.site, stored);
    refresh_robots(session, state, &site);
    info!(
        site = settings.site.map_id(),
        tiles = recovered,
        storage = answered,
        "site map recovered from the storage"
    );
    site
}

/// Assembles live tiles into `site` until `shutdown`, publishing the site map into the snapshot
/// after each batch; refreshes which robots are alive every second.
pub fn assemble_loop(
    session: &zenoh::Session,
    state: &DaemonState,
    mut site: SiteMap,
    settings: &SiteSettings,
    arrivals: &Receiver<Arrival>,
    shutdown: &Shutdown,
) {
    let mut next_liveliness = Instant::now();
    while !shutdown.is_triggered() {
        let mut batch = Vec::new();
        match arrivals.recv_timeout(Duration::from_millis(100)) {
            Ok(first) => {
                batch.push(first);
                batch.extend(arrivals.try_iter().take(TILE_QUEUE));
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return,
        }
        if !batch.is_empty() {
            let received = batch.len() as u64;
            offer(state, &mut site, &settings.site, batch);
            // Counted once the map answers with them: a status that counts a tile shows it.
            state
                .fleet
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .tiles_received += received;
        }
        if Instant::now() >= next_liveliness {
            next_liveliness = Instant::now() + Duration::from_secs(1);
            refresh_robots(session, state, &site);
        }
    }
}

/// Waits (bounded) until a storage of the site's tiles is reachable, then takes every tile it
/// holds; returns them and whether a storage answered.
fn from_storage(
    session: &zenoh::Session,
    site: &MapKeys,
    wait: Duration,
    shutdown: &Shutdown,
) -> (Vec<Arrival>, bool) {
    let querier = match session.declare_querier(site_tiles(site)).wait() {
        Ok(q) => q,
        Err(e) => {
            warn!(error = %e, "cannot ask for the stored tiles; the site starts from live tiles");
            return (Vec::new(), false);
        }
    };
    let deadline = Instant::now() + wait;
    loop {
        if querier.matching_status().wait().is_ok_and(|m| m.matching()) {
            break;
        }
        if shutdown.sleep_until((Instant::now() + Duration::from_millis(20)).min(deadline))
            || Instant::now() >= deadline
        {
            warn!(
                site = site.map_id(),
                "no storage of the site's tiles answers; the site starts from live tiles"
            );
            return (Vec::new(), false);
        }
    }
    // The whole wait (a storage, then its tiles) is `wait`: the query gets what is left.
    let left = deadline
        .saturating_duration_since(Instant::now())
        .max(Duration::from_millis(100));
    let replies = match session.get(site_tiles(site)).timeout(left).wait() {
        Ok(r) => r,
        Err(e) => {
            warn!(error = %e, "the stored tiles cannot be asked for");
            return (Vec::new(), false);
        }
    };
    (arrivals(&replies), true)
}

/// Every sample of a query's replies as (key, bytes), until the query ends (error replies are
/// skipped): what a storage holds.
pub fn arrivals(replies: &zenoh::handlers::FifoChannelHandler<zenoh::query::Reply>) -> Vec<Arrival> {
    let mut tiles = Vec::new();
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result() {
            tiles.push((
                sample.key_expr().as_str().to_owned(),
                sample.payload().to_bytes().into_owned(),
            ));
        }
    }
    tiles
}

/// Decodes `arrivals`, checks each against its key, offers them to `site` and publishes the
/// result; refusals are counted and the first reason of a batch logged.
fn offer(state: &DaemonState, site: &mut SiteMap, keys: &MapKeys, arrivals: Vec<Arrival>) {
    let _span = info_span!("assemble", tiles = arrivals.len()).entered();
    let mut refused = 0u64;
    let mut first_reason: Option<String> = None;
    let mut updates = Vec::with_capacity(arrivals.len());
    for (key, bytes) in arrivals {
        let named = parse_tile_key(keys, &key);
        match decode::<TileUpdate>(Encoding::Bincode, &bytes) {
            Ok(u) if named.as_ref() == Some(&(u.robot.clone(), (u.tile_column, u.tile_row))) => {
                updates.push(u)
            }
            Ok(_) => {
                refused += 1;
                first_reason.get_or_insert_with(|| format!("{key}: the message names another robot or tile"));
            }
            Err(e) => {
                refused += 1;
                first_reason.get_or_insert_with(|| format!("{key}: {e}"));
            }
        }
    }
    let outcome = site.offer(updates);
    let (reasons, failed) = match outcome {
        Ok(reasons) => (reasons, None),
        Err((e, reasons)) => (reasons, Some(e)),
    };
    refused += reasons.len() as u64;
    if let Some(r) = reasons.first() {
        first_reason.get_or_insert_with(|| r.to_string());
    }
    if let Some(e) = failed {
        warn!(error = %e, "site tiles could not all be refitted; the old fits answer there");
    }
    if let Some(reason) = first_reason {
        warn!(refused, reason, "tiles refused");
    }
    state
        .fleet
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .tiles_refused += refused;
    let world = Arc::new(site.world().clone());
    state
        .snapshot
        .rcu(|old| old.with_aggregate(Some(Arc::clone(&world))));
    state.site_sources.store(Some(Arc::new(site.sources())));
}

/// The robots of the site map, each marked alive when its daemon's token is seen, into status.
fn refresh_robots(session: &zenoh::Session, state: &DaemonState, site: &SiteMap) {
    let alive = alive_maps(session);
    let mut robots = site.robots();
    for r in &mut robots {
        r.alive = alive.contains(&r.robot);
    }
    state.fleet.lock().unwrap_or_else(PoisonError::into_inner).robots = robots;
}

/// Map ids whose daemons' liveliness tokens are seen now (robots and sites alike).
fn alive_maps(session: &zenoh::Session) -> BTreeSet<String> {
    let Ok(replies) = session
        .liveliness()
        .get("rangegp/*/@alive")
        .timeout(Duration::from_millis(500))
        .wait()
    else {
        return BTreeSet::new();
    };
    let mut alive = BTreeSet::new();
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result() {
            if let Some(id) = sample.key_expr().as_str().split('/').nth(1) {
                alive.insert(id.to_owned());
            }
        }
    }
    alive
}

#[cfg(test)]
mod tests {
    use super::*;
    use rangegp_proto::codec::encode;
    use rangegp_proto::fleet::TileCell;
    use rangegp_proto::PROTOCOL_VERSION;

    #[test]
    fn the_largest_valid_tile_fits_the_bound_in_either_encoding() {
        let params = WorldParams::default();
        let n = params.tile_cells;
        let cells = (0..n * n)
            .map(|k| TileCell {
                column: -1_000_000 * n + k % n,
                row: -1_000_000 * n + k / n,
                z_m: -1.234_567_890_123_456_7e-300,
                var_m2: 1.234_567_890_123_456_7e300,
                scans: u32::MAX,
            })
            .collect();
        let tile = TileUpdate {
            version: PROTOCOL_VERSION,
            robot: "r".repeat(64),
            tile_column: -1_000_000,
            tile_row: -1_000_000,
            cell_m: params.cell_m,
            tile_cells: n,
            revision: u64::MAX,
            published_ns: u64::MAX,
            newest_scan_ns: u64::MAX,
            cells,
        };
        let bound = max_tile_bytes(&params);
        for encoding in [Encoding::Bincode, Encoding::Json] {
            let bytes = encode(encoding, &tile).expect("a tile encodes").len();
            assert!(bytes <= bound, "{encoding:?}: {bytes} bytes over {bound}");
        }
        assert!(bound < 64 << 10, "the bound is a tile's, not the codec's 64 MiB");
    }
}
