//! The fit thread: newest validated scan → local range map → window → published snapshot, then
//! (off the scan-to-queryable path) σ calibration, the learner's sample and the aggregate's feed.

use super::AggregateFeed;
use crate::ingest::{Arrival, LatestQueue};
use crate::map::calibration::Calibrator;
use crate::map::local::{hyper_sample, HyperSample, MapParams};
use crate::map::scales::SigmaScales;
use crate::map::{LocalRangeMap, MapSnapshot, Window};
use crate::scan::{RejectReason, ScanInput};
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use rangegp_proto::msg::MapUpdate;
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::atomic::Ordering;
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant};
use tracing::{debug, info_span, warn};

/// Where the fitter sends what it made, besides the window.
pub(super) struct FitOutputs {
    /// Hyperparameter samples for the online learner, with the subset size.
    pub learner: Option<(Arc<LatestQueue<HyperSample>>, usize)>,
    /// Fitted scans for the aggregate thread.
    pub aggregate: Option<Arc<AggregateFeed>>,
    /// Learn σ scales from each next scan (`gp.prequential_calibration`).
    pub calibrate: bool,
    /// Add the unseen relief (always learnt with them) to window answers' σ (`gp.unseen_relief`).
    pub relief: bool,
    /// Weight of the other maps' disagreement far from data (`gp.view_disagreement`).
    pub view_disagreement: f64,
    /// σ scales restored from a checkpoint, which the calibrator starts from
    /// ([`Calibrator::with_prior`]).
    pub prior: Option<SigmaScales>,
    /// Where a [`MapUpdate`] goes when a scan's map is published.
    pub updates: zenoh::pubsub::Publisher<'static>,
}

/// Fits scans from `queue` until `shutdown`; the window holds `capacity` maps.
pub(super) fn fit_loop(
    queue: &LatestQueue<Arrival>,
    state: &DaemonState,
    mut params: MapParams,
    capacity: usize,
    outputs: FitOutputs,
    shutdown: &Shutdown,
) {
    let mut window = Window::new(capacity);
    let mut calibrator = outputs.calibrate.then(|| {
        let fresh = Calibrator::new(outputs.relief).with_view_disagreement(outputs.view_disagreement);
        match outputs.prior {
            Some(prior) => fresh.with_prior(prior),
            None => fresh,
        }
    });
    while !shutdown.is_triggered() {
        let Some(Arrival { scan, received }) = queue.pop_timeout(Duration::from_millis(50)) else {
            continue;
        };
        let _span = info_span!(
            "fit",
            publisher = scan.publisher_id,
            sequence = scan.sequence,
            rays = scan.rays.len()
        )
        .entered();
        let started = Instant::now();
        params.kernel = **state.kernel.load();
        let log = &state.corrections.log;
        let lock = || log.lock().unwrap_or_else(PoisonError::into_inner);
        // Sent with the poses of the corrections issued before it arrived.
        let sent_after = lock().generation_at(received);
        let map = match LocalRangeMap::fit(&scan, &params) {
            Ok(map) => Arc::new(map.with_generation(sent_after)),
            Err(e) => {
                state.metrics.reject(RejectReason::FitFailed);
                warn!(error = %e, "fit failed; scan rejected");
                continue;
            }
        };
        let fitted = started.elapsed();
        let m = &state.metrics;
        m.jittered_tiles
            .fetch_add(map.jittered_tiles() as u64, Ordering::Relaxed);
        // The maps as they stood before this scan: what its returns test.
        let before = state.snapshot.load_full();
        window.push(Arc::clone(&map));
        // Every map as moved by the corrections the published aggregate reflects, so that no
        // query sees a half-corrected map.
        {
            let log = lock();
            state.snapshot.rcu(|old| {
                window.bring_up(&log, old.generation);
                window
                    .snapshot()
                    .with_aggregate(old.aggregate.clone())
                    .with_scales(before.scales)
                    .with_max_sigma(before.max_sigma_m)
                    .with_generation(old.generation)
            });
        }
        // As published: moved by any correction the window was just brought up to.
        let map = window.newest().map_or(map, Arc::clone);
        let latency = received.elapsed();
        m.fit.record(fitted);
        m.scan_to_queryable.record(latency);
        m.accepted.fetch_add(1, Ordering::Relaxed);
        announce(&outputs.updates, &scan, latency, window.len());
        if let Some((samples, subset)) = &outputs.learner {
            samples.push(hyper_sample(&scan, &params, *subset));
        }
        // Off the scan-to-queryable path: the map already answers with the former scales.
        if let Some(c) = calibrator.as_mut() {
            let _span = info_span!("calibrate").entered();
            let calibrating = Instant::now();
            let answered = c.observe(&before, &scan, &map);
            let scales = c.scales();
            state
                .snapshot
                .rcu(|old| MapSnapshot::clone(old).with_scales(scales));
            m.calibrate.record(calibrating.elapsed());
            debug!(answered, "σ scales updated");
        }
        if let Some(feed) = &outputs.aggregate {
            if feed.push((scan, map)).is_some() {
                m.aggregate_skipped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// Tells subscribers (planners, `rangegp load`) that a scan's map answers queries now.
fn announce(
    updates: &zenoh::pubsub::Publisher<'static>,
    scan: &ScanInput,
    latency: Duration,
    window_len: usize,
) {
    let event = MapUpdate {
        version: PROTOCOL_VERSION,
        publisher_id: scan.publisher_id,
        sequence: scan.sequence,
        stamp_ns: scan.stamp_ns,
        latency_ms: latency.as_secs_f64() * 1e3,
        window_len: window_len as u32,
    };
    super::publish_event(updates, &event, "map update");
}
