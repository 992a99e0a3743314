//! Simulated scans written as a rosbag2 MCAP recording: an organized PointCloud2 per scan (x, y,
//! z float32, ring uint16, t uint32 ns; no-returns NaN) in the sensor frame ("lidar"), the base
//! pose on nav_msgs/Odometry and /tf (odom → base_link), and the mount on /tf_static
//! (base_link → lidar). What `rangegp replay` is tested on.

use crate::scangen::GeneratedScan;
use mcap::records::MessageHeader;
use nalgebra::Isometry3;
use rangegp_ros::msg::{self as ros, datatype};
use std::collections::BTreeMap;
use std::io::{BufWriter, Seek, Write};

/// Topics and frames of a recording.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// Cloud topic.
    pub cloud_topic: String,
    /// Odometry topic.
    pub odom_topic: String,
    /// The sensor's pose on the base (the base pose is the sensor's times its inverse).
    pub sensor_to_base: Isometry3<f64>,
    /// Compress chunks with zstd (as rosbag2's `--compression-mode message` presets do).
    pub zstd: bool,
}

impl Default for RecordOptions {
    fn default() -> Self {
        Self {
            cloud_topic: "/points".into(),
            odom_topic: "/odom".into(),
            sensor_to_base: Isometry3::identity(),
            zstd: false,
        }
    }
}

/// Why a recording could not be written.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// MCAP writing failed.
    #[error("cannot write MCAP")]
    Mcap(#[from] mcap::McapError),
    /// A message did not encode.
    #[error("cannot encode a message")]
    Encode(#[from] ros::EncodeError),
    /// The file could not be created.
    #[error("cannot create the file")]
    Io(#[from] std::io::Error),
}

/// An organized cloud of `scan` (rows: rings, columns: firing columns).
pub fn cloud_of(scan: &GeneratedScan, frame_id: &str) -> ros::PointCloud2 {
    const STEP: usize = 20;
    let rows = scan
        .points
        .iter()
        .map(|p| usize::from(p.ring) + 1)
        .max()
        .unwrap_or(0);
    let cols = scan
        .points
        .iter()
        .map(|p| usize::from(p.column) + 1)
        .max()
        .unwrap_or(0);
    let mut data = Vec::with_capacity(rows * cols * STEP);
    for _ in 0..rows * cols {
        for _ in 0..3 {
            data.extend(f32::NAN.to_le_bytes());
        }
        data.extend([0u8; 8]);
    }
    for p in &scan.points {
        let k = (usize::from(p.ring) * cols + usize::from(p.column)) * STEP;
        let (r, i, a) = (p.range_m, p.inclination_rad, p.azimuth_rad);
        let xyz = if p.has_return() {
            [r * i.sin() * a.cos(), r * i.sin() * a.sin(), r * i.cos()]
        } else {
            [f32::NAN; 3]
        };
        for (j, v) in xyz.iter().enumerate() {
            data[k + 4 * j..k + 4 * j + 4].copy_from_slice(&v.to_le_bytes());
        }
        data[k + 12..k + 14].copy_from_slice(&p.ring.to_le_bytes());
        data[k + 16..k + 20].copy_from_slice(&p.time_offset_ns.to_le_bytes());
    }
    let field = ros::PointField::new;
    ros::PointCloud2 {
        header: ros::Header {
            stamp: ros::Time::from_ns(scan.header.stamp_ns),
            frame_id: frame_id.into(),
        },
        height: rows as u32,
        width: cols as u32,
        fields: vec![
            field("x", 0, datatype::FLOAT32),
            field("y", 4, datatype::FLOAT32),
            field("z", 8, datatype::FLOAT32),
            field("ring", 12, datatype::UINT16),
            field("t", 16, datatype::UINT32),
        ],
        is_bigendian: false,
        point_step: STEP as u32,
        row_step: (cols * STEP) as u32,
        data,
        is_dense: false,
    }
}

/// The base pose as geometry_msgs fields.
fn pose_msg(base: &Isometry3<f64>) -> (ros::Vector3, ros::Quaternion) {
    let t = base.translation.vector;
    let q = base.rotation.quaternion();
    (
        ros::Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        ros::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    )
}

/// Writes `scans` (stamped, in order) to `out` as a recording.
pub fn write<W: Write + Seek>(
    out: W,
    scans: &[GeneratedScan],
    opts: &RecordOptions,
) -> Result<(), RecordError> {
    let compression = opts.zstd.then_some(mcap::Compression::Zstd);
    let mut w = mcap::WriteOptions::new()
        .profile("ros2")
        .compression(compression)
        .create(BufWriter::new(out))?;
    let none = BTreeMap::new();
    let mut channel = |name: &str, topic: &str| -> Result<u16, RecordError> {
        let text = ros::schema_text(name).unwrap_or_default();
        let schema = w.add_schema(name, "ros2msg", text.as_bytes())?;
        Ok(w.add_channel(schema, topic, "cdr", &none)?)
    };
    let clouds = channel(ros::POINT_CLOUD2, &opts.cloud_topic)?;
    let odom = channel(ros::ODOMETRY, &opts.odom_topic)?;
    let tf = channel(ros::TF_MESSAGE, "/tf")?;
    let tf_static = channel(ros::TF_MESSAGE, "/tf_static")?;
    let mut sequence = 0u32;
    let mut put = |w: &mut mcap::Writer<_>, channel_id: u16, stamp: u64, data: &[u8]| {
        sequence += 1;
        let header = MessageHeader {
            channel_id,
            sequence,
            log_time: stamp,
            publish_time: stamp,
        };
        w.write_to_known_channel(&header, data)
    };
    let base_to_sensor = opts.sensor_to_base.inverse();
    if let Some(first) = scans.first() {
        let (translation, rotation) = pose_msg(&opts.sensor_to_base);
        let mount = ros::TfMessage {
            transforms: vec![ros::TransformStamped {
                header: ros::Header {
                    stamp: ros::Time::from_ns(first.header.stamp_ns),
                    frame_id: "base_link".into(),
                },
                child_frame_id: "lidar".into(),
                transform: ros::Transform {
                    translation,
                    rotation,
                },
            }],
        };
        put(&mut w, tf_static, first.header.stamp_ns, &ros::encode(&mount)?)?;
    }
    for scan in scans {
        let stamp = scan.header.stamp_ns;
        let base = scan.pose * base_to_sensor;
        let (position, orientation) = pose_msg(&base);
        let header = ros::Header {
            stamp: ros::Time::from_ns(stamp),
            frame_id: "odom".into(),
        };
        let o = ros::Odometry {
            header: header.clone(),
            child_frame_id: "base_link".into(),
            pose: ros::PoseWithCovariance {
                pose: ros::Pose {
                    position,
                    orientation,
                },
                covariance: ros::Covariance::default(),
            },
            twist: ros::TwistWithCovariance::default(),
        };
        put(&mut w, odom, stamp, &ros::encode(&o)?)?;
        let t = ros::TfMessage {
            transforms: vec![ros::TransformStamped {
                header,
                child_frame_id: "base_link".into(),
                transform: ros::Transform {
                    translation: position,
                    rotation: orientation,
                },
            }],
        };
        put(&mut w, tf, stamp, &ros::encode(&t)?)?;
        put(&mut w, clouds, stamp, &ros::encode(&cloud_of(scan, "lidar"))?)?;
    }
    w.finish()?;
    Ok(())
}
