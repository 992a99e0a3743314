//! The online hyperparameter thread: the fitter picks up its newest kernel for the next scan.

use crate::gp::hyper::OnlineHyperparameters;
use crate::gp::Kernel;
use crate::ingest::LatestQueue;
use crate::map::local::HyperSample;
use crate::metrics::Metrics;
use crate::priority::{lower_current_thread, Background};
use crate::shutdown::Shutdown;
use arc_swap::ArcSwap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tracing::{debug, info_span, warn};

/// Applies online hyperparameter updates from the newest scan sample until `shutdown`.
/// Failures keep the previous estimate.
pub(super) fn learn_loop(
    mut online: OnlineHyperparameters,
    samples: &LatestQueue<HyperSample>,
    kernel: &ArcSwap<Kernel>,
    metrics: &Metrics,
    shutdown: &Shutdown,
) {
    lower_current_thread(Background::Idle);
    while !shutdown.is_triggered() {
        let Some(sample) = samples.pop_timeout(Duration::from_millis(50)) else {
            continue;
        };
        let _span = info_span!("hyperparameters", rays = sample.inputs.len()).entered();
        match online.update(sample.as_training_set()) {
            Ok(_) => {
                kernel.store(Arc::new(online.kernel()));
                metrics.hyper_updates.fetch_add(1, Ordering::Relaxed);
                debug!(
                    variance = online.kernel().variance,
                    length_scale = online.kernel().length_scale,
                    "hyperparameters updated"
                );
            }
            Err(e) => warn!(error = %e, "hyperparameter update failed; keeping the previous estimate"),
        }
    }
}
