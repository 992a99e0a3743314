//! The daemon: ingest thread → newest-wins queue → fit thread → window → snapshot → queries;
//! the fit thread hands each map to the aggregate thread, which publishes its own copy. Each
//! thread's loop lives in its own file; this one starts them (through [`DaemonBuilder`]) and
//! stops them, in order, with the one [`Shutdown`] signal.

mod aggregate;
mod checkpoint;
mod correct;
mod fit;
mod learn;

use crate::checkpoint::writer::Writer;
use crate::checkpoint::PageStore;
use crate::config::{Config, ConfigError};
use crate::exporter::Exporter;
use crate::fleet::assemble::{self, SiteSettings};
use crate::fleet::publish::{self, Departures, TileSettings};
use crate::fleet::site_map::SiteLimits;
use crate::ingest::subscriber::IngestSettings;
use crate::ingest::{spawn_ingest, IngestError, IngestHandle, LatestQueue};
use crate::map::aggregate::ledger::Ledger;
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use crate::map::calibration;
use crate::map::{LocalRangeMap, MapSnapshot};
use crate::metrics::Metrics;
use crate::scan::ScanInput;
use crate::server::{QueryServer, ServerError, MAX_REQUEST_BYTES};
use crate::shutdown::Shutdown;
use crate::state::{CorrectionDesk, DaemonState};
use aggregate::{aggregate_loop, FusionBudget};
use arc_swap::ArcSwap;
use correct::Kept;
pub use correct::{correct_aggregate, AggregateCorrection};
use fit::{fit_loop, FitOutputs};
use learn::learn_loop;
use rangegp_proto::fleet::{FleetInfo, FleetRole};
use rangegp_transport::{zenoh_config, TransportConfigError};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;
use thiserror::Error;
use tracing::{info, warn};
use zenoh::Wait;

/// The daemon could not start; whatever it had started is stopped again.
#[derive(Debug, Error)]
pub enum StartError {
    /// The configuration is invalid (the error names the field).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// Zenoh settings are invalid.
    #[error(transparent)]
    Transport(#[from] TransportConfigError),
    /// Zenoh refused a step of the start (endpoint in use, bad config file, closed session).
    #[error("cannot {action}")]
    Zenoh {
        /// What the daemon was doing.
        action: &'static str,
        /// Zenoh's error.
        #[source]
        source: zenoh::Error,
    },
    /// The ingest thread could not start.
    #[error(transparent)]
    Ingest(#[from] IngestError),
    /// The query server could not start.
    #[error(transparent)]
    Server(#[from] ServerError),
    /// A thread could not be spawned (the process is out of threads or memory).
    #[error("cannot spawn the {thread} thread")]
    Spawn {
        /// Which thread.
        thread: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
}

/// Fitted scans on their way to the aggregate thread (newest wins).
type AggregateFeed = LatestQueue<(ScanInput, Arc<LocalRangeMap>)>;

/// Starts a [`Daemon`]: the configuration, and optionally a Zenoh configuration of the caller's
/// own (an embedding process, a test) in place of the one built from `[zenoh]`.
#[derive(Debug)]
#[must_use = "a builder does nothing until `start`"]
pub struct DaemonBuilder {
    config: Config,
    zenoh: Option<zenoh::Config>,
}

impl DaemonBuilder {
    /// Uses `zenoh` as the session's configuration instead of the one `[zenoh]` describes.
    pub fn zenoh_config(mut self, zenoh: zenoh::Config) -> Self {
        self.zenoh = Some(zenoh);
        self
    }

    /// Validates the configuration, opens Zenoh, starts the fit, aggregate, learn and checkpoint
    /// threads, the query server, the metrics exporter and the ingest thread, in that order. On
    /// any error, what was already started is stopped before the error is returned.
    pub fn start(self) -> Result<Daemon, StartError> {
        let config = self.config;
        config.validate()?;
        let zconf = match self.zenoh {
            Some(zconf) => zconf,
            None => session_config(&config)?,
        };
        let session = zenoh::open(zconf).wait().map_err(|source| StartError::Zenoh {
            action: "open the zenoh session",
            source,
        })?;
        let metrics = Arc::new(Metrics::default());
        let mut params = config.map_params();
        let world_params = WorldParams {
            change_detection: config.aggregate.change_detection,
            ..WorldParams::default()
        };
        let (store, restored) = if config.aggregate.enabled && config.fleet.role == FleetRole::Robot {
            crate::checkpoint::resume(
                config.checkpoint_dir().as_deref(),
                config.checkpoint.keep,
                &config.map_id,
                &world_params,
                &metrics,
            )
        } else {
            (None, None)
        };
        if let (Some(r), true) = (&restored, config.gp.online.enabled) {
            let c = &r.checkpoint;
            params.kernel = params.kernel.with(c.kernel_variance, c.length_scale);
        }
        // The σ scales learnt before the restart, where this daemon learns them too: it answers
        // with them at once, and its calibrator keeps each part until it has relearnt it.
        let prior = restored
            .as_ref()
            .filter(|_| config.gp.prequential_calibration)
            .and_then(|r| r.checkpoint.scales)
            .map(|s| calibration::under_settings(s, config.gp.unseen_relief, config.gp.view_disagreement));
        let world = restored.map(|r| Arc::new(r.world));
        let kernel = Arc::new(ArcSwap::from_pointee(params.kernel));
        let state = Arc::new(DaemonState {
            snapshot: ArcSwap::from_pointee(
                MapSnapshot::new(Vec::new(), world.clone())
                    .with_scales(prior.unwrap_or_default())
                    .with_max_sigma(config.query.max_sigma_m),
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
            corrections: CorrectionDesk {
                log: Mutex::default(),
                waiting: config.aggregate.enabled.then(Mutex::default),
            },
            robot: config.layers.robot(),
            fleet: Mutex::new(FleetInfo {
                role: config.fleet.role,
                site: config.fleet_site().map(|k| k.map_id().to_owned()),
                ..FleetInfo::default()
            }),
            site_sources: arc_swap::ArcSwapOption::empty(),
        });
        // From here on an early return drops `daemon`, which stops what has started.
        let mut daemon = Daemon {
            shutdown: Shutdown::new(),
            state,
            server: None,
            ingest: None,
            fitter: None,
            learner: None,
            aggregator: None,
            checkpointer: None,
            exporter: None,
            fleet: None,
            session: Some(session.clone()),
        };
        if config.fleet.role == FleetRole::Site {
            daemon.start_site(&session, &config, world_params)?;
            return Ok(daemon);
        }
        let shutdown = daemon.shutdown.clone();
        let state = Arc::clone(&daemon.state);

        let learner_feed = if config.gp.online.enabled {
            let samples = Arc::new(LatestQueue::new(1));
            let (rx, kernel, metrics, shutdown) = (
                Arc::clone(&samples),
                Arc::clone(&kernel),
                Arc::clone(&metrics),
                shutdown.clone(),
            );
            let online = config.online_hyperparameters();
            daemon.learner = Some(spawn("rangegp-hyper", move || {
                learn_loop(online, &rx, &kernel, &metrics, &shutdown);
            })?);
            Some((samples, config.gp.online.subset_rays))
        } else {
            None
        };

        let mut tiles = None;
        let mut page_reader = None;
        let aggregate_feed = if config.aggregate.enabled {
            let feed = Arc::new(LatestQueue::new(config.aggregate.queue_len));
            let (rx, state, shutdown) = (Arc::clone(&feed), Arc::clone(&state), shutdown.clone());
            let radius_m = config.aggregate.radius_m;
            let budget = FusionBudget::new(config.aggregate.cpu_share, world_params.max_reach_m);
            // The site map on disk beside the checkpoints (none without them: far tiles are
            // then forgotten).
            let pages = store.as_ref().and_then(|s| {
                let identity = crate::checkpoint::identity(&config.map_id, &world_params);
                PageStore::open(s.dir(), identity)
                    .inspect_err(|e| {
                        metrics.aggregate_page_failures.fetch_add(1, Ordering::Relaxed);
                        let e: &dyn std::error::Error = e;
                        warn!(
                            error = e,
                            "no site map: tiles beyond the radius will be forgotten"
                        );
                    })
                    .ok()
            });
            let start = world
                .clone()
                .unwrap_or_else(|| Arc::new(WorldAggregate::new(world_params)));
            let changes = session
                .declare_publisher(state.keys.changes())
                .wait()
                .map_err(|source| StartError::Zenoh {
                    action: "declare the change publisher",
                    source,
                })?;
            let departures = config.fleet_site().map(|site| {
                let departures = Arc::new(Departures::default());
                tiles = Some((site, Arc::clone(&departures)));
                departures
            });
            page_reader = pages.as_ref().map(PageStore::reader);
            let kept = Kept {
                pages,
                ledger: Ledger::new(config.aggregate.ledger_mib << 20),
                changes,
                departures,
            };
            daemon.aggregator = Some(spawn("rangegp-aggregate", move || {
                aggregate_loop(&rx, &state, start, radius_m, budget, kept, &shutdown);
            })?);
            Some(feed)
        } else {
            None
        };

        if let Some(store) = store {
            let writer = Arc::new(Mutex::new(Writer::new(
                store,
                &config.map_id,
                &world_params,
                world,
            )));
            let interval = Duration::from_millis(config.checkpoint.interval_ms);
            let thread = checkpoint::spawn(
                Arc::clone(&writer),
                Arc::clone(&state),
                interval,
                shutdown.clone(),
            )
            .map_err(|source| StartError::Spawn {
                thread: "rangegp-checkpoint",
                source,
            })?;
            daemon.checkpointer = Some((writer, thread));
        }

        let updates = session
            .declare_publisher(state.keys.map_updates())
            .wait()
            .map_err(|source| StartError::Zenoh {
                action: "declare the map-update publisher",
                source,
            })?;
        let queue = Arc::new(LatestQueue::new(config.ingest.queue_len));
        {
            let (queue, state, shutdown) = (Arc::clone(&queue), Arc::clone(&state), shutdown.clone());
            let capacity = config.window.capacity;
            let outputs = FitOutputs {
                learner: learner_feed,
                aggregate: aggregate_feed,
                calibrate: config.gp.prequential_calibration,
                relief: config.gp.unseen_relief,
                view_disagreement: config.gp.view_disagreement,
                prior,
                updates,
            };
            daemon.fitter = Some(spawn("rangegp-fit", move || {
                fit_loop(&queue, &state, params, capacity, outputs, &shutdown);
            })?);
        }

        if let Some((site, departures)) = tiles {
            let settings = TileSettings {
                site,
                period: Duration::from_millis(config.fleet.tile_period_ms),
                max_bytes_per_s: config.fleet.max_kib_per_s << 10,
                pages: page_reader,
                max_held_departed: usize::try_from(config.fleet.max_held_departed_tiles)
                    .unwrap_or(usize::MAX),
            };
            let (session, state, shutdown) = (session.clone(), Arc::clone(&state), shutdown.clone());
            daemon.fleet = Some(Fleet {
                thread: spawn("rangegp-tiles", move || {
                    publish::publish_loop(&session, &state, &settings, &departures, &shutdown);
                })?,
                subscriber: None,
            });
        }
        daemon.server = Some(QueryServer::start(
            &session,
            Arc::clone(&state),
            config.query.threads,
            64,
        )?);
        daemon.exporter = exporter(&config, Arc::clone(&state));
        daemon.ingest = Some(spawn_ingest(
            IngestSettings {
                service_name: config.scan_service_name(),
                limits: config.validation_limits(),
                poll_interval: Duration::from_millis(config.ingest.poll_interval_ms),
                cleanup_interval: Duration::from_secs(config.ingest.cleanup_interval_s),
                sequence_restart_window: config.ingest.sequence_restart_window,
                pose: config.pose_limits(),
                max_retry_interval: Duration::from_millis(config.ingest.max_retry_interval_ms),
            },
            queue,
            metrics,
            shutdown,
        )?);
        info!(
            map = config.map_id,
            scans = config.scan_service_name(),
            "rangegpd started"
        );
        Ok(daemon)
    }
}

/// The Zenoh session configuration `[zenoh]` describes.
fn session_config(config: &Config) -> Result<zenoh::Config, StartError> {
    if let Some(path) = &config.zenoh.config_file {
        return zenoh::Config::from_file(path).map_err(|source| StartError::Zenoh {
            action: "read the zenoh config file",
            source,
        });
    }
    let mut zconf = zenoh_config(
        &config.zenoh.mode,
        &config.zenoh.listen,
        &config.zenoh.connect,
        config.zenoh.multicast_scouting,
    )?;
    // Zenoh reassembles a message up to this size only: a larger request is dropped fragment by
    // fragment before it costs memory (docs/OPERATIONS.md).
    let key = "transport/link/rx/max_message_size";
    zconf
        .insert_json5(key, &MAX_REQUEST_BYTES.to_string())
        .map_err(|source| TransportConfigError {
            key: key.into(),
            source,
        })?;
    Ok(zconf)
}

/// The Prometheus exporter `[metrics]` asks for; a failure to start it is logged, not fatal.
fn exporter(config: &Config, state: Arc<DaemonState>) -> Option<Exporter> {
    match config.metrics.listen.as_str() {
        "" => None,
        listen => Exporter::start(listen, state)
            .inspect_err(|e| {
                let e: &dyn std::error::Error = e;
                warn!(error = e, "running without prometheus metrics");
            })
            .ok(),
    }
}

/// Spawns a named daemon thread.
fn spawn(thread: &'static str, body: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>, StartError> {
    std::thread::Builder::new()
        .name(thread.into())
        .spawn(body)
        .map_err(|source| StartError::Spawn { thread, source })
}

/// A running daemon. [`Daemon::shutdown`] (or drop) stops every thread and undeclares the keys.
pub struct Daemon {
    shutdown: Shutdown,
    state: Arc<DaemonState>,
    server: Option<QueryServer>,
    ingest: Option<IngestHandle>,
    fitter: Option<JoinHandle<()>>,
    learner: Option<JoinHandle<()>>,
    aggregator: Option<JoinHandle<()>>,
    checkpointer: Option<(Arc<Mutex<Writer>>, JoinHandle<()>)>,
    exporter: Option<Exporter>,
    fleet: Option<Fleet>,
    /// `None` once stopped.
    session: Option<zenoh::Session>,
}

/// The fleet's thread: a robot's tile publisher, or a site's assembler with its subscription.
struct Fleet {
    thread: JoinHandle<()>,
    subscriber: Option<zenoh::pubsub::Subscriber<()>>,
}

impl std::fmt::Debug for Daemon {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Daemon")
            .field("map", &self.state.keys.map_id())
            .finish()
    }
}

impl Daemon {
    /// Starts the site role on a daemon whose state is made: the subscription to every robot's
    /// tiles, the storage's tiles (waiting up to `fleet.storage_wait_ms` for a storage), the
    /// assembler of live tiles, the query server and the exporter. No
    /// scan intake, fitting or checkpoints: the storage is the site's memory.
    fn start_site(
        &mut self,
        session: &zenoh::Session,
        config: &Config,
        params: WorldParams,
    ) -> Result<(), StartError> {
        let site = config.keys();
        let state = Arc::clone(&self.state);
        let (tx, rx) = std::sync::mpsc::sync_channel(assemble::TILE_QUEUE);
        let max_bytes = assemble::max_tile_bytes(&params);
        let subscriber =
            assemble::subscribe(session, &site, tx, max_bytes, Arc::clone(&state)).map_err(|source| {
                StartError::Zenoh {
                    action: "subscribe to the site's tiles",
                    source,
                }
            })?;
        let settings = SiteSettings {
            site,
            storage_wait: Duration::from_millis(config.fleet.storage_wait_ms),
            params,
            limits: SiteLimits {
                robots: usize::try_from(config.fleet.max_site_robots).unwrap_or(usize::MAX),
                tiles: usize::try_from(config.fleet.max_site_tiles).unwrap_or(usize::MAX),
            },
        };
        let shutdown = self.shutdown.clone();
        // Everything stored first: once its queryables are declared, the site answers all of it.
        let site_map = assemble::recover(session, &state, &settings, &shutdown);
        let thread = {
            let (session, state) = (session.clone(), Arc::clone(&state));
            spawn("rangegp-site", move || {
                assemble::assemble_loop(&session, &state, site_map, &settings, &rx, &shutdown);
            })?
        };
        self.fleet = Some(Fleet {
            thread,
            subscriber: Some(subscriber),
        });
        self.server = Some(QueryServer::start(
            session,
            Arc::clone(&state),
            config.query.threads,
            64,
        )?);
        self.exporter = exporter(config, state);
        info!(site = config.map_id, "rangegpd started as a site daemon");
        Ok(())
    }

    /// A builder for a daemon with `config`.
    pub fn builder(config: Config) -> DaemonBuilder {
        DaemonBuilder { config, zenoh: None }
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

    /// Stops in dependency order: no new queries, no new scans, then the threads that consume
    /// them, then a last checkpoint of what the aggregate thread published, then Zenoh.
    fn stop(&mut self) {
        let Some(session) = self.session.take() else {
            return;
        };
        self.shutdown.trigger();
        self.server.take();
        if let Some(i) = self.ingest.take() {
            i.join();
        }
        for (name, thread) in [
            ("fit", self.fitter.take()),
            ("hyperparameter", self.learner.take()),
            ("aggregate", self.aggregator.take()),
            (
                "fleet",
                self.fleet.take().map(|f| {
                    drop(f.subscriber);
                    f.thread
                }),
            ),
        ] {
            if thread.is_some_and(|t| t.join().is_err()) {
                warn!(thread = name, "a daemon thread panicked");
            }
        }
        if let Some((writer, thread)) = self.checkpointer.take() {
            if thread.join().is_err() {
                warn!("the checkpoint thread panicked");
            }
            writer
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .write_if_changed(&self.state);
        }
        self.exporter.take();
        if let Err(e) = session.close().wait() {
            warn!(error = %e, "closing the zenoh session failed");
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.stop();
    }
}
/// Publishes an event (bincode) on `publisher`; a failure is logged, never propagated (events
/// are advice: the maps answer queries either way).
fn publish_event<T: serde::Serialize>(publisher: &zenoh::pubsub::Publisher<'static>, event: &T, what: &str) {
    match rangegp_proto::codec::encode(rangegp_proto::codec::Encoding::Bincode, event) {
        Ok(bytes) => {
            let encoding = rangegp_transport::zenoh_encoding(rangegp_proto::codec::Encoding::Bincode);
            if let Err(e) = publisher.put(bytes).encoding(encoding).wait() {
                tracing::debug!(error = %e, "{what} not published");
            }
        }
        Err(e) => warn!(error = %e, "cannot encode a {what}"),
    }
}
