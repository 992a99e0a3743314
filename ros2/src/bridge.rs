//! The running bridge: a DDS thread (ros2-client over RustDDS) takes PointCloud2 and Odometry,
//! a scan thread turns clouds into scans and publishes them to the daemon over iceoryx2, and a
//! grid thread asks the daemon for the grid around the robot over Zenoh and publishes it as
//! GridMap and OccupancyGrid.
//!
//! ```text
//!  DDS ──PointCloud2──► dds thread ──(bounded 2, newest kept)──► scan thread ──iceoryx2──► daemon
//!  DDS ──Odometry────►      │ timeline (10 s, Mutex) ◄──── pose at the cloud's stamp
//!                           └──── newest pose ────► grid thread ──Zenoh grid query──► daemon
//!  DDS ◄──GridMap, OccupancyGrid── grid thread (every 1 / grid.rate_hz)
//! ```

use crate::config::{topic_name, BridgeConfig, ConfigError, Reliability};
use futures::StreamExt;
use rangegp_client::{Client, ClientError, PublishError, ScanPublisher};
use rangegp_proto::msg::{ErrorCode, GridReply, GridRequest};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_ros::grid::{grid_map, occupancy_grid, GridMap, OccupancyGrid};
use rangegp_ros::msg::{Header, Odometry, PointCloud2, Time};
use rangegp_ros::poses::Timeline;
use rangegp_ros::scan::{from_cloud, RangeModel, Skip};
use ros2_client::dds::rustdds::DomainParticipantBuilder;
use ros2_client::dds::{Context, Node, Publisher, Subscription};
use ros2_client::qos::{Durability, History, Reliability as QosReliability, WhenFull};
use ros2_client::{MessageTypeName, NodeOptions, QosProfile};
use serde::Serialize;
use std::collections::{BTreeMap, VecDeque};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

/// Odometry kept for pose lookups, nanoseconds.
const POSE_HISTORY_NS: u64 = 10_000_000_000;

/// Longest wait for the scan thread to open its iceoryx2 publisher.
const START_WAIT: Duration = Duration::from_secs(10);

/// How often a cloud waiting for its pose is tried again.
const RETRY: Duration = Duration::from_millis(10);

/// Clouds that may wait for their pose at once.
const MAX_WAITING: usize = 2;

/// Why the bridge did not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A DDS entity (participant, topic, reader, writer) could not be made.
    #[error("cannot create the DDS {what}")]
    Dds {
        /// Which entity.
        what: &'static str,
        /// The cause.
        #[source]
        source: ros2_client::CreateError,
    },
    /// The ROS 2 node could not be made.
    #[error("cannot create the ROS 2 node")]
    Node(#[from] ros2_client::dds::NodeCreateError),
    /// The daemon's Zenoh session could not be opened.
    #[error("cannot open the Zenoh session to the daemon")]
    Daemon(#[from] ClientError),
    /// The iceoryx2 scan publisher could not be opened.
    #[error("cannot open the scan publisher")]
    Publisher(#[from] PublishError),
    /// A thread could not be started, or stopped before saying it was ready.
    #[error("cannot start the {0} thread")]
    Thread(&'static str),
}

/// What the bridge has done since it started.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct BridgeStats {
    /// PointCloud2 messages received.
    pub clouds: u64,
    /// Odometry messages received (valid poses).
    pub odometry: u64,
    /// Odometry messages refused (not finite, quaternion not unit).
    pub bad_odometry: u64,
    /// Scans published to the daemon.
    pub scans_published: u64,
    /// Clouds not sent, by reason (`no_pose`, `empty`, `too_many_points`, `layout`, `decode`,
    /// `busy`: two clouds were already waiting, `publish`: iceoryx2 refused it).
    pub skipped: BTreeMap<String, u64>,
    /// Grids published (a GridMap, and an OccupancyGrid when `cost` is a layer).
    pub grids_published: u64,
    /// Grid ticks without a grid, by reason (`no_pose`: no odometry yet, `no_map`: nothing
    /// fitted yet, `timeout`: the daemon did not answer, `query`: it refused, `publish`).
    pub grid_failures: BTreeMap<String, u64>,
}

/// State the threads share.
#[derive(Default)]
struct Shared {
    timeline: Timeline,
    /// The odometry's frame (the grids' frame when `ros.map_frame` is empty).
    odom_frame: String,
    stats: BridgeStats,
}

type SharedState = Arc<Mutex<Shared>>;

/// Locks the shared state (a thread that panicked holding it left plain data: used as is).
fn lock(s: &SharedState) -> std::sync::MutexGuard<'_, Shared> {
    s.lock().unwrap_or_else(PoisonError::into_inner)
}

fn count(map: &mut BTreeMap<String, u64>, reason: &str) {
    *map.entry(reason.to_owned()).or_default() += 1;
}

/// A running bridge; dropping it (or [`Bridge::stop`]) stops its threads.
pub struct Bridge {
    shared: SharedState,
    stop_dds: Option<futures::channel::oneshot::Sender<()>>,
    stop_grid: Option<mpsc::Sender<()>>,
    threads: Vec<JoinHandle<()>>,
}

/// The DDS entities the DDS thread owns.
struct Readers {
    node: Node,
    clouds: Subscription<PointCloud2>,
    odometry: Subscription<Odometry>,
}

/// The DDS entities the grid thread owns.
struct Writers {
    grid_maps: Publisher<GridMap>,
    costmaps: Publisher<OccupancyGrid>,
}

/// Makes the participant, node, readers and writers.
fn dds(config: &BridgeConfig) -> Result<(Readers, Writers), StartError> {
    let ros = &config.ros;
    let dds_err = |what| move |source| StartError::Dds { what, source };
    let mut participant = DomainParticipantBuilder::new(ros.domain_id);
    if !ros.only_networks.is_empty() {
        participant = participant.with_only_networks(ros.only_networks.iter().copied());
    }
    let participant = participant
        .build()
        .map_err(|e| dds_err("participant")(e.into()))?;
    let context = Context::from_domain_participant(participant).map_err(dds_err("context"))?;
    let mut node = context.new_node(config.node_name()?, NodeOptions::new())?;
    let sensor_qos = QosProfile::subscription_default()
        .reliability(match ros.cloud_reliability {
            Reliability::BestEffort => QosReliability::BestEffort,
            Reliability::Reliable => QosReliability::Reliable {
                when_full: WhenFull::DEFAULT,
            },
        })
        .history(History::KeepLast { depth: 2 });
    let odom_qos = QosProfile::subscription_default().history(History::KeepLast { depth: 50 });
    // Latched like a map server's: a planner that joins late gets the newest grid at once.
    let map_qos = QosProfile::publisher_default()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 });
    let topic = |what, (field, name): (&'static str, &str), (package, kind), qos| {
        node.create_topic(
            &topic_name(field, name)?,
            MessageTypeName::new(package, kind),
            qos,
        )
        .map_err(dds_err(what))
    };
    let cloud_topic = topic(
        "cloud topic",
        ("ros.cloud_topic", &ros.cloud_topic),
        ("sensor_msgs", "PointCloud2"),
        &sensor_qos,
    )?;
    let odom_topic = topic(
        "odometry topic",
        ("ros.odom_topic", &ros.odom_topic),
        ("nav_msgs", "Odometry"),
        &odom_qos,
    )?;
    let grid_topic = topic(
        "grid map topic",
        ("ros.grid_map_topic", &ros.grid_map_topic),
        ("grid_map_msgs", "GridMap"),
        &map_qos,
    )?;
    let cost_topic = topic(
        "costmap topic",
        ("ros.costmap_topic", &ros.costmap_topic),
        ("nav_msgs", "OccupancyGrid"),
        &map_qos,
    )?;
    let writers = Writers {
        grid_maps: node
            .create_publisher(&grid_topic, Some(map_qos.clone()))
            .map_err(dds_err("grid map writer"))?,
        costmaps: node
            .create_publisher(&cost_topic, Some(map_qos))
            .map_err(dds_err("costmap writer"))?,
    };
    let readers = Readers {
        clouds: node
            .create_subscription(&cloud_topic, Some(sensor_qos))
            .map_err(dds_err("cloud reader"))?,
        odometry: node
            .create_subscription(&odom_topic, Some(odom_qos))
            .map_err(dds_err("odometry reader"))?,
        node,
    };
    Ok((readers, writers))
}

/// Now, nanoseconds since the epoch.
fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The DDS thread's work until `stop` fires: the node's spinner, clouds handed to the scan
/// thread, odometry into the timeline.
async fn run_dds(
    mut dds: Readers,
    shared: SharedState,
    to_scans: SyncSender<(PointCloud2, u64)>,
    stop: futures::channel::oneshot::Receiver<()>,
) {
    let spinner = match dds.node.spinner() {
        Ok(s) => s.spin(),
        Err(e) => {
            tracing::error!(error = %e, "the ROS 2 node's spinner did not start");
            return;
        }
    };
    let clouds = async {
        let mut stream = std::pin::pin!(dds.clouds.async_stream());
        while let Some(item) = stream.next().await {
            let mut s = lock(&shared);
            match item {
                Ok((cloud, _)) => {
                    s.stats.clouds += 1;
                    let stamp = match cloud.header.stamp.as_ns() {
                        0 => now_ns(),
                        t => t,
                    };
                    match to_scans.try_send((cloud, stamp)) {
                        Ok(()) => {}
                        Err(TrySendError::Full(_)) => count(&mut s.stats.skipped, "busy"),
                        Err(TrySendError::Disconnected(_)) => return,
                    }
                }
                Err(e) => {
                    tracing::debug!(error = %e, "a PointCloud2 did not decode");
                    count(&mut s.stats.skipped, "decode");
                }
            }
        }
    };
    let odometry = async {
        let mut stream = std::pin::pin!(dds.odometry.async_stream());
        while let Some(item) = stream.next().await {
            let mut s = lock(&shared);
            match item {
                Ok((odom, _)) if s.timeline.add_odometry(&odom) => {
                    s.stats.odometry += 1;
                    if s.odom_frame != odom.header.frame_id {
                        s.odom_frame = odom.header.frame_id;
                    }
                    let newest = s.timeline.newest_ns().unwrap_or(0);
                    s.timeline.forget_before(newest.saturating_sub(POSE_HISTORY_NS));
                }
                _ => s.stats.bad_odometry += 1,
            }
        }
    };
    let (spinner, clouds, odometry) = (
        std::pin::pin!(spinner),
        std::pin::pin!(clouds),
        std::pin::pin!(odometry),
    );
    let readers = futures::future::select(clouds, odometry);
    let work = std::pin::pin!(futures::future::select(spinner, readers));
    // Only the stop signal ends this on purpose: a spinner or reader that ended is an error.
    if let futures::future::Either::Left(_) = futures::future::select(work, stop).await {
        tracing::error!("the ROS 2 node's spinner or a reader stopped: no more clouds or odometry");
    }
}

/// A cloud waiting for the odometry that brackets its stamp (odometry often lags the lidar).
struct Waiting {
    cloud: PointCloud2,
    stamp_ns: u64,
    since: Instant,
}

/// The scan thread: each cloud as a scan, published to the daemon. A cloud newer than every
/// pose waits up to `scans.pose_wait_s` for the odometry after it (two clouds at most wait;
/// a third pushes the oldest out as `busy`).
fn run_scans(
    config: &BridgeConfig,
    shared: &SharedState,
    clouds: &Receiver<(PointCloud2, u64)>,
    mut publisher: ScanPublisher,
) {
    let mount = config.sensor_to_base();
    let model = RangeModel {
        max_range_m: config.scans.max_range_m,
        range_noise_per_m: config.scans.range_noise_per_m,
    };
    let pose_wait = Duration::from_secs_f64(config.scans.pose_wait_s);
    let mut waiting: VecDeque<Waiting> = VecDeque::new();
    loop {
        match clouds.recv_timeout(RETRY) {
            Ok((cloud, stamp_ns)) => {
                if waiting.len() == MAX_WAITING {
                    waiting.pop_front();
                    count(&mut lock(shared).stats.skipped, "busy");
                }
                waiting.push_back(Waiting {
                    cloud,
                    stamp_ns,
                    since: Instant::now(),
                });
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return,
        }
        while let Some(w) = waiting.front() {
            let scan = {
                let s = lock(shared);
                let pose_may_come = s.timeline.newest_ns().is_none_or(|t| t < w.stamp_ns);
                match from_cloud(
                    &w.cloud,
                    w.stamp_ns,
                    &s.timeline,
                    &mount,
                    model,
                    config.scans.max_points,
                ) {
                    Err(Skip::NoPose) if pose_may_come && w.since.elapsed() < pose_wait => break,
                    scan => scan,
                }
            };
            waiting.pop_front();
            let published = match scan {
                Ok((header, points)) => publisher.publish(header, &points).map(drop).map_err(|e| {
                    tracing::warn!(error = %rangegp_proto::error_chain(&e), "a scan was not published");
                    "publish"
                }),
                Err(skip) => Err(skip.reason()),
            };
            let mut s = lock(shared);
            match published {
                Ok(()) => s.stats.scans_published += 1,
                Err(reason) => count(&mut s.stats.skipped, reason),
            }
        }
    }
}

/// The grid request for a square of `config.grid` centred on (x, y), its corners on multiples
/// of the resolution so that a cell keeps its place from one grid to the next.
pub fn grid_request(config: &BridgeConfig, x: f64, y: f64) -> GridRequest {
    let g = &config.grid;
    let cells = (g.size_m / g.resolution_m).round().max(1.0);
    let corner = |c: f64| ((c - 0.5 * g.size_m) / g.resolution_m).floor() * g.resolution_m;
    let min_m = [corner(x), corner(y)];
    // Half a cell short of the far edge: `ceil` in the daemon's shape gives exactly `cells`.
    let span = (cells - 0.5) * g.resolution_m;
    GridRequest {
        version: PROTOCOL_VERSION,
        min_m,
        max_m: [min_m[0] + span, min_m[1] + span],
        resolution_m: g.resolution_m,
        layers: g.layers.clone(),
        robot: None,
    }
}

/// One grid tick: the grid around the newest pose, published; the reason when there was none.
fn grid_tick(
    config: &BridgeConfig,
    shared: &SharedState,
    client: &Client,
    writers: &Writers,
) -> Result<(), &'static str> {
    let (pose, frame) = {
        let s = lock(shared);
        let frame = match config.ros.map_frame.as_str() {
            "" => s.odom_frame.clone(),
            f => f.to_owned(),
        };
        (s.timeline.newest().ok_or("no_pose")?, frame)
    };
    // Stamped when asked, as a costmap is: the map as it stood at that instant.
    let stamp = now_ns();
    let t = pose.translation.vector;
    let reply: GridReply = client
        .grid_request(&grid_request(config, t.x, t.y))
        .map_err(|e| match e {
            // Before the first scan is fitted there is nothing to publish yet.
            ClientError::Server {
                code: ErrorCode::NoMap,
                ..
            } => "no_map",
            ClientError::Timeout(_) => "timeout",
            e => {
                tracing::warn!(error = %rangegp_proto::error_chain(&e), "grid query failed");
                "query"
            }
        })?;
    let header = Header {
        stamp: Time::from_ns(stamp),
        frame_id: frame,
    };
    if let Some(costmap) = occupancy_grid(&reply, header.clone()) {
        writers.costmaps.publish(costmap).map_err(|_| "publish")?;
    }
    writers
        .grid_maps
        .publish(grid_map(&reply, header))
        .map_err(|_| "publish")?;
    Ok(())
}

impl Bridge {
    /// Validates `config`, makes the DDS entities, connects to the daemon and starts the threads.
    pub fn start(config: BridgeConfig) -> Result<Self, StartError> {
        config.validate()?;
        let client = Client::builder(&config.map_id)
            .connect(config.connect.iter().cloned())
            .open()?;
        let (readers, writers) = dds(&config)?;
        let shared = SharedState::default();
        let config = Arc::new(config);
        let mut threads = Vec::new();

        let (to_scans, scans_rx) = mpsc::sync_channel(2);
        let (ready_tx, ready_rx) = mpsc::channel();
        let (c, s) = (config.clone(), shared.clone());
        threads.push(spawn("rangegp-ros2-scans", move || {
            // iceoryx2 ports stay on the thread that opened them.
            match ScanPublisher::new(&c.scans.service, c.scans.publisher_id, c.scans.max_points) {
                Ok(publisher) => {
                    let _ = ready_tx.send(Ok(()));
                    run_scans(&c, &s, &scans_rx, publisher);
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                }
            }
        })?);
        match ready_rx.recv_timeout(START_WAIT) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(e.into()),
            Err(_) => return Err(StartError::Thread("scan")),
        }

        let (stop_dds, stop_rx) = futures::channel::oneshot::channel();
        let s = shared.clone();
        threads.push(spawn("rangegp-ros2-dds", move || {
            futures::executor::block_on(run_dds(readers, s, to_scans, stop_rx));
        })?);

        let (stop_grid, grid_stop_rx) = mpsc::channel::<()>();
        let (c, s) = (config.clone(), shared.clone());
        threads.push(spawn("rangegp-ros2-grid", move || {
            let period = Duration::from_secs_f64(1.0 / c.grid.rate_hz);
            while let Err(RecvTimeoutError::Timeout) = grid_stop_rx.recv_timeout(period) {
                let done = grid_tick(&c, &s, &client, &writers);
                let mut st = lock(&s);
                match done {
                    Ok(()) => st.stats.grids_published += 1,
                    Err(reason) => count(&mut st.stats.grid_failures, reason),
                }
            }
        })?);
        Ok(Self {
            shared,
            stop_dds: Some(stop_dds),
            stop_grid: Some(stop_grid),
            threads,
        })
    }

    /// What the bridge has done so far.
    pub fn stats(&self) -> BridgeStats {
        lock(&self.shared).stats.clone()
    }

    /// Stops the threads and waits for them.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        if let Some(tx) = self.stop_dds.take() {
            let _ = tx.send(());
        }
        if let Some(tx) = self.stop_grid.take() {
            let _ = tx.send(());
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Starts a named thread.
fn spawn(name: &'static str, f: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>, StartError> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(|_| StartError::Thread(name))
}
