//! Pose corrections on the aggregate thread: move the ledger's scans, edit the cells in memory
//! and the pages on disk, and publish the corrected aggregate with the window's maps moved by
//! the same correction in one snapshot swap.

use super::aggregate::Kept;
use crate::map::aggregate::ledger::ScanRaster;
use crate::map::aggregate::world::WorldAggregate;
use crate::map::correction::ScanId;
use crate::map::LocalRangeMap;
use crate::state::{CorrectionJob, DaemonState};
use rangegp_proto::msg::CorrectionReply;
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, PoisonError};
use tracing::{info, info_span, warn};

/// The corrections the aggregate thread has applied (its maps are brought up to these).
#[derive(Debug, Default)]
pub(super) struct AggregateGeneration(u64);

impl AggregateGeneration {
    /// `maps` brought up to the corrections the aggregate reflects.
    pub(super) fn bring_up<'a>(
        &self,
        state: &DaemonState,
        maps: impl Iterator<Item = &'a Arc<LocalRangeMap>>,
    ) -> Vec<Arc<LocalRangeMap>> {
        let log = state
            .corrections
            .log
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        maps.map(|m| log.bring_up(m, self.0)).collect()
    }
}

/// Applies every correction waiting, in order, answering each.
pub(super) fn apply_waiting(
    state: &DaemonState,
    world: &mut Arc<WorldAggregate>,
    kept: &mut Kept,
    generation: &mut AggregateGeneration,
    pool: &rayon::ThreadPool,
) {
    let Some(waiting) = &state.corrections.waiting else {
        return;
    };
    loop {
        let job = waiting.lock().unwrap_or_else(PoisonError::into_inner).pop_front();
        let Some(job) = job else { return };
        let outcome = apply(&job, state, world, kept, generation, pool);
        // The worker waiting for it may have given up (its bounded wait): nothing to do then.
        let _ = job.reply.try_send(outcome);
    }
}

fn scan_id(r: &ScanRaster) -> ScanId {
    ScanId {
        publisher_id: r.publisher_id,
        sequence: r.sequence,
        stamp_ns: r.stamp_ns,
    }
}

fn apply(
    job: &CorrectionJob,
    state: &DaemonState,
    world: &mut Arc<WorldAggregate>,
    kept: &mut Kept,
    generation: &mut AggregateGeneration,
    pool: &rayon::ThreadPool,
) -> Result<CorrectionReply, String> {
    let _span = info_span!("correct").entered();
    let c = &job.correction;
    let lock = || {
        state
            .corrections
            .log
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    };
    let g = lock().push(Arc::clone(c), job.arrived);
    let plan = pool.install(|| {
        kept.ledger
            .plan(|r| c.apply(scan_id(r), &r.pose), world.params().cell_m)
    });
    let ids = kept.ledger.ids();
    let not_correctable = world
        .history()
        .filter(|r| {
            !ids.contains(&(r.publisher_id, r.sequence))
                && c.names(ScanId {
                    publisher_id: r.publisher_id,
                    sequence: r.sequence,
                    stamp_ns: r.stamp_ns,
                })
        })
        .count();
    let mut next = WorldAggregate::clone(world);
    let on_disk = kept.pages.as_ref().map(|s| s.keys().clone()).unwrap_or_default();
    let applied = match pool.install(|| next.apply_edits(plan.edits, &|t| on_disk.contains(&t))) {
        Ok(applied) => applied,
        Err(e) => {
            lock().void(g);
            warn!(error = %e, "a correction could not be applied; the map is unchanged");
            return Err(format!("the corrected tiles could not be refitted: {e}"));
        }
    };
    let moved = plan.moved.len();
    kept.ledger.commit(plan.moved);
    let mut pages_rewritten = 0u32;
    if let Some(store) = &mut kept.pages {
        for (tile, edits) in &applied.page_edits {
            let written = store.read(*tile).and_then(|mut page| {
                page.apply_edits(edits, next.params());
                store.write(&page)
            });
            match written {
                Ok(()) => pages_rewritten += 1,
                Err(e) => {
                    state.metrics.aggregate_page_failures.fetch_add(1, Relaxed);
                    let e: &dyn std::error::Error = &e;
                    warn!(
                        error = e,
                        "a paged tile could not be corrected; it keeps its old cells"
                    );
                }
            }
        }
    }
    *world = Arc::new(next);
    generation.0 = g;
    let window_maps_moved = state
        .snapshot
        .load()
        .maps()
        .iter()
        .filter(|m| {
            c.names(ScanId {
                publisher_id: m.publisher_id,
                sequence: m.sequence,
                stamp_ns: m.stamp_ns,
            })
        })
        .count();
    {
        let log = lock();
        state
            .snapshot
            .rcu(|old| old.with_aggregate(Some(Arc::clone(world))).brought_up(&log, g));
    }
    let m = &state.metrics;
    m.corrections.fetch_add(1, Relaxed);
    m.ledger_bytes.store(kept.ledger.bytes() as u64, Relaxed);
    let reply = CorrectionReply {
        version: PROTOCOL_VERSION,
        generation: g,
        window_maps_moved: window_maps_moved as u32,
        aggregate_scans_moved: moved as u32,
        not_correctable: not_correctable as u32,
        cells_changed: applied.cells_changed,
        tiles_refitted: applied.tiles_refitted as u32,
        pages_rewritten,
        apply_ms: job.arrived.elapsed().as_secs_f64() * 1e3,
    };
    info!(
        generation = g,
        scans = moved,
        window = window_maps_moved,
        cells = applied.cells_changed,
        pages = pages_rewritten,
        ms = reply.apply_ms,
        "pose correction applied"
    );
    Ok(reply)
}
