//! The ingest thread: takes scans from the iceoryx2 service, validates a private copy, and hands
//! accepted scans to the fitter. iceoryx2 has no async API, so this is a plain thread.

use super::queue::LatestQueue;
use super::validate::{check_header, validate, SequenceTracker, Source, ValidationLimits};
use super::Arrival;
use crate::metrics::Metrics;
use iceoryx2::prelude::*;
use rangegp_proto::scan::{open_scan_service, ScanHeader, ScanPoint};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;
use tracing::{debug, info, info_span, warn};

/// The ingest thread could not start.
#[derive(Debug, Error)]
pub enum IngestError {
    /// The service name is not a valid iceoryx2 service name.
    #[error("invalid iceoryx2 service name {name:?}: {reason}")]
    ServiceName {
        /// Name given.
        name: String,
        /// Cause.
        reason: String,
    },
    /// The iceoryx2 node could not be created (shared memory or permissions).
    #[error("cannot create the iceoryx2 node: {0}")]
    Node(String),
    /// The scan service could not be opened or created (incompatible settings or types).
    #[error("cannot open the scan service {name:?}: {reason}")]
    Service {
        /// Service name.
        name: String,
        /// Cause.
        reason: String,
    },
    /// The subscriber could not be created (too many subscribers).
    #[error("cannot create the scan subscriber: {0}")]
    Subscriber(String),
    /// The OS refused to start the thread.
    #[error("cannot spawn the ingest thread: {0}")]
    Spawn(#[from] std::io::Error),
    /// The thread stopped before reporting whether it started.
    #[error("ingest thread exited during start-up")]
    StartupLost,
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

/// Starts the ingest thread and waits until its subscriber exists (so no scan published after
/// this returns is missed).
pub fn spawn_ingest(
    settings: IngestSettings,
    queue: Arc<LatestQueue<Arrival>>,
    metrics: Arc<Metrics>,
    shutdown: Arc<AtomicBool>,
) -> Result<IngestHandle, IngestError> {
    let (ready_tx, ready_rx) = mpsc::sync_channel(1);
    let thread = std::thread::Builder::new()
        .name("rangegp-ingest".into())
        .spawn(move || {
            let setup = Intake::open(&settings);
            let intake = match setup {
                Ok(intake) => {
                    let _ = ready_tx.send(Ok(()));
                    intake
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
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

struct Intake {
    node: Node<ipc::Service>,
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, [ScanPoint], ScanHeader>,
    sequences: SequenceTracker,
}

impl Intake {
    fn open(settings: &IngestSettings) -> Result<Self, IngestError> {
        let name = ServiceName::new(&settings.service_name).map_err(|e| IngestError::ServiceName {
            name: settings.service_name.clone(),
            reason: format!("{e:?}"),
        })?;
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| IngestError::Node(format!("{e:?}")))?;
        // A daemon killed with SIGKILL leaves its subscriber port behind; free it before asking
        // for a new one (the service admits few subscribers).
        log_cleanup(node.try_cleanup_dead_nodes());
        let service = open_scan_service(&node, &name).map_err(|e| IngestError::Service {
            name: settings.service_name.clone(),
            reason: format!("{e:?}"),
        })?;
        let subscriber = service
            .subscriber_builder()
            .create()
            .map_err(|e| IngestError::Subscriber(format!("{e:?}")))?;
        info!(service = %settings.service_name, "ingest listening");
        Ok(Self {
            node,
            subscriber,
            sequences: SequenceTracker::default(),
        })
    }

    fn run(
        mut self,
        settings: &IngestSettings,
        queue: &LatestQueue<Arrival>,
        metrics: &Metrics,
        shutdown: &AtomicBool,
    ) {
        let mut last_cleanup = Instant::now();
        while !shutdown.load(Ordering::Relaxed) {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    let received = Instant::now();
                    let now_ns = unix_now_ns();
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
        let checked = validate(&header, points, &settings.limits, now_ns).and_then(|scan| {
            self.sequences
                .check(source, scan.sequence)
                .map(|gaps| (scan, gaps))
        });
        match checked {
            Ok((scan, gaps)) => {
                self.sequences.accept(source, scan.sequence);
                metrics.count_source(scan.publisher_id, gaps);
                if gaps > 0 {
                    debug!(publisher = scan.publisher_id, missing = gaps, "sequence gap");
                }
                if let Some(old) = queue.push(Arrival { scan, received }) {
                    metrics.skipped.fetch_add(1, Ordering::Relaxed);
                    warn!(
                        publisher = old.scan.publisher_id,
                        sequence = old.scan.sequence,
                        skipped_total = metrics.skipped.load(Ordering::Relaxed),
                        "fitting behind: skipped an older scan"
                    );
                }
            }
            Err(reason) => {
                metrics.reject(reason);
                debug!(reason = reason.as_str(), "scan rejected");
            }
        }
    }
}

/// A sample's header copied out of shared memory, with where and when it came from.
struct Received {
    header: ScanHeader,
    source: Source,
    received: Instant,
    now_ns: u64,
}

/// This machine's clock, nanoseconds since the Unix epoch (0 if it is set before 1970).
fn unix_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
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
