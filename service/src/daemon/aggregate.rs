//! The aggregate thread: folds every fitted scan into the world aggregate and publishes the
//! result. When it falls behind, the scans that waited meanwhile are fused together in one
//! insert (each tile refitted once), so it catches up instead of dropping scans.

use super::AggregateFeed;
use crate::map::aggregate::world::WorldAggregate;
use crate::map::aggregate::Aggregate;
use crate::priority::{lower_current_thread, Background};
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tracing::{debug, info_span, warn};

/// Folds every fitted scan from `feed` into the world aggregate: each insert takes all the
/// scans waiting (in order) into a copy of the published map (tiles are shared, so a copy costs
/// the cells), evicts tiles beyond `radius_m` of the newest sensor (never by a scan far from
/// everything mapped: [`WorldAggregate::insert_all_and_evict`]), and publishes the copy. A
/// failed insert is counted per scan (not fused) and logged; the published map stays as it was.
pub(super) fn aggregate_loop(
    feed: &AggregateFeed,
    state: &DaemonState,
    mut world: Arc<WorldAggregate>,
    radius_m: f64,
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
    while !shutdown.is_triggered() {
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
        let mut next = WorldAggregate::clone(&world);
        let scans: Vec<_> = batch.iter().map(|(scan, map)| (scan, map.as_ref())).collect();
        let n = batch.len() as u64;
        match pool.install(|| next.insert_all_and_evict(&scans, radius_m)) {
            Ok(evicted) => {
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
