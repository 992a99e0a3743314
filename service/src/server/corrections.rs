//! The query worker's side of a pose correction: validate it, hand it to the aggregate thread
//! and wait (bounded) for the outcome, or, without an aggregate, move the window's maps here.

use crate::map::correction::{Correction, InvalidCorrection};
use crate::state::{CorrectionJob, DaemonState, CORRECTIONS_WAITING};
use rangegp_proto::msg::{CorrectionReply, CorrectionRequest};
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{mpsc, Arc, PoisonError};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Longest wait for the aggregate thread to apply a correction.
pub const CORRECTION_DEADLINE: Duration = Duration::from_secs(30);

/// Why a correction was not applied (nothing changed, except for `TimedOut`).
#[derive(Debug, Error)]
pub enum SubmitError {
    /// The request is invalid.
    #[error(transparent)]
    Invalid(#[from] InvalidCorrection),
    /// Too many corrections are waiting already; retry later.
    #[error("{CORRECTIONS_WAITING} corrections are waiting already; retry later")]
    Busy,
    /// The aggregate could not be corrected.
    #[error("{0}")]
    Failed(String),
    /// Not applied within [`CORRECTION_DEADLINE`] (it stays queued and may still apply).
    #[error("the correction was not applied within {} s (it stays queued and may still apply)", CORRECTION_DEADLINE.as_secs())]
    TimedOut,
}

/// Applies `req` (arrived at `arrived`) and says what it changed once queries see it.
pub fn submit(
    state: &DaemonState,
    req: &CorrectionRequest,
    arrived: Instant,
) -> Result<CorrectionReply, SubmitError> {
    let correction = Arc::new(Correction::from_request(req)?);
    let Some(waiting) = &state.corrections.waiting else {
        return Ok(window_only(state, correction, arrived));
    };
    let (reply, outcome) = mpsc::sync_channel(1);
    {
        let mut queue = waiting.lock().unwrap_or_else(PoisonError::into_inner);
        if queue.len() >= CORRECTIONS_WAITING {
            return Err(SubmitError::Busy);
        }
        queue.push_back(CorrectionJob {
            correction,
            arrived,
            reply,
        });
    }
    match outcome.recv_timeout(CORRECTION_DEADLINE) {
        Ok(Ok(reply)) => Ok(reply),
        Ok(Err(message)) => Err(SubmitError::Failed(message)),
        Err(_) => Err(SubmitError::TimedOut),
    }
}

/// Without an aggregate, a correction moves the window's maps only.
fn window_only(state: &DaemonState, correction: Arc<Correction>, arrived: Instant) -> CorrectionReply {
    let mut log = state
        .corrections
        .log
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    let g = log.push(Arc::clone(&correction), arrived);
    let old = state.snapshot.rcu(|old| old.brought_up(&log, g));
    let moved = correction.maps_named(old.maps());
    state.metrics.corrections.fetch_add(1, Relaxed);
    CorrectionReply {
        version: PROTOCOL_VERSION,
        generation: g,
        window_maps_moved: moved as u32,
        aggregate_scans_moved: 0,
        not_correctable: 0,
        cells_changed: 0,
        tiles_refitted: 0,
        pages_rewritten: 0,
        apply_ms: arrived.elapsed().as_secs_f64() * 1e3,
    }
}
