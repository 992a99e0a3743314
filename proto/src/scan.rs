//! Shared-memory scan types: one [`ScanHeader`] (iceoryx2 user header) and a slice of [`ScanPoint`].
//!
//! Layouts are fixed (`#[repr(C)]`, explicit reserved fields, no implicit padding) and checked by
//! tests below so that C++ and Python mirrors stay byte-identical. See `docs/PROTOCOL.md`.

use iceoryx2::prelude::ZeroCopySend;

/// Type name the iceoryx2 service registers for the header (Python / C++ mirrors must match).
pub const SCAN_HEADER_TYPE_NAME: &str = "rangegp::ScanHeader";
/// Type name the iceoryx2 service registers for one point (Python / C++ mirrors must match).
pub const SCAN_POINT_TYPE_NAME: &str = "rangegp::ScanPoint";

/// Metadata of one LiDAR scan: who sent it, when, from where, and the sensor model.
///
/// The pose is the sensor frame in the map frame (REP-103: x forward, y left, z up); the
/// quaternion is Hamilton, unit norm, with its components named (`qw` is the scalar part).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("rangegp::ScanHeader")]
#[repr(C)]
pub struct ScanHeader {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// Number of valid entries in the point slice (the slice may be longer, never shorter).
    pub point_count: u32,
    /// Stable id of the publishing process or driver; sequences are tracked per publisher.
    pub publisher_id: u64,
    /// Per-publisher sequence number, strictly increasing by one per scan.
    pub sequence: u64,
    /// Acquisition time, nanoseconds since the Unix epoch.
    pub stamp_ns: u64,
    /// Sensor position in the map frame, metres.
    pub px_m: f64,
    /// Sensor position y, metres.
    pub py_m: f64,
    /// Sensor position z, metres.
    pub pz_m: f64,
    /// Orientation quaternion, x component.
    pub qx: f64,
    /// Orientation quaternion, y component.
    pub qy: f64,
    /// Orientation quaternion, z component.
    pub qz: f64,
    /// Orientation quaternion, scalar component.
    pub qw: f64,
    /// Maximum range of the sensor, metres; returns at or beyond it are treated as no-return.
    pub max_range_m: f64,
    /// Range noise standard deviation per metre of range (σ_i = coefficient · r_i), dimensionless.
    pub range_noise_per_m: f64,
    /// The sensor's linear velocity during the sweep, in its own frame at `stamp_ns`, m/s, x
    /// component (with the angular velocity: the twist the daemon deskews with; all six zero for
    /// a sensor at rest or a driver that deskewed already).
    pub vx_mps: f64,
    /// Linear velocity, y component, m/s.
    pub vy_mps: f64,
    /// Linear velocity, z component, m/s.
    pub vz_mps: f64,
    /// The sensor's angular velocity during the sweep, in its own frame, rad/s, x component.
    pub wx_radps: f64,
    /// Angular velocity, y component, rad/s.
    pub wy_radps: f64,
    /// Angular velocity, z component, rad/s.
    pub wz_radps: f64,
}

impl Default for ScanHeader {
    fn default() -> Self {
        Self {
            protocol_version: crate::PROTOCOL_VERSION,
            point_count: 0,
            publisher_id: 0,
            sequence: 0,
            stamp_ns: 0,
            px_m: 0.0,
            py_m: 0.0,
            pz_m: 0.0,
            qx: 0.0,
            qy: 0.0,
            qz: 0.0,
            qw: 1.0,
            max_range_m: 0.0,
            range_noise_per_m: 0.0,
            vx_mps: 0.0,
            vy_mps: 0.0,
            vz_mps: 0.0,
            wx_radps: 0.0,
            wy_radps: 0.0,
            wz_radps: 0.0,
        }
    }
}

/// Point flag: the ray produced no return (range is ignored).
pub const FLAG_NO_RETURN: u16 = 1;
/// Point flag: `ring` and `column` carry the driver's indices.
pub const FLAG_RING_COLUMN_VALID: u16 = 2;

/// One LiDAR ray in the sensor frame, stored as the driver measured it (no xyz round trip).
///
/// Inclination is the polar angle from the sensor's +z axis (π/2 is horizontal), azimuth is
/// `atan2(y, x)` in the sensor frame, both in radians.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("rangegp::ScanPoint")]
#[repr(C)]
pub struct ScanPoint {
    /// Measured range, metres.
    pub range_m: f32,
    /// Polar angle from the sensor's +z axis, radians, in [0, π].
    pub inclination_rad: f32,
    /// Azimuth `atan2(y, x)` in the sensor frame, radians, in [−π, π] or in [0, 2π).
    pub azimuth_rad: f32,
    /// Laser ring index (valid with [`FLAG_RING_COLUMN_VALID`]).
    pub ring: u16,
    /// Firing column index (valid with [`FLAG_RING_COLUMN_VALID`]).
    pub column: u16,
    /// Bit set of `FLAG_*` values; unknown bits are rejected.
    pub flags: u16,
    /// Must be zero.
    pub reserved: u16,
    /// When the ray fired, nanoseconds after the header's `stamp_ns` (0 when the driver does not
    /// say, or deskewed already); at most [`MAX_TIME_OFFSET_NS`].
    pub time_offset_ns: u32,
}

/// Latest a point may fire after its scan's stamp, nanoseconds (one second: a sweep is 50–200 ms).
pub const MAX_TIME_OFFSET_NS: u32 = 1_000_000_000;

impl ScanPoint {
    /// True when the ray produced a return.
    pub fn has_return(&self) -> bool {
        self.flags & FLAG_NO_RETURN == 0
    }
}

/// Publishers the scan service admits (iceoryx2's default of 2 silently limits a robot stack).
pub const SCAN_SERVICE_MAX_PUBLISHERS: usize = 16;
/// Subscribers the scan service admits (the daemon plus tools such as recorders).
pub const SCAN_SERVICE_MAX_SUBSCRIBERS: usize = 4;
/// Samples a subscriber may hold queued before the oldest is overwritten.
pub const SCAN_SERVICE_SUBSCRIBER_BUFFER: usize = 8;
/// Nodes the scan service admits.
pub const SCAN_SERVICE_MAX_NODES: usize = 32;

/// Error opening or creating the iceoryx2 scan service.
pub type ScanServiceError = iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError;

/// The iceoryx2 port factory of a scan service (header + point slice).
pub type ScanService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<
    iceoryx2::prelude::ipc::Service,
    [ScanPoint],
    ScanHeader,
>;

/// A node builder on iceoryx2's configuration: the file iceoryx2 itself would load (project
/// `config/iceoryx2.toml`, then `$HOME/.config/iceoryx2/iceoryx2.toml`, then
/// `/etc/iceoryx2/iceoryx2.toml`) when one exists, else iceoryx2's defaults given explicitly, which
/// is what iceoryx2 falls back to anyway, without its "No config file was loaded" warning at
/// every start of every process.
pub fn node_builder() -> iceoryx2::prelude::NodeBuilder {
    let home = std::env::var_os("HOME").map(std::path::PathBuf::from);
    let candidates = [
        Some(std::path::PathBuf::from("config/iceoryx2.toml")),
        home.map(|h| h.join(".config/iceoryx2/iceoryx2.toml")),
        Some(std::path::PathBuf::from("/etc/iceoryx2/iceoryx2.toml")),
    ];
    let builder = iceoryx2::prelude::NodeBuilder::new();
    if candidates.iter().flatten().any(|p| p.is_file()) {
        builder
    } else {
        builder.config(&iceoryx2::prelude::Config::default())
    }
}

/// Opens (or creates) the scan service `name` with the contract's quality of service, so every
/// publisher and the daemon agree on it whoever comes first.
pub fn open_scan_service(
    node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    name: &iceoryx2::prelude::ServiceName,
) -> Result<ScanService, ScanServiceError> {
    node.service_builder(name)
        .publish_subscribe::<[ScanPoint]>()
        .user_header::<ScanHeader>()
        .max_publishers(SCAN_SERVICE_MAX_PUBLISHERS)
        .max_subscribers(SCAN_SERVICE_MAX_SUBSCRIBERS)
        .subscriber_max_buffer_size(SCAN_SERVICE_SUBSCRIBER_BUFFER)
        .max_nodes(SCAN_SERVICE_MAX_NODES)
        .history_size(0)
        .open_or_create()
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::mem::{align_of, offset_of, size_of};

    #[test]
    fn header_layout_is_the_documented_one() {
        assert_eq!(size_of::<ScanHeader>(), 152);
        assert_eq!(align_of::<ScanHeader>(), 8);
        assert_eq!(offset_of!(ScanHeader, protocol_version), 0);
        assert_eq!(offset_of!(ScanHeader, point_count), 4);
        assert_eq!(offset_of!(ScanHeader, publisher_id), 8);
        assert_eq!(offset_of!(ScanHeader, sequence), 16);
        assert_eq!(offset_of!(ScanHeader, stamp_ns), 24);
        assert_eq!(offset_of!(ScanHeader, px_m), 32);
        assert_eq!(offset_of!(ScanHeader, qx), 56);
        assert_eq!(offset_of!(ScanHeader, qw), 80);
        assert_eq!(offset_of!(ScanHeader, max_range_m), 88);
        assert_eq!(offset_of!(ScanHeader, range_noise_per_m), 96);
        assert_eq!(offset_of!(ScanHeader, vx_mps), 104);
        assert_eq!(offset_of!(ScanHeader, vz_mps), 120);
        assert_eq!(offset_of!(ScanHeader, wx_radps), 128);
        assert_eq!(offset_of!(ScanHeader, wz_radps), 144);
    }

    #[test]
    fn point_layout_is_the_documented_one() {
        assert_eq!(size_of::<ScanPoint>(), 24);
        assert_eq!(align_of::<ScanPoint>(), 4);
        assert_eq!(offset_of!(ScanPoint, range_m), 0);
        assert_eq!(offset_of!(ScanPoint, inclination_rad), 4);
        assert_eq!(offset_of!(ScanPoint, azimuth_rad), 8);
        assert_eq!(offset_of!(ScanPoint, ring), 12);
        assert_eq!(offset_of!(ScanPoint, column), 14);
        assert_eq!(offset_of!(ScanPoint, flags), 16);
        assert_eq!(offset_of!(ScanPoint, reserved), 18);
        assert_eq!(offset_of!(ScanPoint, time_offset_ns), 20);
    }
}
