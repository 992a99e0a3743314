//! The domain types of a scan inside the daemon: what ingest makes of a shared-memory sample
//! ([`ScanInput`], [`RayObservation`]) and why one may be refused ([`RejectReason`]). Fitting,
//! ingest and metrics all use them; they depend on nothing else in the crate.

use nalgebra::Isometry3;

/// One returned ray of a validated scan, in the sensor frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayObservation {
    /// Polar angle from the sensor's +z axis, radians.
    pub inclination: f64,
    /// Azimuth, radians.
    pub azimuth: f64,
    /// Measured range, metres.
    pub range: f64,
}

/// A validated scan in private memory: what the ingest hands to fitting.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanInput {
    /// Publisher that sent it.
    pub publisher_id: u64,
    /// Its per-publisher sequence number.
    pub sequence: u64,
    /// Acquisition time, ns since the Unix epoch.
    pub stamp_ns: u64,
    /// Sensor frame in the map frame.
    pub pose: Isometry3<f64>,
    /// Sensor maximum range, metres.
    pub max_range_m: f64,
    /// Range noise σ per metre of range.
    pub range_noise_per_m: f64,
    /// Range noise σ at every range beyond the header's per-metre part, metres: what the scan's
    /// own returns show (`ingest::noise`; 0 where they cannot tell).
    pub range_noise_floor_m: f64,
    /// Returned rays.
    pub rays: Vec<RayObservation>,
}

impl ScanInput {
    /// Range noise σ of a return at `range` metres: √(floor² + (per_m · range)²).
    pub fn range_sd(&self, range: f64) -> f64 {
        self.range_noise_floor_m.hypot(self.range_noise_per_m * range)
    }
}

/// Why a scan was rejected; each is counted separately and reported by `status`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RejectReason {
    /// `protocol_version` is not this daemon's.
    UnsupportedVersion,
    /// `point_count` is zero.
    EmptyScan,
    /// `point_count` exceeds `ingest.max_points`.
    TooManyPoints,
    /// `point_count` exceeds the slice actually sent.
    Truncated,
    /// A returned ray has a non-finite or negative range.
    InvalidRange,
    /// A ray's angles are non-finite or out of [0, π] × [−π, 2π).
    InvalidAngle,
    /// A point sets unknown flag bits or a non-zero reserved field.
    InvalidFlags,
    /// The pose has a non-finite position or quaternion component.
    InvalidPose,
    /// The quaternion's norm is not 1 (± 1e-3).
    NonUnitQuaternion,
    /// Max range or noise coefficient out of range.
    InvalidSensorModel,
    /// Sequence number below the source's last accepted one, within
    /// `ingest.sequence_restart_window` (out of order or replayed late).
    StaleSequence,
    /// Sequence number equal to the publisher's last accepted one (sent twice).
    DuplicateSequence,
    /// Acquisition time later than now plus `ingest.max_future_ms` (a driver clock gone wrong).
    FutureTimestamp,
    /// Every ray was a no-return: nothing to map.
    NoReturns,
    /// The GP could not be fitted (Cholesky failed after jitter).
    FitFailed,
    /// The pose lies outside `ingest.map_bounds_m`, or jumped from the publisher's last
    /// accepted pose faster than `ingest.max_speed_mps` allows (a localisation glitch).
    ImplausiblePose,
    /// The sweep's twist is non-finite or beyond 100 m/s or 50 rad/s, or a point fired more
    /// than a second after the stamp.
    InvalidMotion,
}

impl RejectReason {
    /// Every reason, in status order.
    pub const ALL: [RejectReason; 17] = [
        RejectReason::UnsupportedVersion,
        RejectReason::EmptyScan,
        RejectReason::TooManyPoints,
        RejectReason::Truncated,
        RejectReason::InvalidRange,
        RejectReason::InvalidAngle,
        RejectReason::InvalidFlags,
        RejectReason::InvalidPose,
        RejectReason::NonUnitQuaternion,
        RejectReason::InvalidSensorModel,
        RejectReason::StaleSequence,
        RejectReason::DuplicateSequence,
        RejectReason::FutureTimestamp,
        RejectReason::NoReturns,
        RejectReason::FitFailed,
        RejectReason::ImplausiblePose,
        RejectReason::InvalidMotion,
    ];

    /// Stable snake_case name (status replies, logs, docs/PROTOCOL.md).
    pub fn as_str(self) -> &'static str {
        match self {
            RejectReason::UnsupportedVersion => "unsupported_version",
            RejectReason::EmptyScan => "empty_scan",
            RejectReason::TooManyPoints => "too_many_points",
            RejectReason::Truncated => "truncated",
            RejectReason::InvalidRange => "invalid_range",
            RejectReason::InvalidAngle => "invalid_angle",
            RejectReason::InvalidFlags => "invalid_flags",
            RejectReason::InvalidPose => "invalid_pose",
            RejectReason::NonUnitQuaternion => "non_unit_quaternion",
            RejectReason::InvalidSensorModel => "invalid_sensor_model",
            RejectReason::StaleSequence => "stale_sequence",
            RejectReason::DuplicateSequence => "duplicate_sequence",
            RejectReason::FutureTimestamp => "future_timestamp",
            RejectReason::NoReturns => "no_returns",
            RejectReason::FitFailed => "fit_failed",
            RejectReason::ImplausiblePose => "implausible_pose",
            RejectReason::InvalidMotion => "invalid_motion",
        }
    }
}
