//! `rangegp replay FILE.mcap`: a rosbag2 recording (MCAP, ROS 2 CDR) of
//! sensor_msgs/PointCloud2 with nav_msgs/Odometry or /tf, turned into scans and published to the
//! daemon over iceoryx2, at the recorded pace or as fast as the daemon takes them
//! (docs/INTEROP.md "Recorded ROS 2 data").
//!
//! The file is streamed twice with bounded memory (Foxglove's sans-io reader; compressed chunks
//! included): once for the topics, poses and frames, once for the clouds.

pub mod record;

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader};
use nalgebra::Isometry3;
use rangegp_client::{Client, ClientError, PublishError, ScanPublisher};
use rangegp_ros::msg as ros;
use rangegp_ros::poses::{self, Timeline};
use rangegp_ros::scan::{from_cloud, RangeModel};
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Where the base pose comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PoseSource {
    /// nav_msgs/Odometry when the file has it, else /tf.
    Auto,
    /// nav_msgs/Odometry (`--odom-topic`).
    Odom,
    /// tf2_msgs/TFMessage on /tf: the transform whose child is `--base-frame`.
    Tf,
}

/// How fast scans are sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Pace {
    /// At the recorded intervals (divided by `--speed`).
    Recorded,
    /// Each scan after the daemon has taken the previous one (needs the Zenoh connection).
    Accepted,
}

/// Options of `rangegp replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayOptions {
    /// The MCAP file (rosbag2's default storage).
    pub file: PathBuf,
    /// List the topics (name, type, encoding, messages, time span) and exit.
    #[arg(long)]
    pub list: bool,
    /// PointCloud2 topic (default: the file's only one).
    #[arg(long)]
    pub cloud_topic: Option<String>,
    /// Odometry topic (default: the file's only one).
    #[arg(long)]
    pub odom_topic: Option<String>,
    /// Where the base pose comes from.
    #[arg(long, value_enum, default_value_t = PoseSource::Auto)]
    pub pose_source: PoseSource,
    /// TF topic holding the base pose.
    #[arg(long, default_value = "/tf")]
    pub tf_topic: String,
    /// Child frame of the base pose in /tf (REP-105).
    #[arg(long, default_value = "base_link")]
    pub base_frame: String,
    /// The sensor's pose on the base: X Y Z (metres) ROLL PITCH YAW (degrees); default: from
    /// `/tf_static` (the chain from `--base-frame` to the cloud's frame).
    #[arg(long, num_args = 6, allow_negative_numbers = true)]
    pub sensor_to_base: Option<Vec<f64>>,
    /// The sensor's maximum range, metres (returns at or beyond it are no-returns).
    #[arg(long, default_value_t = 100.0)]
    pub max_range_m: f64,
    /// Range noise σ per metre of range (the scan header's noise model).
    #[arg(long, default_value_t = 0.002)]
    pub range_noise_per_m: f64,
    /// iceoryx2 scan service of the daemon.
    #[arg(long, default_value = "rangegp/default/scans")]
    pub service: String,
    /// Publisher id in the scan headers.
    #[arg(long, default_value_t = 0x7265_706c_6179)]
    pub publisher_id: u64,
    /// Largest cloud, in points.
    #[arg(long, default_value_t = 262_144)]
    pub max_points: usize,
    /// Sending pace.
    #[arg(long, value_enum, default_value_t = Pace::Recorded)]
    pub pace: Pace,
    /// Playback speed factor at the recorded pace.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// With `--pace accepted`: longest wait for the daemon to take a scan, seconds.
    #[arg(long, default_value_t = 10.0)]
    pub accept_timeout_s: f64,
}

/// Why a replay stopped.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The file could not be read.
    #[error("cannot read {path}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid MCAP.
    #[error("not a valid MCAP file")]
    Mcap(#[from] mcap::McapError),
    /// No topic of the type needed, or several and none chosen.
    #[error("{0}")]
    Topic(String),
    /// An option is out of range.
    #[error("invalid option: {0}")]
    Option(String),
    /// No usable pose sample in the file.
    #[error("no {0} pose in the file (see --pose-source, --odom-topic, --tf-topic, --base-frame)")]
    NoPoses(&'static str),
    /// The scan publisher failed.
    #[error("cannot publish scans")]
    Publish(#[from] PublishError),
    /// The daemon could not be asked.
    #[error("cannot reach the daemon")]
    Daemon(#[from] ClientError),
    /// The daemon did not take a scan in time.
    #[error("the daemon did not take scan {sequence} within {timeout_s} s")]
    NotTaken {
        /// The scan's sequence.
        sequence: u64,
        /// The wait.
        timeout_s: f64,
    },
}

/// One topic of a file.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TopicInfo {
    /// Topic name.
    pub topic: String,
    /// Schema (message type) name.
    pub schema: String,
    /// Message encoding.
    pub encoding: String,
    /// Messages.
    pub messages: u64,
    /// First and last log time, ns.
    pub span_ns: (u64, u64),
}

/// What a replay did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReplaySummary {
    /// Clouds on the cloud topic.
    pub clouds: u64,
    /// Scans published.
    pub published: u64,
    /// Clouds not sent, by reason (`no_pose`, `decode`, `layout`, `too_many_points`, `empty`).
    pub skipped: BTreeMap<String, u64>,
    /// Pose samples read.
    pub poses: u64,
    /// Pose messages that did not decode or held an invalid transform.
    pub bad_poses: u64,
    /// Wall time of the replay, seconds.
    pub seconds: f64,
    /// Where the sensor's pose on the base came from: `--sensor-to-base`, `/tf_static`, or
    /// `identity` (the cloud's frame is the base).
    pub mount_from: String,
}

impl ReplaySummary {
    fn skip(&mut self, reason: &str) {
        *self.skipped.entry(reason.to_owned()).or_default() += 1;
    }
}

/// A channel as the reader knows it.
#[derive(Debug, Clone)]
struct ChannelInfo {
    topic: String,
    schema: String,
    encoding: String,
}

/// Streams every message of `path` to `f` (channel, log time, bytes), with bounded memory.
fn for_each_message(
    path: &Path,
    mut f: impl FnMut(&ChannelInfo, u64, &[u8]) -> Result<(), ReplayError>,
) -> Result<(), ReplayError> {
    let io = |source| ReplayError::Io {
        path: path.to_owned(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut reader = LinearReader::new();
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, ChannelInfo> = HashMap::new();
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(need) => {
                let n = file.read(reader.insert(need)).map_err(io)?;
                reader.notify_read(n);
            }
            LinearReadEvent::Record { opcode, data } => match mcap::parse_record(opcode, data)? {
                Record::Schema { header, .. } => {
                    schemas.insert(header.id, header.name);
                }
                Record::Channel(c) => {
                    let schema = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                    channels.insert(
                        c.id,
                        ChannelInfo {
                            topic: c.topic,
                            schema,
                            encoding: c.message_encoding,
                        },
                    );
                }
                Record::Message { header, data } => {
                    if let Some(c) = channels.get(&header.channel_id) {
                        f(c, header.log_time, &data)?;
                    }
                }
                _ => {}
            },
        }
    }
    Ok(())
}

/// What the first pass over a file gathers: its topics and, when asked (`frames`: the TF topic
/// and the base frame), every pose sample of every possible source, the static transforms and
/// each cloud topic's frame, so that one pass serves whichever topics are then chosen.
#[derive(Default)]
struct Survey {
    topics: BTreeMap<String, TopicInfo>,
    /// Pose samples and undecodable or invalid messages per odometry topic.
    odometry: HashMap<String, (Timeline, u64)>,
    /// The base's poses from the TF topic, and invalid messages or transforms there.
    tf: (Timeline, u64),
    statics: Vec<ros::TransformStamped>,
    /// The first cloud's frame per cloud topic.
    cloud_frames: HashMap<String, String>,
}

/// The first pass over `path` (see [`Survey`]).
fn survey(path: &Path, frames: Option<(&str, &str)>) -> Result<Survey, ReplayError> {
    let mut s = Survey::default();
    for_each_message(path, |c, t, data| {
        let e = s.topics.entry(c.topic.clone()).or_insert_with(|| TopicInfo {
            topic: c.topic.clone(),
            schema: c.schema.clone(),
            encoding: c.encoding.clone(),
            messages: 0,
            span_ns: (t, t),
        });
        e.messages += 1;
        e.span_ns = (e.span_ns.0.min(t), e.span_ns.1.max(t));
        let Some((tf_topic, base_frame)) = frames else {
            return Ok(());
        };
        match c.schema.as_str() {
            ros::ODOMETRY => {
                let (timeline, bad) = s.odometry.entry(c.topic.clone()).or_default();
                let ok = ros::decode::<ros::Odometry>(data).is_ok_and(|m| timeline.add_odometry(&m));
                *bad += u64::from(!ok);
            }
            ros::TF_MESSAGE if c.topic == STATIC_TF_TOPIC => {
                if let Ok(m) = ros::decode::<ros::TfMessage>(data) {
                    s.statics.extend(m.transforms);
                }
            }
            ros::TF_MESSAGE if c.topic == tf_topic => match ros::decode::<ros::TfMessage>(data) {
                Ok(m) => s.tf.1 += s.tf.0.add_tf(&m, base_frame).1 as u64,
                Err(_) => s.tf.1 += 1,
            },
            ros::POINT_CLOUD2 if !s.cloud_frames.contains_key(&c.topic) => {
                if let Ok(m) = ros::decode::<ros::PointCloud2>(data) {
                    s.cloud_frames.insert(c.topic.clone(), m.header.frame_id);
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    Ok(s)
}

/// The topics of `path`, sorted by name.
pub fn list(path: &Path) -> Result<Vec<TopicInfo>, ReplayError> {
    Ok(survey(path, None)?.topics.into_values().collect())
}

/// The topic of type `schema` to use: `chosen`, else the file's only one.
fn pick(
    topics: &BTreeMap<String, TopicInfo>,
    schema: &str,
    chosen: Option<&str>,
    flag: &str,
) -> Result<Option<String>, ReplayError> {
    let of_type: Vec<&str> = topics
        .values()
        .filter(|t| t.schema == schema && t.encoding == "cdr")
        .map(|t| t.topic.as_str())
        .collect();
    match (chosen, of_type.as_slice()) {
        (Some(c), _) if of_type.contains(&c) => Ok(Some(c.to_owned())),
        (Some(c), _) => Err(ReplayError::Topic(format!(
            "{c} is not a CDR {schema} topic of this file (those are: {of_type:?})"
        ))),
        (None, [one]) => Ok(Some((*one).to_owned())),
        (None, []) => Ok(None),
        (None, many) => Err(ReplayError::Topic(format!(
            "several {schema} topics ({many:?}): choose one with {flag}"
        ))),
    }
}

/// The sensor's pose on the base from `[x, y, z, roll°, pitch°, yaw°]`.
pub fn mount(v: &[f64]) -> Result<Isometry3<f64>, ReplayError> {
    let Ok(six) = <[f64; 6]>::try_from(v) else {
        return Err(ReplayError::Option("--sensor-to-base takes 6 numbers".into()));
    };
    if !v.iter().all(|c| c.is_finite()) {
        return Err(ReplayError::Option("--sensor-to-base must be finite".into()));
    }
    Ok(poses::mount(six))
}

/// The base's poses from the chosen source, sorted; counts them and the bad messages there.
fn choose_poses(
    opts: &ReplayOptions,
    survey: &mut Survey,
    summary: &mut ReplaySummary,
) -> Result<Timeline, ReplayError> {
    let odom = pick(
        &survey.topics,
        ros::ODOMETRY,
        opts.odom_topic.as_deref(),
        "--odom-topic",
    )?;
    let use_odom = match opts.pose_source {
        PoseSource::Odom => Some(odom.ok_or(ReplayError::NoPoses("nav_msgs/Odometry"))?),
        PoseSource::Tf => None,
        PoseSource::Auto => odom,
    };
    let (timeline, bad) = match &use_odom {
        Some(topic) => survey.odometry.remove(topic).unwrap_or_default(),
        None => std::mem::take(&mut survey.tf),
    };
    if timeline.is_empty() {
        return Err(ReplayError::NoPoses(if use_odom.is_some() {
            "nav_msgs/Odometry"
        } else {
            "/tf"
        }));
    }
    summary.poses = timeline.len() as u64;
    summary.bad_poses = bad;
    Ok(timeline)
}

/// The topic of static transforms (the sensor's mount on the base).
const STATIC_TF_TOPIC: &str = "/tf_static";

/// The sensor's pose on the base and where it came from: `--sensor-to-base`, else the
/// `/tf_static` chain from the base frame to the cloud's frame.
fn sensor_mount(
    opts: &ReplayOptions,
    statics: &[ros::TransformStamped],
    cloud_frame: Option<&str>,
) -> Result<(Isometry3<f64>, &'static str), ReplayError> {
    if let Some(v) = &opts.sensor_to_base {
        return Ok((mount(v)?, "--sensor-to-base"));
    }
    let sensor = cloud_frame.unwrap_or_default();
    if sensor.is_empty() || sensor == opts.base_frame {
        return Ok((Isometry3::identity(), "identity"));
    }
    poses::static_mount(statics, &opts.base_frame, sensor)
        .map(|m| (m, STATIC_TF_TOPIC))
        .ok_or_else(|| {
            ReplayError::Option(format!(
                "no {STATIC_TF_TOPIC} chain from {} to the clouds' frame {sensor:?}: give --sensor-to-base",
                opts.base_frame
            ))
        })
}

/// Scans the daemon has taken so far: accepted, rejected or skipped.
fn taken(client: &Client) -> Result<u64, ReplayError> {
    let s = client.status()?;
    Ok(s.scans_accepted + s.scans_rejected + s.scans_skipped)
}

/// Waits (bounded) until the daemon has taken more than `before` scans; returns how many.
fn wait_taken(client: &Client, before: u64, sequence: u64, timeout: Duration) -> Result<u64, ReplayError> {
    let deadline = Instant::now() + timeout;
    loop {
        let now = taken(client)?;
        if now > before {
            return Ok(now);
        }
        if Instant::now() > deadline {
            return Err(ReplayError::NotTaken {
                sequence,
                timeout_s: timeout.as_secs_f64(),
            });
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Replays `opts.file` into the daemon; `client` (required with [`Pace::Accepted`]) asks it
/// whether each scan was taken; `progress` gets a line now and then.
pub fn run(
    opts: &ReplayOptions,
    client: Option<&Client>,
    mut progress: impl FnMut(&str),
) -> Result<ReplaySummary, ReplayError> {
    if !(opts.max_range_m.is_finite() && opts.max_range_m > 0.0) {
        return Err(ReplayError::Option("--max-range-m must be positive".into()));
    }
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(ReplayError::Option("--speed must be positive".into()));
    }
    let client = match (opts.pace, client) {
        (Pace::Accepted, None) => {
            return Err(ReplayError::Option(
                "--pace accepted needs the daemon's connection".into(),
            ))
        }
        (Pace::Accepted, Some(c)) => Some(c),
        (Pace::Recorded, _) => None,
    };
    let started = Instant::now();
    let mut survey = survey(&opts.file, Some((&opts.tf_topic, &opts.base_frame)))?;
    let cloud_topic = pick(
        &survey.topics,
        ros::POINT_CLOUD2,
        opts.cloud_topic.as_deref(),
        "--cloud-topic",
    )?
    .ok_or_else(|| ReplayError::Topic("no CDR sensor_msgs/msg/PointCloud2 topic in the file".into()))?;
    let mut summary = ReplaySummary::default();
    let timeline = choose_poses(opts, &mut survey, &mut summary)?;
    let cloud_frame = survey.cloud_frames.get(&cloud_topic).map(String::as_str);
    let (sensor_to_base, from) = sensor_mount(opts, &survey.statics, cloud_frame)?;
    summary.mount_from = from.to_owned();
    progress(&format!(
        "{cloud_topic}: {} clouds; {} pose samples",
        survey.topics.get(&cloud_topic).map_or(0, |t| t.messages),
        summary.poses
    ));
    let model = RangeModel {
        max_range_m: opts.max_range_m,
        range_noise_per_m: opts.range_noise_per_m,
    };
    let mut publisher = ScanPublisher::new(&opts.service, opts.publisher_id, opts.max_points)?;
    let timeout = Duration::from_secs_f64(opts.accept_timeout_s.max(0.0));
    let mut first: Option<(u64, Instant)> = None;
    let mut taken_before = client.map(taken).transpose()?;
    for_each_message(&opts.file, |c, log_time, data| {
        if c.topic != cloud_topic {
            return Ok(());
        }
        summary.clouds += 1;
        let msg = match ros::decode::<ros::PointCloud2>(data) {
            Ok(m) => m,
            Err(_) => {
                summary.skip("decode");
                return Ok(());
            }
        };
        let stamp = match msg.header.stamp.as_ns() {
            0 => log_time,
            s => s,
        };
        let (header, points) =
            match from_cloud(&msg, stamp, &timeline, &sensor_to_base, model, opts.max_points) {
                Ok(scan) => scan,
                Err(skip) => {
                    summary.skip(skip.reason());
                    return Ok(());
                }
            };
        if opts.pace == Pace::Recorded {
            let (t0, w0) = *first.get_or_insert((log_time, Instant::now()));
            let due = Duration::from_secs_f64(log_time.saturating_sub(t0) as f64 * 1e-9 / opts.speed);
            std::thread::sleep(due.saturating_sub(w0.elapsed()));
        }
        let sequence = publisher.publish(header, &points)?;
        summary.published += 1;
        if let (Some(cl), Some(before)) = (client, taken_before) {
            // The count this wait ends on is the next scan's `before`: one status a scan.
            taken_before = Some(wait_taken(cl, before, sequence, timeout)?);
        }
        if summary.published % 50 == 0 {
            progress(&format!("{} scans sent", summary.published));
        }
        Ok(())
    })?;
    summary.seconds = started.elapsed().as_secs_f64();
    Ok(summary)
}
