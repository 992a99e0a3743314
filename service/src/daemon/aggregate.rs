//! The aggregate thread: folds every fitted scan into the world aggregate and publishes the
//! result. When it falls behind, the scans that waited meanwhile are fused together in one
//! insert (each tile refitted once), so it catches up instead of dropping scans.

use super::correct::{apply_waiting, AggregateGeneration, Kept};
use super::AggregateFeed;
use crate::checkpoint::PageStore;
use crate::map::aggregate::world::{Change, TilePage, WorldAggregate};
use crate::map::aggregate::Aggregate;
use crate::metrics::Metrics;
use crate::priority::{lower_current_thread, Background};
use crate::scan::ScanInput;
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use rangegp_proto::msg::{ChangeEvent, ChangedCell};
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tracing::{debug, info_span, warn};

/// How far from its sensor each scan is fused, so that fusing keeps up with the sensor on a
/// share of one core: the cost of a scan grows as the square of its reach, so with c the
/// measured seconds per square metre of reach and f the scans per second arriving, the reach
/// is √(share / (f c)), between [`MIN_REACH_M`] and the aggregate's `max_reach_m`. Every scan is
/// fused; a fast sensor's scans each contribute their nearest (and surest) ground.
#[derive(Debug, Clone, Copy)]
pub(super) struct FusionBudget {
    /// Fraction of one core the aggregate may use (`aggregate.cpu_share`).
    share: f64,
    /// Longest reach, metres.
    max_reach_m: f64,
    /// Seconds of insert per m² of reach², smoothed.
    cost: Option<f64>,
    /// Scans per second, smoothed.
    rate: Option<f64>,
}

/// The reach never falls below this (metres): the ground right around the robot.
pub(super) const MIN_REACH_M: f64 = 3.0;
/// Weight of a new measurement in the smoothed cost and rate.
const SMOOTHING: f64 = 0.2;

impl FusionBudget {
    /// A budget of `share` of a core for reaches up to `max_reach_m`.
    pub(super) fn new(share: f64, max_reach_m: f64) -> Self {
        Self {
            share,
            max_reach_m,
            cost: None,
            rate: None,
        }
    }

    /// The reach to fuse the next scans with.
    pub(super) fn reach_m(&self) -> f64 {
        match (self.cost, self.rate) {
            (Some(c), Some(f)) if c > 0.0 && f > 0.0 => {
                (self.share / (f * c)).sqrt().clamp(MIN_REACH_M, self.max_reach_m)
            }
            _ => self.max_reach_m,
        }
    }

    /// Learns from an insert of `scans` at `reach_m` that took `took`, `since_last` after the
    /// previous insert began.
    pub(super) fn observe(&mut self, scans: usize, reach_m: f64, took: Duration, since_last: Duration) {
        let smooth = |old: Option<f64>, new: f64| Some(old.map_or(new, |o| o + SMOOTHING * (new - o)));
        let area = scans as f64 * reach_m * reach_m;
        if area > 0.0 {
            self.cost = smooth(self.cost, took.as_secs_f64() / area);
        }
        if since_last > Duration::ZERO {
            self.rate = smooth(self.rate, scans as f64 / since_last.as_secs_f64());
        }
    }
}

/// Folds every fitted scan from `feed` into the world aggregate, each out to the reach `budget`
/// allows: each insert takes all the scans waiting (in order) into a copy of the published map (tiles are shared, so a copy costs
/// the cells), evicts tiles beyond `radius_m` of the newest sensor (never by a scan far from
/// everything mapped: [`WorldAggregate::insert_all_and_evict`]), and publishes the copy. A
/// failed insert is counted per scan (not fused) and logged; the published map stays as it was.
pub(super) fn aggregate_loop(
    feed: &AggregateFeed,
    state: &DaemonState,
    mut world: Arc<WorldAggregate>,
    radius_m: f64,
    mut budget: FusionBudget,
    mut kept: Kept,
    shutdown: &Shutdown,
) {
    let m = &state.metrics;
    // One worker of its own: the aggregate's parallel loops must not queue the fitter's tiles
    // behind a whole insert in the shared pool (seen as 100 ms fit spikes).
    lower_current_thread(Background::Idle);
    let pool = match rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .thread_name(|_| "rangegp-aggregate-pool".into())
        .start_handler(|_| lower_current_thread(Background::Idle))
        .build()
    {
        Ok(pool) => pool,
        Err(e) => {
            warn!(error = %e, "cannot start the aggregate's worker; aggregate disabled");
            return;
        }
    };
    let mut last_start: Option<Instant> = None;
    let mut generation = AggregateGeneration::default();
    while !shutdown.is_triggered() {
        apply_waiting(state, &mut world, &mut kept, &mut generation);
        let batch = feed.drain_timeout(Duration::from_millis(50));
        let Some((newest, _)) = batch.last() else {
            continue;
        };
        let _span = info_span!(
            "aggregate",
            publisher = newest.publisher_id,
            sequence = newest.sequence,
            scans = batch.len()
        )
        .entered();
        let started = Instant::now();
        let since_last = last_start.map_or(Duration::ZERO, |t| started - t);
        last_start = Some(started);
        let reach_m = budget.reach_m();
        let mut next = WorldAggregate::clone(&world);
        next.set_window_scales(&state.snapshot.load().scales);
        // Maps fitted before a correction this aggregate reflects are moved by it first.
        let maps = generation.bring_up(state, batch.iter().map(|(_, map)| map));
        if let Some(store) = &kept.pages {
            // The radius around the newest sensor, and every tile a scan of the batch may fuse
            // into or refit as a neighbour (its reach, plus a tile's half diagonal and margin):
            // a tile beyond the radius (a radius shorter than the reach, or the robot moved
            // within the batch) must come back before it is touched, or its page would be
            // replaced by the new cells alone when it is evicted again.
            let s = newest.pose.translation.vector;
            let mut discs = vec![(s.x, s.y, radius_m)];
            let params = world.params();
            let half_side = (0.5 * params.tile_cells as f64 + params.margin_cells as f64) * params.cell_m;
            let tile_reach = reach_m + half_side * std::f64::consts::SQRT_2;
            discs.extend(maps.iter().map(|map| {
                let p = map.sensor_position();
                (p.x, p.y, tile_reach)
            }));
            page_in(store, &mut next, &discs, &pool, m);
        }
        let scans: Vec<_> = batch
            .iter()
            .zip(&maps)
            .map(|((scan, _), map)| (scan, map.as_ref()))
            .collect();
        let n = batch.len() as u64;
        let inserted = pool.install(|| next.insert_all_and_evict(&scans, radius_m, reach_m));
        budget.observe(batch.len(), reach_m, started.elapsed(), since_last);
        m.aggregate_reach_mm
            .store((reach_m * 1e3) as u64, Ordering::Relaxed);
        match inserted {
            Ok(inserted) => {
                for raster in inserted.fused {
                    kept.ledger.push(raster);
                }
                for ((scan, _), cells) in batch.iter().zip(&inserted.changes) {
                    announce_changes(&kept.changes, scan, cells, world.params().cell_m, m);
                }
                m.ledger_scans.store(kept.ledger.len() as u64, Ordering::Relaxed);
                m.ledger_bytes
                    .store(kept.ledger.bytes() as u64, Ordering::Relaxed);
                let evicted = inserted.evicted;
                // Out of the published map only once its successor is ready: write them first,
                // then hand them to the tile publisher, which reads back those on disk.
                let on_disk = match &mut kept.pages {
                    Some(store) => page_out(store, &evicted, m),
                    None => vec![false; evicted.len()],
                };
                if let Some(departures) = &kept.departures {
                    departures.push(evicted.iter().cloned().zip(on_disk));
                }
                let evicted = evicted.len();
                world = Arc::new(next);
                state
                    .snapshot
                    .rcu(|old| old.with_aggregate(Some(Arc::clone(&world))));
                m.aggregate_insert.record(started.elapsed());
                m.aggregate_inserts.fetch_add(n, Ordering::Relaxed);
                m.aggregate_evicted_tiles
                    .fetch_add(evicted as u64, Ordering::Relaxed);
                debug!(
                    scans = n,
                    cells = world.len(),
                    tiles = world.tiles(),
                    evicted,
                    "aggregate updated"
                );
            }
            Err(e) => {
                m.aggregate_failed.fetch_add(n, Ordering::Relaxed);
                warn!(error = %e, scans = n, "aggregate insert failed; the scans stay in the window only");
            }
        }
    }
}

/// Publishes the cells `scan` replaced (nothing when none).
fn announce_changes(
    publisher: &zenoh::pubsub::Publisher<'static>,
    scan: &ScanInput,
    cells: &[Change],
    cell_m: f64,
    m: &Metrics,
) {
    if cells.is_empty() {
        return;
    }
    m.changed_cells.fetch_add(cells.len() as u64, Ordering::Relaxed);
    let event = ChangeEvent {
        version: PROTOCOL_VERSION,
        publisher_id: scan.publisher_id,
        sequence: scan.sequence,
        stamp_ns: scan.stamp_ns,
        cell_m,
        cells: cells
            .iter()
            .map(|c| ChangedCell {
                x_m: c.x_m,
                y_m: c.y_m,
                old_z_m: c.old.z,
                old_sigma_m: c.old.var.sqrt(),
                new_z_m: c.new.z.is_finite().then_some(c.new.z),
                new_sigma_m: c.new.z.is_finite().then(|| c.new.var.sqrt()),
            })
            .collect(),
    };
    super::publish_event(publisher, &event, "change event");
}

/// Brings back the tiles on disk whose centre lies within one of the `discs` (x, y, radius,
/// metres) that `world` does not hold, before the scans near them are fused. A page that cannot be read is counted and logged and stays on
/// disk; the tile starts anew from the scans.
fn page_in(
    store: &PageStore,
    world: &mut WorldAggregate,
    discs: &[(f64, f64, f64)],
    pool: &rayon::ThreadPool,
    m: &Metrics,
) {
    let wanted: Vec<(i32, i32)> = store
        .keys()
        .iter()
        .copied()
        .filter(|&k| !world.has_tile(k) && discs.iter().any(|&(x, y, r)| world.tile_distance(k, x, y) <= r))
        .collect();
    if wanted.is_empty() {
        return;
    }
    let loaded: Vec<_> = wanted
        .into_iter()
        .filter_map(|k| {
            store
                .read(k)
                .inspect_err(|e| {
                    m.aggregate_page_failures.fetch_add(1, Ordering::Relaxed);
                    let e: &dyn std::error::Error = e;
                    warn!(error = e, "a paged tile cannot be read; it starts anew");
                })
                .ok()
        })
        .collect();
    match pool.install(|| world.restore_pages(loaded)) {
        Ok(restored) => {
            m.aggregate_paged_in.fetch_add(restored as u64, Ordering::Relaxed);
            debug!(restored, "tiles paged in");
        }
        Err(e) => {
            m.aggregate_page_failures.fetch_add(1, Ordering::Relaxed);
            warn!(error = %e, "paged tiles cannot be refitted; they start anew");
        }
    }
}

/// Writes the tiles that left the radius to disk, saying which were written; a failure is
/// counted and logged (that tile is then forgotten, as without a site map).
fn page_out(store: &mut PageStore, evicted: &[TilePage], m: &Metrics) -> Vec<bool> {
    evicted
        .iter()
        .map(|page| {
            // A tile that owns no cell (one refitted from a neighbour's margin alone) would
            // replace a real page with nothing; it holds nothing to keep.
            if page.cells.is_empty() {
                return false;
            }
            match store.write(page) {
                Ok(()) => {
                    m.aggregate_paged_out.fetch_add(1, Ordering::Relaxed);
                    true
                }
                Err(e) => {
                    m.aggregate_page_failures.fetch_add(1, Ordering::Relaxed);
                    let e: &dyn std::error::Error = &e;
                    warn!(
                        error = e,
                        "a tile leaving the radius cannot be written; it is forgotten"
                    );
                    false
                }
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reach_shrinks_as_the_rate_times_the_cost_grows_within_bounds() {
        let mut b = FusionBudget::new(0.5, 10.0);
        assert_eq!(b.reach_m(), 10.0, "full reach until measured");
        // 50 ms for one scan at 10 m (0.5 ms per m²), one scan every 50 ms (20 Hz): half a core
        // allows 25 ms per scan, i.e. a reach of 10 / √2.
        for _ in 0..50 {
            b.observe(1, 10.0, Duration::from_millis(50), Duration::from_millis(50));
        }
        assert!((b.reach_m() - 10.0 / 2f64.sqrt()).abs() < 0.05, "{}", b.reach_m());
        // Slow scans: full reach; a flood: the floor.
        let mut slow = FusionBudget::new(0.5, 10.0);
        slow.observe(1, 10.0, Duration::from_millis(50), Duration::from_secs(1));
        assert_eq!(slow.reach_m(), 10.0);
        let mut flood = FusionBudget::new(0.5, 10.0);
        flood.observe(100, 10.0, Duration::from_secs(5), Duration::from_millis(100));
        assert_eq!(flood.reach_m(), MIN_REACH_M);
    }
}
