//! The daemon: ingest thread → newest-wins queue → fitter thread → window → snapshot → queries;
//! the fitter hands each map to the aggregate thread, which publishes its own copy.

use crate::checkpoint::writer::{self, Writer};
use crate::config::Config;
use crate::gp::hyper::OnlineHyperparameters;
use crate::gp::Kernel;
use crate::ingest::subscriber::IngestSettings;
use crate::ingest::{
    spawn_ingest, Arrival, IngestError, IngestHandle, LatestQueue, RejectReason, ValidationLimits,
};
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use crate::map::aggregate::Aggregate;
use crate::map::calibration::Calibrator;
use crate::map::local::{hyper_sample, HyperSample, MapParams, ScanInput};
use crate::map::{LocalRangeMap, MapSnapshot, Window};
use crate::metrics::prometheus::Exporter;
use crate::metrics::Metrics;
use crate::priority::{lower_current_thread, Background};
use crate::server::{QueryServer, ServerError, ServerState, MAX_REQUEST_BYTES};
use crate::sleep::sleep_until;
use arc_swap::ArcSwap;
use rangegp_client::transport::{zenoh_config, zenoh_encoding, TransportConfigError};
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::msg::MapUpdate;
use rangegp_proto::PROTOCOL_VERSION;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;
use tracing::{debug, info, info_span, warn};
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
    learner: Option<JoinHandle<()>>,
    aggregator: Option<JoinHandle<()>>,
    checkpointer: Option<(Arc<Mutex<Writer>>, JoinHandle<()>)>,
    exporter: Option<Exporter>,
    session: zenoh::Session,
}

/// The online hyperparameter thread and its input.
struct Learner {
    samples: Arc<LatestQueue<HyperSample>>,
    subset: usize,
    thread: JoinHandle<()>,
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
            None => {
                let mut zconf = zenoh_config(
                    &config.zenoh.mode,
                    &config.zenoh.listen,
                    &config.zenoh.connect,
                    config.zenoh.multicast_scouting,
                )?;
                // Zenoh reassembles a message up to this size only: a larger request is dropped
                // fragment by fragment before it costs memory (docs/OPERATIONS.md).
                let key = "transport/link/rx/max_message_size";
                zconf
                    .insert_json5(key, &MAX_REQUEST_BYTES.to_string())
                    .map_err(|e| TransportConfigError {
                        key: key.into(),
                        reason: e.to_string(),
                    })?;
                zconf
            }
        };
        let session = zenoh::open(zconf)
            .wait()
            .map_err(|e| StartError::Zenoh(e.to_string()))?;
        let metrics = Arc::new(Metrics::default());
        let shutdown = Arc::new(AtomicBool::new(false));
        let mut params = config.map_params();
        let world_params = WorldParams::default();
        let (store, restored) = if config.aggregate.enabled {
            crate::checkpoint::resume(&config.checkpoint, &config.map_id, &world_params, &metrics)
        } else {
            (None, None)
        };
        if let (Some(r), true) = (&restored, config.gp.online.enabled) {
            let c = &r.checkpoint;
            params.kernel = params.kernel.with(c.kernel_variance, c.length_scale);
        }
        let world = restored.map(|r| Arc::new(r.world));
        let kernel = Arc::new(ArcSwap::from_pointee(params.kernel));
        let state = Arc::new(ServerState {
            snapshot: ArcSwap::from_pointee(
                MapSnapshot::new(Vec::new(), world.clone()).with_max_sigma(config.query.max_sigma_m),
            ),
            metrics: Arc::clone(&metrics),
            keys: config.keys(),
            max_batch: config.query.max_batch,
            max_ray_range_m: config.query.max_ray_range_m,
            batch_threads: config.query.threads,
            window_capacity: config.window.capacity,
            kernel: Arc::clone(&kernel),
            nugget_m2: params.nugget_m2,
            aggregate_radius_m: config.aggregate.enabled.then_some(config.aggregate.radius_m),
            queue_deadline: Duration::from_millis(config.query.queue_deadline_ms),
        });
        let server = QueryServer::start(&session, Arc::clone(&state), config.query.threads, 64)?;
        let exporter = match config.metrics.listen.as_str() {
            "" => None,
            listen => Exporter::start(listen, Arc::clone(&state))
                .inspect_err(|e| warn!(error = %e, "running without prometheus metrics"))
                .ok(),
        };
        let updates = session
            .declare_publisher(state.keys.map_updates())
            .wait()
            .map_err(|e| StartError::Zenoh(e.to_string()))?;
        let learner = if config.gp.online.enabled {
            let samples = Arc::new(LatestQueue::new(1));
            let (rx, kernel, metrics, shutdown) = (
                Arc::clone(&samples),
                Arc::clone(&kernel),
                Arc::clone(&metrics),
                Arc::clone(&shutdown),
            );
            let online = config.online_hyperparameters();
            let thread = std::thread::Builder::new()
                .name("rangegp-hyper".into())
                .spawn(move || hyper_loop(online, &rx, &kernel, &metrics, &shutdown))?;
            Some(Learner {
                samples,
                subset: config.gp.online.subset_rays,
                thread,
            })
        } else {
            None
        };
        let (aggregate_feed, aggregator) = if config.aggregate.enabled {
            let feed = Arc::new(LatestQueue::new(config.aggregate.queue_len));
            let (rx, state, shutdown) = (Arc::clone(&feed), Arc::clone(&state), Arc::clone(&shutdown));
            let pace = AggregatePace {
                radius_m: config.aggregate.radius_m,
                min_interval: Duration::from_millis(config.aggregate.min_interval_ms),
            };
            let start = world
                .clone()
                .unwrap_or_else(|| Arc::new(WorldAggregate::new(world_params)));
            let thread = std::thread::Builder::new()
                .name("rangegp-aggregate".into())
                .spawn(move || aggregate_loop(&rx, &state, start, pace, &shutdown))?;
            (Some(feed), Some(thread))
        } else {
            (None, None)
        };
        let checkpointer = match store {
            Some(store) => {
                let w = Arc::new(Mutex::new(Writer::new(
                    store,
                    &config.map_id,
                    &world_params,
                    world,
                )));
                let interval = Duration::from_millis(config.checkpoint.interval_ms);
                let thread = writer::spawn(
                    Arc::clone(&w),
                    Arc::clone(&state),
                    interval,
                    Arc::clone(&shutdown),
                )?;
                Some((w, thread))
            }
            None => None,
        };
        let queue = Arc::new(LatestQueue::new(config.ingest.queue_len));
        let feed = learner.as_ref().map(|l| (Arc::clone(&l.samples), l.subset));
        let fitter = {
            let (queue, state, shutdown) = (Arc::clone(&queue), Arc::clone(&state), Arc::clone(&shutdown));
            let capacity = config.window.capacity;
            let outputs = FitOutputs {
                learner: feed,
                aggregate: aggregate_feed,
                calibrate: config.gp.prequential_calibration,
                updates,
            };
            std::thread::Builder::new()
                .name("rangegp-fit".into())
                .spawn(move || fit_loop(&queue, &state, params, capacity, outputs, &shutdown))?
        };
        let ingest = spawn_ingest(
            IngestSettings {
                service_name: config.scan_service_name(),
                limits: ValidationLimits {
                    max_points: config.ingest.max_points,
                    max_future_ns: config.ingest.max_future_ms.saturating_mul(1_000_000),
                },
                poll_interval: Duration::from_millis(config.ingest.poll_interval_ms),
                cleanup_interval: Duration::from_secs(config.ingest.cleanup_interval_s),
                sequence_restart_window: config.ingest.sequence_restart_window,
                pose: config.pose_limits(),
                max_retry_interval: Duration::from_millis(config.ingest.max_retry_interval_ms),
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
                if let Some(l) = learner {
                    let _ = l.thread.join();
                }
                if let Some(a) = aggregator {
                    let _ = a.join();
                }
                if let Some((_, c)) = checkpointer {
                    let _ = c.join();
                }
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
            learner: learner.map(|l| l.thread),
            aggregator,
            checkpointer,
            exporter,
            session,
        })
    }

    /// Shared counters.
    pub fn metrics(&self) -> &Metrics {
        &self.state.metrics
    }

    /// Where Prometheus metrics are served, if they are.
    pub fn metrics_addr(&self) -> Option<std::net::SocketAddr> {
        self.exporter.as_ref().map(Exporter::addr)
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
        if let Some(l) = self.learner.take() {
            let _ = l.join();
        }
        if let Some(a) = self.aggregator.take() {
            let _ = a.join();
        }
        // The aggregate thread has published its last insert: write it before exiting.
        if let Some((w, thread)) = self.checkpointer.take() {
            let _ = thread.join();
            w.lock()
                .unwrap_or_else(PoisonError::into_inner)
                .write_if_changed(&self.state);
        }
        self.exporter.take();
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

/// Fitted scans on their way to the aggregate thread (newest wins).
type AggregateFeed = LatestQueue<(ScanInput, Arc<LocalRangeMap>)>;

/// Where the fitter sends what it made, besides the window.
struct FitOutputs {
    /// Hyperparameter samples for the online learner, with the subset size.
    learner: Option<(Arc<LatestQueue<HyperSample>>, usize)>,
    /// Fitted scans for the aggregate thread.
    aggregate: Option<Arc<AggregateFeed>>,
    /// Learn σ scales from each next scan (`gp.prequential_calibration`).
    calibrate: bool,
    /// Where a [`MapUpdate`] goes when a scan's map is published.
    updates: zenoh::pubsub::Publisher<'static>,
}

/// How the aggregate thread paces itself and bounds its area.
#[derive(Debug, Clone, Copy)]
struct AggregatePace {
    /// Evict tiles beyond this distance from the newest sensor position, metres.
    radius_m: f64,
    /// At most one insert per interval.
    min_interval: Duration,
}

fn fit_loop(
    queue: &LatestQueue<Arrival>,
    state: &ServerState,
    mut params: MapParams,
    capacity: usize,
    outputs: FitOutputs,
    shutdown: &AtomicBool,
) {
    let mut window = Window::new(capacity);
    let mut calibrator = outputs.calibrate.then(Calibrator::default);
    while !shutdown.load(Ordering::Relaxed) {
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
        match LocalRangeMap::fit(&scan, &params) {
            Ok(map) => {
                let fitted = started.elapsed();
                state
                    .metrics
                    .jittered_tiles
                    .fetch_add(map.jittered_tiles() as u64, Ordering::Relaxed);
                // The maps as they stood before this scan: what its returns test.
                let before = state.snapshot.load_full();
                let map = Arc::new(map);
                window.push(Arc::clone(&map));
                let maps = window
                    .snapshot()
                    .with_scales(before.scales)
                    .with_max_sigma(before.max_sigma_m);
                state
                    .snapshot
                    .rcu(|old| maps.with_aggregate(old.aggregate.clone()));
                let latency = received.elapsed();
                let m = &state.metrics;
                m.fit.record(fitted);
                m.scan_to_queryable.record(latency);
                m.accepted.fetch_add(1, Ordering::Relaxed);
                announce(&outputs.updates, &scan, latency, maps.maps().len());
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
                        state.metrics.aggregate_skipped.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            Err(e) => {
                state.metrics.reject(RejectReason::FitFailed);
                warn!(error = %e, "fit failed; scan rejected");
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
    match codec::encode(Encoding::Bincode, &event) {
        Ok(bytes) => {
            if let Err(e) = updates
                .put(bytes)
                .encoding(zenoh_encoding(Encoding::Bincode))
                .wait()
            {
                debug!(error = %e, "map update not published");
            }
        }
        Err(e) => warn!(error = %e, "cannot encode a map update"),
    }
}

/// Folds fitted scans into the world aggregate at most once per `pace.min_interval`, newest
/// first: each insert goes into a copy of the published map (tiles are shared, so a copy costs
/// the cells), tiles beyond `pace.radius_m` of the sensor are evicted (never by a scan far from
/// everything mapped: [`WorldAggregate::insert_and_evict`]), and the copy is published. A failed insert is counted and logged; the published map stays as it was.
fn aggregate_loop(
    feed: &AggregateFeed,
    state: &ServerState,
    mut world: Arc<WorldAggregate>,
    pace: AggregatePace,
    shutdown: &AtomicBool,
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
    while !shutdown.load(Ordering::Relaxed) {
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
        sleep_until(started + pace.min_interval, shutdown);
    }
}

/// Applies online hyperparameter updates from the newest scan sample; the fitter picks the
/// result up for the next scan. Failures keep the previous estimate.
fn hyper_loop(
    mut online: OnlineHyperparameters,
    samples: &LatestQueue<HyperSample>,
    kernel: &ArcSwap<Kernel>,
    metrics: &Metrics,
    shutdown: &AtomicBool,
) {
    lower_current_thread(Background::Idle);
    while !shutdown.load(Ordering::Relaxed) {
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
