//! The daemon: ingest thread → newest-wins queue → fitter thread → window → snapshot → queries.

use crate::config::Config;
use crate::ingest::subscriber::IngestSettings;
use crate::ingest::{spawn_ingest, IngestError, IngestHandle, LatestQueue, RejectReason, ValidationLimits};
use crate::map::local::{MapParams, ScanInput};
use crate::map::{LocalRangeMap, MapSnapshot, Window};
use crate::metrics::Metrics;
use crate::server::{QueryServer, ServerError, ServerState};
use arc_swap::ArcSwap;
use rangegp_client::transport::{zenoh_config, TransportConfigError};
use rangegp_proto::msg::HyperparametersInfo;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;
use tracing::{info, info_span, warn};
use zenoh::Wait;

/// The daemon could not start.
#[derive(Debug, Error)]
pub enum StartError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    /// Zenoh settings are invalid.
    #[error(transparent)]
    Transport(#[from] TransportConfigError),
    /// The Zenoh session could not be opened (endpoint in use, bad config file).
    #[error("cannot open the zenoh session: {0}")]
    Zenoh(String),
    /// The ingest thread could not start.
    #[error(transparent)]
    Ingest(#[from] IngestError),
    /// The query server could not start.
    #[error(transparent)]
    Server(#[from] ServerError),
    /// The fitter thread could not be spawned.
    #[error("cannot spawn the fitter: {0}")]
    Spawn(#[from] std::io::Error),
}

/// A running daemon. [`Daemon::shutdown`] (or drop) stops every thread and undeclares the keys.
pub struct Daemon {
    shutdown: Arc<AtomicBool>,
    state: Arc<ServerState>,
    server: Option<QueryServer>,
    ingest: Option<IngestHandle>,
    fitter: Option<JoinHandle<()>>,
    session: zenoh::Session,
}

impl std::fmt::Debug for Daemon {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Daemon")
            .field("map", &self.state.keys.map_id())
            .finish()
    }
}

impl Daemon {
    /// Validates `config`, opens Zenoh, starts the fitter, the ingest thread and the queryables.
    pub fn start(config: &Config) -> Result<Self, StartError> {
        config.validate()?;
        let zconf = match &config.zenoh.config_file {
            Some(path) => zenoh::Config::from_file(path).map_err(|e| StartError::Zenoh(e.to_string()))?,
            None => zenoh_config(
                &config.zenoh.mode,
                &config.zenoh.listen,
                &config.zenoh.connect,
                config.zenoh.multicast_scouting,
            )?,
        };
        let session = zenoh::open(zconf)
            .wait()
            .map_err(|e| StartError::Zenoh(e.to_string()))?;
        let metrics = Arc::new(Metrics::default());
        let shutdown = Arc::new(AtomicBool::new(false));
        let params = config.map_params();
        let state = Arc::new(ServerState {
            snapshot: ArcSwap::from_pointee(MapSnapshot::default()),
            metrics: Arc::clone(&metrics),
            keys: config.keys(),
            max_batch: config.query.max_batch,
            max_ray_range_m: config.query.max_ray_range_m,
            batch_threads: config.query.threads,
            window_capacity: config.window.capacity,
            hyperparameters: HyperparametersInfo {
                kernel: format!("{:?}", params.kernel.family),
                variance: params.kernel.variance,
                length_scale: params.kernel.length_scale,
                nugget: params.nugget_m2,
            },
        });
        let queue = Arc::new(LatestQueue::new(config.ingest.queue_len));
        let fitter = {
            let (queue, state, shutdown) = (Arc::clone(&queue), Arc::clone(&state), Arc::clone(&shutdown));
            let capacity = config.window.capacity;
            std::thread::Builder::new()
                .name("rangegp-fit".into())
                .spawn(move || fit_loop(&queue, &state, &params, capacity, &shutdown))?
        };
        let server = QueryServer::start(&session, Arc::clone(&state), config.query.threads, 64)?;
        let ingest = spawn_ingest(
            IngestSettings {
                service_name: config.scan_service_name(),
                limits: ValidationLimits {
                    max_points: config.ingest.max_points,
                },
                poll_interval: Duration::from_millis(config.ingest.poll_interval_ms),
                cleanup_interval: Duration::from_secs(config.ingest.cleanup_interval_s),
            },
            Arc::clone(&queue),
            Arc::clone(&metrics),
            Arc::clone(&shutdown),
        );
        let ingest = match ingest {
            Ok(handle) => handle,
            Err(e) => {
                shutdown.store(true, Ordering::Relaxed);
                let _ = fitter.join();
                return Err(e.into());
            }
        };
        info!(
            map = config.map_id,
            scans = config.scan_service_name(),
            "rangegpd started"
        );
        Ok(Self {
            shutdown,
            state,
            server: Some(server),
            ingest: Some(ingest),
            fitter: Some(fitter),
            session,
        })
    }

    /// Shared counters.
    pub fn metrics(&self) -> &Metrics {
        &self.state.metrics
    }

    /// The maps queries see now.
    pub fn snapshot(&self) -> Arc<MapSnapshot> {
        self.state.snapshot.load_full()
    }

    /// Stops ingest, fitting and serving, and waits for every thread.
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        self.shutdown.store(true, Ordering::Relaxed);
        self.server.take();
        if let Some(i) = self.ingest.take() {
            i.join();
        }
        if let Some(f) = self.fitter.take() {
            let _ = f.join();
        }
        if let Err(e) = self.session.close().wait() {
            warn!(error = %e, "closing the zenoh session failed");
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if self.fitter.is_some() {
            self.stop();
        }
    }
}

fn fit_loop(
    queue: &LatestQueue<ScanInput>,
    state: &ServerState,
    params: &MapParams,
    capacity: usize,
    shutdown: &AtomicBool,
) {
    let mut window = Window::new(capacity);
    while !shutdown.load(Ordering::Relaxed) {
        let Some(scan) = queue.pop_timeout(Duration::from_millis(50)) else {
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
        match LocalRangeMap::fit(&scan, params) {
            Ok(map) => {
                window.push(Arc::new(map));
                state.snapshot.store(Arc::new(window.snapshot()));
                state.metrics.record_fit(started.elapsed());
                state.metrics.accepted.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => {
                state.metrics.reject(RejectReason::FitFailed);
                warn!(error = %e, "fit failed; scan rejected");
            }
        }
    }
}
