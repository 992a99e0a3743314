//! The ROS 2 messages a recording carries (sensor_msgs/PointCloud2, nav_msgs/Odometry,
//! tf2_msgs/TFMessage and what they contain), field for field as their `.msg` files define them,
//! and their CDR encoding as rosbag2 stores it in MCAP: a 4-byte encapsulation header, then the
//! message in OMG CDR.

use byteorder::{BigEndian, LittleEndian};
use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Encapsulation header of little-endian plain CDR (what ROS 2 writes on x86 and ARM).
const CDR_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// MCAP schema names of the messages read.
pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
/// Odometry's schema name.
pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
/// TF's schema name.
pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";

/// A message that did not decode.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// Fewer than the 4 bytes of the encapsulation header.
    #[error("message of {0} bytes has no CDR encapsulation header")]
    Truncated(usize),
    /// An encapsulation other than plain CDR (e.g. XCDR2 or parameter lists).
    #[error("unsupported CDR encapsulation {0:02x?} (plain CDR, little or big endian, is read)")]
    Encapsulation([u8; 2]),
    /// The body did not match the message's layout.
    #[error("CDR body does not match the message layout")]
    Cdr(#[from] cdr_encoding::Error),
}

/// A message that did not encode.
#[derive(Debug, thiserror::Error)]
#[error("CDR encoding failed")]
pub struct EncodeError(#[from] cdr_encoding::Error);

/// Decodes a CDR-encapsulated message.
pub fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Result<T, DecodeError> {
    let (head, body) = bytes
        .split_at_checked(4)
        .ok_or(DecodeError::Truncated(bytes.len()))?;
    match [head[0], head[1]] {
        [0x00, 0x01] => Ok(cdr_encoding::from_bytes::<T, LittleEndian>(body)?.0),
        [0x00, 0x00] => Ok(cdr_encoding::from_bytes::<T, BigEndian>(body)?.0),
        other => Err(DecodeError::Encapsulation(other)),
    }
}

/// Encodes a message as little-endian CDR with its encapsulation header.
pub fn encode<T: Serialize>(message: &T) -> Result<Vec<u8>, EncodeError> {
    let mut out = CDR_LE.to_vec();
    out.extend(cdr_encoding::to_vec::<T, LittleEndian>(message)?);
    Ok(out)
}

/// builtin_interfaces/Time.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch (0 for a time before it).
    pub fn as_ns(&self) -> u64 {
        u64::try_from(self.sec).map_or(0, |s| s * 1_000_000_000 + u64::from(self.nanosec))
    }

    /// The time `ns` nanoseconds after the epoch (seconds saturate at i32::MAX).
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// std_msgs/Header.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Time,
    /// Frame the data is in.
    pub frame_id: String,
}

/// sensor_msgs/PointField.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (x, y, z, ring, t, time, ...).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// One of the `datatype` constants (INT8 = 1 ... FLOAT64 = 8).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

impl PointField {
    /// A field of one element.
    pub fn new(name: &str, offset: u32, datatype: u8) -> Self {
        Self {
            name: name.into(),
            offset,
            datatype,
            count: 1,
        }
    }
}

/// PointField datatypes.
pub mod datatype {
    /// int8.
    pub const INT8: u8 = 1;
    /// uint8.
    pub const UINT8: u8 = 2;
    /// int16.
    pub const INT16: u8 = 3;
    /// uint16.
    pub const UINT16: u8 = 4;
    /// int32.
    pub const INT32: u8 = 5;
    /// uint32.
    pub const UINT32: u8 = 6;
    /// float32.
    pub const FLOAT32: u8 = 7;
    /// float64.
    pub const FLOAT64: u8 = 8;
}

/// sensor_msgs/PointCloud2.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and sensor frame.
    pub header: Header,
    /// Rows (1 for an unorganized cloud; the laser rings of an organized one).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// Layout of one point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// True when no point is invalid (NaN).
    pub is_dense: bool,
}

/// geometry_msgs/Vector3 (and Point: the same three float64).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// geometry_msgs/Quaternion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// Scalar part.
    pub w: f64,
}

/// geometry_msgs/Pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position (a geometry_msgs/Point).
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// A row-major 6 × 6 covariance (`float64[36]`: CDR writes it without a length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Default for Covariance {
    fn default() -> Self {
        Self([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut t = serializer.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Elements;
        impl<'de> Visitor<'de> for Elements {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut out = [0.0; 36];
                for (i, v) in out.iter_mut().enumerate() {
                    *v = seq
                        .next_element()?
                        .ok_or_else(|| de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(out))
            }
        }
        deserializer.deserialize_tuple(36, Elements)
    }
}

/// geometry_msgs/PoseWithCovariance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Its covariance.
    pub covariance: Covariance,
}

/// geometry_msgs/Twist.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity, m/s.
    pub linear: Vector3,
    /// Angular velocity, rad/s.
    pub angular: Vector3,
}

/// geometry_msgs/TwistWithCovariance.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Its covariance.
    pub covariance: Covariance,
}

/// nav_msgs/Odometry: the pose of `child_frame_id` in `header.frame_id`, the twist in the child
/// frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Stamp and the parent frame.
    pub header: Header,
    /// The moving frame (the robot's base).
    pub child_frame_id: String,
    /// Pose of the child frame.
    pub pose: PoseWithCovariance,
    /// Velocity of the child frame, in the child frame.
    pub twist: TwistWithCovariance,
}

/// geometry_msgs/Transform.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// geometry_msgs/TransformStamped: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The transform.
    pub transform: Transform,
}

/// tf2_msgs/TFMessage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// The `ros2msg` schema text of `name` as rosbag2 writes it (the message, then each nested type
/// after a separator line), for recordings written by the lab.
pub fn schema_text(name: &str) -> Option<String> {
    let sep = "================================================================================";
    let header = "builtin_interfaces/Time stamp\nstring frame_id";
    let time = "int32 sec\nuint32 nanosec";
    let dep = |n: &str, body: &str| format!("{sep}\nMSG: {n}\n{body}\n");
    let text = match name {
        POINT_CLOUD2 => format!(
            "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n\
             bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n{}{}{}",
            dep("std_msgs/Header", header),
            dep("builtin_interfaces/Time", time),
            dep(
                "sensor_msgs/PointField",
                "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n\
                 uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\n\
                 uint8 datatype\nuint32 count"
            ),
        ),
        ODOMETRY => format!(
            "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
             geometry_msgs/TwistWithCovariance twist\n{}{}{}{}{}{}{}{}{}",
            dep("std_msgs/Header", header),
            dep("builtin_interfaces/Time", time),
            dep(
                "geometry_msgs/PoseWithCovariance",
                "Pose pose\nfloat64[36] covariance"
            ),
            dep("geometry_msgs/Pose", "Point position\nQuaternion orientation"),
            dep("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z"),
            dep(
                "geometry_msgs/Quaternion",
                "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1"
            ),
            dep(
                "geometry_msgs/TwistWithCovariance",
                "Twist twist\nfloat64[36] covariance"
            ),
            dep("geometry_msgs/Twist", "Vector3 linear\nVector3 angular"),
            dep("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z"),
        ),
        TF_MESSAGE => format!(
            "geometry_msgs/TransformStamped[] transforms\n{}{}{}{}{}{}",
            dep(
                "geometry_msgs/TransformStamped",
                "std_msgs/Header header\nstring child_frame_id\nTransform transform"
            ),
            dep("std_msgs/Header", header),
            dep("builtin_interfaces/Time", time),
            dep(
                "geometry_msgs/Transform",
                "Vector3 translation\nQuaternion rotation"
            ),
            dep("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z"),
            dep(
                "geometry_msgs/Quaternion",
                "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1"
            ),
        ),
        _ => return None,
    };
    Some(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_round_trips_in_both_byte_orders_with_rosbag2_alignment() {
        let mut cov = Covariance::default();
        cov.0[35] = 0.25;
        let odom = Odometry {
            header: Header {
                stamp: Time::from_ns(1_700_000_000_123_456_789),
                frame_id: "odom".into(),
            },
            child_frame_id: "base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose {
                    position: Vector3 {
                        x: 1.0,
                        y: -2.0,
                        z: 0.5,
                    },
                    orientation: Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: 0.6,
                        w: 0.8,
                    },
                },
                covariance: cov,
            },
            twist: TwistWithCovariance::default(),
        };
        let le = encode(&odom).expect("encode");
        assert_eq!(&le[..4], &CDR_LE);
        // Header: sec, nanosec, "odom\0" (4 + 5 bytes), then "base_link\0" at a 4-byte boundary
        // and the first float64 at an 8-byte boundary of the body.
        let body = &le[4..];
        assert_eq!(&body[8..12], &5u32.to_le_bytes());
        assert_eq!(&body[12..17], b"odom\0");
        assert_eq!(&body[20..24], &10u32.to_le_bytes());
        assert_eq!(&body[24..34], b"base_link\0");
        assert_eq!(&body[40..48], &1.0f64.to_le_bytes());
        assert_eq!(decode::<Odometry>(&le).expect("decode"), odom);
        // A recording from a big-endian machine: encapsulation 0x0000, the body big-endian.
        let mut be = vec![0x00, 0x00, 0x00, 0x00];
        be.extend(cdr_encoding::to_vec::<_, BigEndian>(&odom).expect("encode"));
        assert_eq!(decode::<Odometry>(&be).expect("decode"), odom);
        assert!(matches!(
            decode::<Odometry>(&le[..2]),
            Err(DecodeError::Truncated(2))
        ));
        let mut xcdr2 = le.clone();
        xcdr2[1] = 0x07;
        assert!(matches!(
            decode::<Odometry>(&xcdr2),
            Err(DecodeError::Encapsulation(_))
        ));
        assert!(decode::<Odometry>(&le[..30]).is_err());
        assert_eq!(odom.header.stamp.as_ns(), 1_700_000_000_123_456_789);
    }
}
