//! The checkpoint writer: writes the published aggregate when it changed since the last write.
//! Disk errors are counted and logged; ingest, fitting and queries never wait for the disk.

use super::{encode, identity, Checkpoint, Store};
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use crate::map::aggregate::Aggregate;
use crate::state::DaemonState;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;
use tracing::{debug, info_span, warn};

/// Writes the aggregate of a [`DaemonState`] when it changed since the last write.
#[derive(Debug)]
pub struct Writer {
    store: Store,
    identity: u64,
    last: Option<Arc<WorldAggregate>>,
}

impl Writer {
    /// A writer for the map `map_id` with aggregate settings `params`; `restored` is the
    /// aggregate already on disk (not written again until it changes).
    pub fn new(
        store: Store,
        map_id: &str,
        params: &WorldParams,
        restored: Option<Arc<WorldAggregate>>,
    ) -> Self {
        Self {
            store,
            identity: identity(map_id, params),
            last: restored,
        }
    }

    /// Writes the published aggregate if it is not the one written last.
    pub fn write_if_changed(&mut self, state: &DaemonState) {
        let snapshot = state.snapshot.load_full();
        let Some(world) = snapshot.aggregate.clone() else {
            return;
        };
        if self.last.as_ref().is_some_and(|w| Arc::ptr_eq(w, &world)) {
            return;
        }
        // An empty map on disk is worth nothing and would replace one that was not empty:
        // only a deliberate reset (`rangegpd reset-checkpoints`) clears the checkpoints.
        if world.is_empty() {
            state
                .metrics
                .checkpoints_empty_refused
                .fetch_add(1, Ordering::Relaxed);
            self.last = Some(world);
            return;
        }
        let _span = info_span!("checkpoint", inserts = world.inserts()).entered();
        let started = Instant::now();
        let kernel = **state.kernel.load();
        let checkpoint = Checkpoint {
            created_unix_ns: crate::metrics::unix_now_ns(),
            kernel_variance: kernel.variance,
            length_scale: kernel.length_scale,
            world: world.state(),
            scales: Some(snapshot.scales),
        };
        let m = &state.metrics;
        let written = encode(&checkpoint, self.identity)
            .map_err(|e| e.to_string())
            .and_then(|bytes| self.store.write(&bytes).map_err(|e| e.to_string()));
        match written {
            Ok(path) => {
                m.checkpoint_write.record(started.elapsed());
                m.checkpoints_written.fetch_add(1, Ordering::Relaxed);
                self.last = Some(world);
                debug!(file = %path.display(), "checkpoint written");
            }
            Err(e) => {
                let failures = m.checkpoint_failures.fetch_add(1, Ordering::Relaxed) + 1;
                // Every failure is counted; the log says so for the first and then sparsely.
                if failures.is_power_of_two() {
                    warn!(error = %e, failures, "checkpoint not written; the map keeps running");
                }
            }
        }
    }
}
