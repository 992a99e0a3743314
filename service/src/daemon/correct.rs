//! Pose corrections on the aggregate thread: move the ledger's scans, edit the cells in memory
//! and the pages on disk, and publish the corrected aggregate with the window's maps moved by
//! the same correction in one snapshot swap.

use crate::checkpoint::{PageError, PageStore};
use crate::map::aggregate::ledger::Ledger;
use crate::map::aggregate::world::WorldAggregate;
use crate::map::aggregate::AggregateError;
use crate::map::correction::{Correction, ScanId};
use crate::map::LocalRangeMap;
use crate::state::{CorrectionJob, DaemonState};
use rangegp_proto::msg::CorrectionReply;
use rangegp_proto::PROTOCOL_VERSION;
use rayon::prelude::*;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, PoisonError};
use tracing::{info, info_span, warn};

/// What the aggregate thread keeps besides the map: the site map on disk (checkpoints on) and
/// the ledger of each scan's cells (what a pose correction moves).
pub(super) struct Kept {
    /// Tiles beyond the radius, on disk.
    pub pages: Option<PageStore>,
    /// Each fused scan's cells, within a memory budget.
    pub ledger: Ledger,
    /// Where the cells each scan replaced are announced.
    pub changes: zenoh::pubsub::Publisher<'static>,
    /// Where tiles leaving the radius go for the site's key space (in a fleet).
    pub departures: Option<std::sync::Arc<crate::fleet::publish::Departures>>,
}

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
) {
    let Some(waiting) = &state.corrections.waiting else {
        return;
    };
    loop {
        let job = waiting.lock().unwrap_or_else(PoisonError::into_inner).pop_front();
        let Some(job) = job else { return };
        let outcome = apply(&job, state, world, kept, generation);
        // The worker waiting for it may have given up (its bounded wait): nothing to do then.
        let _ = job.reply.try_send(outcome);
    }
}

/// What correcting the aggregate did ([`correct_aggregate`]).
#[derive(Debug)]
pub struct AggregateCorrection {
    /// The corrected aggregate.
    pub world: WorldAggregate,
    /// Scans moved.
    pub moved: usize,
    /// Scans the correction names that the aggregate fused but the ledger no longer keeps.
    pub not_correctable: usize,
    /// Cells whose evidence changed (in memory and on disk).
    pub cells_changed: u64,
    /// Tiles refitted in memory.
    pub tiles_refitted: usize,
    /// Pages rewritten on disk.
    pub pages_rewritten: u32,
    /// Pages that could not be read or written (they keep their old cells).
    pub page_failures: u32,
}

/// Corrects a copy of `world` by `c`: the ledger's scans it names move (their rasters carried
/// to the new poses), the cells they left and reached are edited, in-memory tiles refitted and
/// the pages on disk rewritten. The ledger changes only when the refit succeeds.
pub fn correct_aggregate(
    world: &WorldAggregate,
    ledger: &mut Ledger,
    pages: Option<&mut PageStore>,
    c: &Correction,
) -> Result<AggregateCorrection, AggregateError> {
    let stale = |cell, insert| world.replaced_at(cell).is_some_and(|at| at > insert);
    let plan = ledger.plan(|r| c.apply(r.into(), &r.pose), world.params().cell_m, &stale);
    let ids = ledger.ids();
    let not_correctable = world
        .history()
        .filter(|r| !ids.contains(&(r.publisher_id, r.sequence)) && c.names(ScanId::from(*r)))
        .count();
    let mut next = WorldAggregate::clone(world);
    let on_disk = pages.as_ref().map(|s| s.keys().clone()).unwrap_or_default();
    let applied = next.apply_edits(plan.edits, &|t| on_disk.contains(&t))?;
    let moved = plan.moved.len();
    ledger.commit(plan.moved);
    let (mut pages_rewritten, mut page_failures) = (0u32, 0u32);
    if let Some(store) = pages {
        // Only tiles on disk get page edits: each is rewritten in place, several at once.
        let outcomes: Vec<Result<(), PageError>> = applied
            .page_edits
            .par_iter()
            .map(|(tile, edits)| {
                let mut page = store.read(*tile)?;
                page.apply_edits(edits, next.params());
                store.rewrite(&page)
            })
            .collect();
        for outcome in outcomes {
            match outcome {
                Ok(()) => pages_rewritten += 1,
                Err(e) => {
                    page_failures += 1;
                    let e: &dyn std::error::Error = &e;
                    warn!(
                        error = e,
                        "a paged tile could not be corrected; it keeps its old cells"
                    );
                }
            }
        }
    }
    Ok(AggregateCorrection {
        world: next,
        moved,
        not_correctable,
        cells_changed: applied.cells_changed,
        tiles_refitted: applied.tiles_refitted,
        pages_rewritten,
        page_failures,
    })
}

fn apply(
    job: &CorrectionJob,
    state: &DaemonState,
    world: &mut Arc<WorldAggregate>,
    kept: &mut Kept,
    generation: &mut AggregateGeneration,
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
    // On the global pool (both cores): a correction is rare and queries wait for it.
    let corrected = match correct_aggregate(world, &mut kept.ledger, kept.pages.as_mut(), c) {
        Ok(corrected) => corrected,
        Err(e) => {
            lock().void(g);
            warn!(error = %e, "a correction could not be applied; the map is unchanged");
            return Err(format!("the corrected tiles could not be refitted: {e}"));
        }
    };
    let m = &state.metrics;
    m.aggregate_page_failures
        .fetch_add(u64::from(corrected.page_failures), Relaxed);
    *world = Arc::new(corrected.world);
    generation.0 = g;
    // The window the correction was applied to: the snapshot it replaced.
    let window_maps_moved = {
        let log = lock();
        let old = state
            .snapshot
            .rcu(|old| old.with_aggregate(Some(Arc::clone(world))).brought_up(&log, g));
        c.maps_named(old.maps())
    };
    m.corrections.fetch_add(1, Relaxed);
    m.ledger_bytes.store(kept.ledger.bytes() as u64, Relaxed);
    let reply = CorrectionReply {
        version: PROTOCOL_VERSION,
        generation: g,
        window_maps_moved: window_maps_moved as u32,
        aggregate_scans_moved: corrected.moved as u32,
        not_correctable: corrected.not_correctable as u32,
        cells_changed: corrected.cells_changed,
        tiles_refitted: corrected.tiles_refitted as u32,
        pages_rewritten: corrected.pages_rewritten,
        apply_ms: job.arrived.elapsed().as_secs_f64() * 1e3,
    };
    info!(
        generation = g,
        scans = reply.aggregate_scans_moved,
        window = window_maps_moved,
        cells = reply.cells_changed,
        pages = reply.pages_rewritten,
        ms = reply.apply_ms,
        "pose correction applied"
    );
    Ok(reply)
}
