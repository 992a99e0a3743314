//! Scan headers from poses: where the sensor was when it swept, and how it moved meanwhile.

use crate::cloud::{scan_points, CloudError};
use crate::msg::PointCloud2;
use crate::poses::{sensor_twist, Timeline};
use nalgebra::Isometry3;
use rangegp_proto::scan::{ScanHeader, ScanPoint};

/// A scan header at `stamp_ns` for a sensor at `pose` with its range and noise model (no
/// motion; sequence, publisher id and point count left for the publisher).
pub fn pose_header(
    pose: &Isometry3<f64>,
    stamp_ns: u64,
    max_range_m: f64,
    range_noise_per_m: f64,
) -> ScanHeader {
    let q = pose.rotation.quaternion();
    let t = pose.translation.vector;
    ScanHeader {
        stamp_ns,
        px_m: t.x,
        py_m: t.y,
        pz_m: t.z,
        qx: q.i,
        qy: q.j,
        qz: q.k,
        qw: q.w,
        max_range_m,
        range_noise_per_m,
        ..ScanHeader::default()
    }
}

/// `header` with the sensor's linear (m/s) and angular (rad/s) velocity in its own frame.
pub fn with_twist(header: ScanHeader, linear: [f64; 3], angular: [f64; 3]) -> ScanHeader {
    let ([vx_mps, vy_mps, vz_mps], [wx_radps, wy_radps, wz_radps]) = (linear, angular);
    ScanHeader {
        vx_mps,
        vy_mps,
        vz_mps,
        wx_radps,
        wy_radps,
        wz_radps,
        ..header
    }
}

/// The range model a scan header carries for a sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeModel {
    /// Returns at or beyond this range are no-returns, metres.
    pub max_range_m: f64,
    /// Range noise σ per metre of range.
    pub range_noise_per_m: f64,
}

/// Why a cloud did not become a scan; [`Skip::reason`] is the name it is counted under.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Skip {
    /// No base pose within the timeline's gap limit of the cloud's stamp.
    NoPose,
    /// The cloud holds no point.
    Empty,
    /// More points than a scan may carry.
    TooManyPoints,
    /// Fields missing or the layout inconsistent.
    Layout,
}

impl Skip {
    /// The counter name: `no_pose`, `empty`, `too_many_points`, `layout`.
    pub fn reason(self) -> &'static str {
        match self {
            Skip::NoPose => "no_pose",
            Skip::Empty => "empty",
            Skip::TooManyPoints => "too_many_points",
            Skip::Layout => "layout",
        }
    }
}

/// A cloud stamped `stamp_ns` as a scan: the base's pose and twist at that stamp from
/// `timeline`, carried to the sensor through `sensor_to_base`, and the cloud's points (sensor
/// frame), at most `max_points`.
pub fn from_cloud(
    cloud: &PointCloud2,
    stamp_ns: u64,
    timeline: &Timeline,
    sensor_to_base: &Isometry3<f64>,
    model: RangeModel,
    max_points: usize,
) -> Result<(ScanHeader, Vec<ScanPoint>), Skip> {
    let (base, base_twist) = timeline.at(stamp_ns).ok_or(Skip::NoPose)?;
    let points = match scan_points(cloud, max_points) {
        Ok(p) if p.is_empty() => return Err(Skip::Empty),
        Ok(p) => p,
        Err(CloudError::TooManyPoints { .. }) => return Err(Skip::TooManyPoints),
        Err(_) => return Err(Skip::Layout),
    };
    let (v, w) = base_twist
        .map(|t| sensor_twist(t, sensor_to_base))
        .unwrap_or_default();
    let at = pose_header(
        &(base * sensor_to_base),
        stamp_ns,
        model.max_range_m,
        model.range_noise_per_m,
    );
    Ok((with_twist(at, v.into(), w.into()), points))
}
