//! The robot's base pose over a recording, from nav_msgs/Odometry or from /tf, interpolated at
//! each cloud's stamp (linear in position, spherical in rotation), and the sensor's pose and twist
//! through the fixed sensor-to-base transform (REP-105: base_link in odom or map).

use crate::msg as ros;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// Pose samples further than this from a stamp do not vouch for it, nanoseconds.
pub const MAX_GAP_NS: u64 = 200_000_000;

/// A twist: linear (m/s) and angular (rad/s) velocity, in the frame that moves.
pub type Twist = (Vector3<f64>, Vector3<f64>);

/// One sample: stamp, pose of the base, and its twist in the base frame when known.
#[derive(Debug, Clone, Copy)]
struct Sample {
    stamp_ns: u64,
    pose: Isometry3<f64>,
    twist: Option<Twist>,
}

/// The base's pose over time.
#[derive(Debug, Clone, Default)]
pub struct Timeline {
    samples: Vec<Sample>,
}

/// A pose as an isometry (`None` when not finite or the quaternion is far from unit).
fn isometry(p: &ros::Vector3, q: &ros::Quaternion) -> Option<Isometry3<f64>> {
    let quat = Quaternion::new(q.w, q.x, q.y, q.z);
    let norm = quat.norm();
    let finite = [p.x, p.y, p.z, q.x, q.y, q.z, q.w].iter().all(|v| v.is_finite());
    (finite && (norm - 1.0).abs() < 1e-3).then(|| {
        Isometry3::from_parts(
            Translation3::new(p.x, p.y, p.z),
            UnitQuaternion::from_quaternion(quat),
        )
    })
}

impl Timeline {
    /// Adds an odometry message; false when its pose is not a valid rigid transform.
    pub fn add_odometry(&mut self, m: &ros::Odometry) -> bool {
        let Some(pose) = isometry(&m.pose.pose.position, &m.pose.pose.orientation) else {
            return false;
        };
        let (l, a) = (m.twist.twist.linear, m.twist.twist.angular);
        let twist = Some((Vector3::new(l.x, l.y, l.z), Vector3::new(a.x, a.y, a.z)))
            .filter(|(l, a)| l.iter().chain(a.iter()).all(|v| v.is_finite()));
        self.insert(Sample {
            stamp_ns: m.header.stamp.as_ns(),
            pose,
            twist,
        });
        true
    }

    /// Adds the transforms of a TF message whose child is `base_frame` (its parent is the fixed
    /// frame: odom or map); returns how many were taken and how many were invalid.
    pub fn add_tf(&mut self, m: &ros::TfMessage, base_frame: &str) -> (usize, usize) {
        let (mut taken, mut invalid) = (0, 0);
        for t in m.transforms.iter().filter(|t| t.child_frame_id == base_frame) {
            match isometry(&t.transform.translation, &t.transform.rotation) {
                Some(pose) => {
                    self.insert(Sample {
                        stamp_ns: t.header.stamp.as_ns(),
                        pose,
                        twist: None,
                    });
                    taken += 1;
                }
                None => invalid += 1,
            }
        }
        (taken, invalid)
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True without samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Keeps the samples in stamp order (appending when they come in order, as they do live).
    fn insert(&mut self, sample: Sample) {
        let at = self.samples.partition_point(|s| s.stamp_ns <= sample.stamp_ns);
        self.samples.insert(at, sample);
    }

    /// Drops the samples older than `stamp_ns` except the newest of them (it still brackets a
    /// stamp just after): what bounds a live timeline's memory.
    pub fn forget_before(&mut self, stamp_ns: u64) {
        let older = self.samples.partition_point(|s| s.stamp_ns < stamp_ns);
        self.samples.drain(..older.saturating_sub(1));
    }

    /// Stamp of the newest sample.
    pub fn newest_ns(&self) -> Option<u64> {
        self.samples.last().map(|s| s.stamp_ns)
    }

    /// The newest sample's pose.
    pub fn newest(&self) -> Option<Isometry3<f64>> {
        self.samples.last().map(|s| s.pose)
    }

    /// The base pose at `stamp_ns` and its twist (linear, angular; base frame), interpolated
    /// between the samples around it, or `None` when no sample lies within [`MAX_GAP_NS`] on
    /// either side (a stamp beyond the ends is answered by the end sample within that gap).
    pub fn at(&self, stamp_ns: u64) -> Option<(Isometry3<f64>, Option<Twist>)> {
        let i = self.samples.partition_point(|s| s.stamp_ns < stamp_ns);
        let after = self.samples.get(i);
        let before = i.checked_sub(1).map(|k| &self.samples[k]);
        let near = |s: &Sample| s.stamp_ns.abs_diff(stamp_ns) <= MAX_GAP_NS;
        match (before, after) {
            (Some(a), Some(b)) if near(a) && near(b) => {
                let span = (b.stamp_ns - a.stamp_ns) as f64;
                let w = if span > 0.0 {
                    (stamp_ns - a.stamp_ns) as f64 / span
                } else {
                    0.0
                };
                let t = a.pose.translation.vector.lerp(&b.pose.translation.vector, w);
                let r = a
                    .pose
                    .rotation
                    .try_slerp(&b.pose.rotation, w, 1e-9)
                    .unwrap_or(a.pose.rotation);
                let twist = if w < 0.5 {
                    a.twist.or(b.twist)
                } else {
                    b.twist.or(a.twist)
                };
                Some((Isometry3::from_parts(Translation3::from(t), r), twist))
            }
            (Some(s), _) | (_, Some(s)) if near(s) => Some((s.pose, s.twist)),
            _ => None,
        }
    }
}

/// A mount as the command line and configuration give it: x, y, z (metres), roll, pitch, yaw
/// (degrees, applied as ROS does: about x, then y, then z).
pub fn mount(xyz_rpy_deg: [f64; 6]) -> Isometry3<f64> {
    let [x, y, z, roll, pitch, yaw] = xyz_rpy_deg;
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), yaw.to_radians()),
    )
}

/// Most links followed from the sensor's frame up to the base in `/tf_static`.
const MAX_STATIC_LINKS: usize = 16;

/// The pose of `sensor_frame` on `base_frame` through the static transforms (each the pose of
/// its child in its parent), following child → parent links; the identity when the frames are
/// the same, `None` when no chain joins them.
pub fn static_mount(
    transforms: &[ros::TransformStamped],
    base_frame: &str,
    sensor_frame: &str,
) -> Option<Isometry3<f64>> {
    let mut pose = Isometry3::identity();
    let mut frame = sensor_frame;
    for _ in 0..MAX_STATIC_LINKS {
        if frame == base_frame {
            return Some(pose);
        }
        let link = transforms.iter().find(|t| t.child_frame_id == frame)?;
        pose = isometry(&link.transform.translation, &link.transform.rotation)? * pose;
        frame = &link.header.frame_id;
    }
    None
}

/// The sensor's twist in its own frame, from the base's (base frame) through the sensor's pose
/// on the base: ω_s = Rᵀ ω_b, v_s = Rᵀ (v_b + ω_b × t).
pub fn sensor_twist(base_twist: Twist, sensor_to_base: &Isometry3<f64>) -> Twist {
    let (v, w) = base_twist;
    let r = sensor_to_base.rotation.inverse();
    let lever = w.cross(&sensor_to_base.translation.vector);
    (r * (v + lever), r * w)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn odom(stamp_ns: u64, x: f64, yaw: f64) -> ros::Odometry {
        let (s, c) = (0.5 * yaw).sin_cos();
        ros::Odometry {
            header: ros::Header {
                stamp: ros::Time::from_ns(stamp_ns),
                frame_id: "odom".into(),
            },
            child_frame_id: "base_link".into(),
            pose: ros::PoseWithCovariance {
                pose: ros::Pose {
                    position: ros::Vector3 { x, y: 0.0, z: 0.0 },
                    orientation: ros::Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: s,
                        w: c,
                    },
                },
                covariance: ros::Covariance::default(),
            },
            twist: ros::TwistWithCovariance {
                twist: ros::Twist {
                    linear: ros::Vector3 {
                        x: 1.0,
                        y: 0.0,
                        z: 0.0,
                    },
                    angular: ros::Vector3 {
                        x: 0.0,
                        y: 0.0,
                        z: 0.5,
                    },
                },
                covariance: ros::Covariance::default(),
            },
        }
    }

    #[test]
    fn poses_interpolate_between_samples_and_refuse_gaps() {
        let mut t = Timeline::default();
        assert!(t.add_odometry(&odom(2_000_000_000, 2.0, 0.4)));
        assert!(t.add_odometry(&odom(1_900_000_000, 1.0, 0.2)));
        let mut bad = odom(1_950_000_000, 1.0, 0.0);
        bad.pose.pose.orientation.w = 3.0;
        assert!(!t.add_odometry(&bad), "a non-unit quaternion is refused");
        let (mid, twist) = t.at(1_950_000_000).expect("between two samples");
        assert!((mid.translation.x - 1.5).abs() < 1e-12);
        assert!((mid.rotation.euler_angles().2 - 0.3).abs() < 1e-9);
        assert!(twist.is_some());
        assert!(
            t.at(2_100_000_000).is_some(),
            "within the gap after the last sample"
        );
        assert!(t.at(2_300_000_000).is_none(), "too far after the last sample");
        assert!(t.add_odometry(&odom(2_100_000_000, 3.0, 0.4)));
        t.forget_before(2_050_000_000);
        assert_eq!(
            t.len(),
            2,
            "the newest older sample stays to bracket later stamps"
        );
        assert!(t.at(2_050_000_000).is_some());
        assert_eq!(t.newest_ns(), Some(2_100_000_000));
        // A sensor 1 m ahead of the base turning at 0.5 rad/s moves sideways at 0.5 m/s too.
        let mount = Isometry3::translation(1.0, 0.0, 0.0);
        let (v, w) = sensor_twist((Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.5)), &mount);
        assert!((v - Vector3::new(1.0, 0.5, 0.0)).norm() < 1e-12);
        assert!((w.z - 0.5).abs() < 1e-12);
        // base_link → mast (1 m up) → lidar (turned 90° about z, 0.2 m ahead on the mast).
        let link = |parent: &str, child: &str, x: f64, z: f64, yaw: f64| ros::TransformStamped {
            header: ros::Header {
                stamp: ros::Time::default(),
                frame_id: parent.into(),
            },
            child_frame_id: child.into(),
            transform: ros::Transform {
                translation: ros::Vector3 { x, y: 0.0, z },
                rotation: ros::Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: (0.5 * yaw).sin(),
                    w: (0.5 * yaw).cos(),
                },
            },
        };
        let tf = [
            link("mast", "lidar", 0.2, 0.0, std::f64::consts::FRAC_PI_2),
            link("base_link", "mast", 0.0, 1.0, 0.0),
        ];
        let m = static_mount(&tf, "base_link", "lidar").expect("a chain");
        assert!((m.translation.vector - Vector3::new(0.2, 0.0, 1.0)).norm() < 1e-12);
        assert!((m.rotation.euler_angles().2 - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert_eq!(
            static_mount(&tf, "base_link", "base_link"),
            Some(Isometry3::identity())
        );
        assert!(static_mount(&tf, "base_link", "camera").is_none());
    }
}
