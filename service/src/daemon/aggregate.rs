//! The aggregate thread: folds fitted scans into the world aggregate and publishes each result.

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

/// How the aggregate thread paces itself and bounds its area.
#[derive(Debug, Clone, Copy)]
pub(super) struct AggregatePace {
    /// Evict tiles beyond this distance from the newest sensor position, metres.
    pub radius_m: f64,
    /// At most one insert per interval.
    pub min_interval: Duration,
}

/// Folds fitted scans into the world aggregate at most once per `pace.min_interval`, newest
/// first: each insert goes into a copy of the published map (tiles are shared, so a copy costs
/// the cells), tiles beyond `pace.radius_m` of the sensor are evicted (never by a scan far from
/// everything mapped: [`WorldAggregate::insert_and_evict`]), and the copy is published. A failed
/// insert is counted and logged; the published map stays as it was.
pub(super) fn aggregate_loop(
    feed: &AggregateFeed,
    state: &DaemonState,
    mut world: Arc<WorldAggregate>,
    pace: AggregatePace,
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
        let Some((scan, map)) = feed.pop_timeout(Duration::from_millis(50)) else {
            continue;
        };
        let _span = info_span!(
            "aggregate",
            publisher = scan.publisher_id,
            sequence = scan.sequence
        )
        .entered();
        let started = Instant::now();
        let mut next = WorldAggregate::clone(&world);
        match pool.install(|| next.insert_and_evict(&scan, &map, pace.radius_m)) {
            Ok(evicted) => {
                world = Arc::new(next);
                state
                    .snapshot
                    .rcu(|old| old.with_aggregate(Some(Arc::clone(&world))));
                m.aggregate_insert.record(started.elapsed());
                m.aggregate_inserts.fetch_add(1, Ordering::Relaxed);
                m.aggregate_evicted_tiles
                    .fetch_add(evicted as u64, Ordering::Relaxed);
                debug!(
                    cells = world.len(),
                    tiles = world.tiles(),
                    evicted,
                    "aggregate updated"
                );
            }
            Err(e) => {
                m.aggregate_failed.fetch_add(1, Ordering::Relaxed);
                warn!(error = %e, "aggregate insert failed; scan kept in the window only");
            }
        }
        shutdown.sleep_until(started + pace.min_interval);
    }
}
