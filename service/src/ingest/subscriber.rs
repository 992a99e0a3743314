//! The ingest thread: takes scans from the iceoryx2 service, validates a private copy, and hands
//! accepted scans to the fitter. iceoryx2 has no async API, so this is a plain thread.

use super::plausibility::{PoseGate, PoseLimits, PoseVerdict};
use super::queue::LatestQueue;
use super::sequence::{SequenceCheck, SequenceTracker, Source};
use super::validate::{check_header, validate, ValidationLimits};
use super::Arrival;
use crate::metrics::throttle::Throttle;
use crate::metrics::Metrics;
use crate::scan::RejectReason;
use crate::shutdown::Shutdown;
use iceoryx2::prelude::*;
use rangegp_proto::scan::{node_builder, open_scan_service, ScanHeader, ScanPoint, ScanServiceError};
use std::sync::atomic::Ordering;
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;
use tracing::{debug, info, info_span, warn};

/// The ingest thread could not open its subscriber. Only [`IngestError::ServiceName`] and
/// [`IngestError::Spawn`] stop the daemon's start; the others are retried with back-off while
/// the daemon serves queries (another process may hold the slots or the service for a while).
#[derive(Debug, Error)]
pub enum IngestError {
    /// The service name is not a valid iceoryx2 service name.
    #[error("invalid iceoryx2 service name {name:?}")]
    ServiceName {
        /// Name given.
        name: String,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::service::service_name::ServiceNameError,
    },
    /// The iceoryx2 node could not be created (shared memory or permissions).
    #[error("cannot create the iceoryx2 node")]
    Node(#[source] iceoryx2::node::NodeCreationFailure),
    /// The scan service could not be opened or created (incompatible settings or types).
    #[error("cannot open the scan service {name:?}")]
    Service {
        /// Service name.
        name: String,
        /// iceoryx2's reason.
        #[source]
        source: ScanServiceError,
    },
    /// The subscriber could not be created (too many subscribers).
    #[error("cannot create the scan subscriber")]
    Subscriber(#[source] iceoryx2::port::subscriber::SubscriberCreateError),
    /// The OS refused to start the thread.
    #[error("cannot spawn the ingest thread")]
    Spawn(#[from] std::io::Error),
    /// The thread stopped before reporting whether it started.
    #[error("ingest thread exited during start-up")]
    StartupLost,
}

impl IngestError {
    /// Whether waiting can cure it (the node, the service or a subscriber slot may free up).
    fn is_transient(&self) -> bool {
        matches!(
            self,
            IngestError::Node(_) | IngestError::Service { .. } | IngestError::Subscriber(_)
        )
    }
}

/// Settings of the ingest thread.
#[derive(Debug, Clone)]
pub struct IngestSettings {
    /// iceoryx2 service name.
    pub service_name: String,
    /// Validation bounds.
    pub limits: ValidationLimits,
    /// Poll period when no sample is waiting.
    pub poll_interval: Duration,
    /// Dead-node cleanup period.
    pub cleanup_interval: Duration,
    /// A sequence jump beyond this many numbers restarts the source's bookkeeping.
    pub sequence_restart_window: u64,
    /// Plausible poses.
    pub pose: PoseLimits,
    /// Longest wait between two attempts to open the subscriber.
    pub max_retry_interval: Duration,
}

/// A running ingest thread; stops when the shared shutdown flag is set.
#[derive(Debug)]
pub struct IngestHandle {
    thread: JoinHandle<()>,
}

impl IngestHandle {
    /// Waits for the thread to finish (after shutdown was requested).
    pub fn join(self) {
        if self.thread.join().is_err() {
            warn!("ingest thread panicked");
        }
    }
}

/// Starts the ingest thread and waits for its first attempt to subscribe: when it succeeded, no
/// scan published after this returns is missed; when it failed for a cause that can pass (see
/// [`IngestError`]), the thread keeps trying with back-off and the state shows in `status`.
pub fn spawn_ingest(
    settings: IngestSettings,
    queue: Arc<LatestQueue<Arrival>>,
    metrics: Arc<Metrics>,
    shutdown: Shutdown,
) -> Result<IngestHandle, IngestError> {
    let (ready_tx, ready_rx) = mpsc::sync_channel(1);
    let thread = std::thread::Builder::new()
        .name("rangegp-ingest".into())
        .spawn(move || {
            let Some(intake) = open_with_retry(&settings, &metrics, &shutdown, ready_tx) else {
                return;
            };
            intake.run(&settings, &queue, &metrics, &shutdown);
        })?;
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(IngestHandle { thread }),
        Ok(Err(e)) => {
            let _ = thread.join();
            Err(e)
        }
        Err(_) => Err(IngestError::StartupLost),
    }
}

/// Opens the subscriber, retrying transient failures with doubling waits (from 250 ms up to
/// `settings.max_retry_interval`) until it succeeds or shutdown is requested. The first
/// attempt's outcome goes to `ready` (a permanent failure as the error).
fn open_with_retry(
    settings: &IngestSettings,
    metrics: &Metrics,
    shutdown: &Shutdown,
    ready: mpsc::SyncSender<Result<(), IngestError>>,
) -> Option<Intake> {
    let mut ready = Some(ready);
    let mut wait = Duration::from_millis(250);
    loop {
        match Intake::open(settings) {
            Ok(intake) => {
                metrics.set_ingest_state(None);
                if let Some(r) = ready.take() {
                    let _ = r.send(Ok(()));
                }
                return Some(intake);
            }
            Err(e) if e.is_transient() => {
                let cause = rangegp_proto::error_chain(&e);
                warn!(error = %cause, retry_in_ms = wait.as_millis() as u64, "cannot subscribe to scans; queries are still served");
                metrics.set_ingest_state(Some(cause));
                if let Some(r) = ready.take() {
                    let _ = r.send(Ok(()));
                }
            }
            Err(e) => {
                if let Some(r) = ready.take() {
                    let _ = r.send(Err(e));
                }
                return None;
            }
        }
        if shutdown.sleep_until(Instant::now() + wait) {
            return None;
        }
        wait = (wait * 2).min(settings.max_retry_interval);
    }
}

struct Intake {
    node: Node<ipc::Service>,
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, [ScanPoint], ScanHeader>,
    sequences: SequenceTracker,
    poses: PoseGate,
    skipped_log: Throttle,
    restart_log: Throttle,
}

/// At most one line per this interval for per-scan events.
const LOG_INTERVAL: Duration = Duration::from_secs(5);

impl Intake {
    fn open(settings: &IngestSettings) -> Result<Self, IngestError> {
        let name = ServiceName::new(&settings.service_name).map_err(|source| IngestError::ServiceName {
            name: settings.service_name.clone(),
            source,
        })?;
        let node = node_builder()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(IngestError::Node)?;
        // A daemon killed with SIGKILL leaves its subscriber port behind; free it before asking
        // for a new one (the service admits few subscribers).
        log_cleanup(node.try_cleanup_dead_nodes());
        let service = open_scan_service(&node, &name).map_err(|source| IngestError::Service {
            name: settings.service_name.clone(),
            source,
        })?;
        let subscriber = service
            .subscriber_builder()
            .create()
            .map_err(IngestError::Subscriber)?;
        info!(service = %settings.service_name, "ingest listening");
        Ok(Self {
            node,
            subscriber,
            sequences: SequenceTracker::new(settings.sequence_restart_window),
            poses: PoseGate::new(settings.pose),
            skipped_log: Throttle::new(LOG_INTERVAL),
            restart_log: Throttle::new(LOG_INTERVAL),
        })
    }

    fn run(
        mut self,
        settings: &IngestSettings,
        queue: &LatestQueue<Arrival>,
        metrics: &Metrics,
        shutdown: &Shutdown,
    ) {
        let mut last_cleanup = Instant::now();
        while !shutdown.is_triggered() {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    let received = Instant::now();
                    let now_ns = crate::metrics::unix_now_ns();
                    let header = *sample.user_header();
                    let source = Source {
                        publisher_id: header.publisher_id,
                        port: sample.header().publisher_id().value(),
                    };
                    let slice = sample.payload();
                    // The slice length lives in the publisher's memory: read it once, bound it.
                    let slice_len = slice.len();
                    metrics.received.fetch_add(1, Ordering::Relaxed);
                    let _span = info_span!(
                        "ingest",
                        publisher = header.publisher_id,
                        sequence = header.sequence
                    )
                    .entered();
                    if let Err(reason) = check_header(&header, slice_len, &settings.limits, now_ns) {
                        self.sequences.saw(source, header.sequence);
                        metrics.reject(reason);
                        debug!(reason = reason.as_str(), "scan rejected");
                        continue;
                    }
                    let points: Vec<ScanPoint> = slice[..header.point_count as usize].to_vec();
                    drop(sample);
                    let arrived = Received {
                        header,
                        source,
                        received,
                        now_ns,
                    };
                    self.accept(arrived, &points, settings, queue, metrics);
                    continue;
                }
                Ok(None) => {}
                Err(e) => warn!(error = ?e, "receive failed"),
            }
            if last_cleanup.elapsed() >= settings.cleanup_interval {
                log_cleanup(self.node.try_cleanup_dead_nodes());
                last_cleanup = Instant::now();
            }
            std::thread::sleep(settings.poll_interval);
        }
        info!("ingest stopped");
    }

    fn accept(
        &mut self,
        arrived: Received,
        points: &[ScanPoint],
        settings: &IngestSettings,
        queue: &LatestQueue<Arrival>,
        metrics: &Metrics,
    ) {
        let Received {
            header,
            source,
            received,
            now_ns,
        } = arrived;
        let scan = match validate(&header, points, &settings.limits, now_ns) {
            Ok(scan) => scan,
            Err(reason) => return self.refuse(source, header.sequence, reason, metrics),
        };
        let sequence = match self.sequences.check(source, scan.sequence) {
            Ok(check) => check,
            Err(reason) => return self.refuse(source, scan.sequence, reason, metrics),
        };
        let position = scan.pose.translation.vector;
        let pose = self.poses.judge(scan.publisher_id, scan.stamp_ns, position);
        match pose {
            PoseVerdict::Implausible => {
                return self.refuse(source, scan.sequence, RejectReason::ImplausiblePose, metrics)
            }
            PoseVerdict::Relocated => {
                metrics.relocations.fetch_add(1, Ordering::Relaxed);
                info!(
                    publisher = scan.publisher_id,
                    x = position.x,
                    y = position.y,
                    "publisher relocated"
                );
            }
            PoseVerdict::Plausible => {}
        }
        self.sequences.accept(source, scan.sequence);
        let lost = match sequence {
            SequenceCheck::Next { lost } => lost,
            SequenceCheck::Restart => {
                metrics.publisher_restarts.fetch_add(1, Ordering::Relaxed);
                if let Some(n) = self.restart_log.hit(received) {
                    info!(
                        publisher = scan.publisher_id,
                        sequence = scan.sequence,
                        restarts = n,
                        "sequence jumped: publisher restarted"
                    );
                }
                0
            }
        };
        metrics.count_source(scan.publisher_id, lost);
        if lost > 0 {
            debug!(publisher = scan.publisher_id, lost, "scans lost in transport");
        }
        if queue.push(Arrival { scan, received }).is_some() {
            metrics.skipped.fetch_add(1, Ordering::Relaxed);
            if let Some(n) = self.skipped_log.hit(received) {
                warn!(
                    skipped = n,
                    skipped_total = metrics.skipped.load(Ordering::Relaxed),
                    "fitting behind: older scans skipped (newest wins)"
                );
            }
        }
    }

    /// Counts a rejection; the scan's number arrived, so it is not counted as lost later.
    fn refuse(&mut self, source: Source, sequence: u64, reason: RejectReason, metrics: &Metrics) {
        self.sequences.saw(source, sequence);
        metrics.reject(reason);
        debug!(reason = reason.as_str(), "scan rejected");
    }
}

/// A sample's header copied out of shared memory, with where and when it came from.
struct Received {
    header: ScanHeader,
    source: Source,
    received: Instant,
    now_ns: u64,
}

fn log_cleanup(state: iceoryx2::node::CleanupState) {
    if state.cleanups > 0 || state.failed_cleanups > 0 {
        info!(
            cleaned = state.cleanups,
            failed = state.failed_cleanups,
            "dead iceoryx2 nodes"
        );
    }
}
