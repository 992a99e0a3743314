//! Query requests and replies (serde). Every message carries the protocol version; every batch
//! item answers the request item at the same index. Points, rays and views are here; grids and
//! slopes in `grid.rs`, the daemon's counters in `status.rs`, map events and pose corrections in
//! `world.rs`, all re-exported, so that every message is `msg::Name`.

mod grid;
mod status;
mod world;

pub use grid::*;
pub use status::*;
pub use world::*;

use serde::{Deserialize, Serialize};

/// Elevation at map-frame (x, y) points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ElevationRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Query points (x, y) in the map frame, metres.
    pub points: Vec<[f64; 2]>,
}

/// Where an answer came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// A local range map of a recent scan.
    Window,
    /// The aggregate map of everything seen.
    Aggregate,
    /// No map covers the query: no value is given.
    None,
}

/// Why a point got no value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Refusal {
    /// No map saw the point (outside every field of view, or in a shadow).
    Unobserved,
    /// A map answered, but with σ above the daemon's bound (`query.max_sigma_m`): it knows too
    /// little there to give a number.
    TooUncertain,
}

/// How much data stands behind an answer, by the distance from the answered point to the
/// nearest datum of the answering map (a training return's footprint for a window map, a fused
/// cell's centre for the aggregate), in units of that map's correlation length ℓ.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Provenance {
    /// Within 0.3 ℓ of a datum (kernel correlation ≥ 0.9): the point lies in data a scan measured.
    Observed,
    /// Within ℓ of a datum: between data, within the model's correlation length.
    Interpolated,
    /// Farther than ℓ from every datum: the model's smooth continuation, not data.
    Extrapolated,
    /// No answer.
    None,
}

/// One elevation answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ElevationItem {
    /// Predicted surface height, metres (absent when `source` is `none`).
    pub z_m: Option<f64>,
    /// Variance of `z_m`, square metres (latent surface, sensor noise excluded).
    pub z_var_m2: Option<f64>,
    /// Per-axis standard deviations (x, y, z) of the surface point the answering sensor's ray
    /// meets there, metres (seed 000 Table I: s_r |w_x|, s_r |w_y|, s_r |w_z| along the ray's
    /// unit direction w; calibrated like `z_var_m2`). The aggregate, a height field, gives
    /// (0, 0, σ_z).
    pub point_sigma_m: Option<[f64; 3]>,
    /// Which map answered.
    pub source: Source,
    /// How much data stands behind the answer (`none` without one).
    pub provenance: Provenance,
    /// Why there is no value (`None` when there is one).
    pub refusal: Option<Refusal>,
}

/// Elevation answers, one per request point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ElevationReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Answers in request order.
    pub items: Vec<ElevationItem>,
}

/// Elevation variance only at map-frame (x, y) points (the cheap path for planners' cost maps).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VarianceRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Query points (x, y) in the map frame, metres.
    pub points: Vec<[f64; 2]>,
}

/// One variance answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VarianceItem {
    /// Variance of the surface height, square metres (absent when `source` is `none`).
    pub z_var_m2: Option<f64>,
    /// Which map answered.
    pub source: Source,
    /// Why there is no value (`None` when there is one).
    pub refusal: Option<Refusal>,
}

/// Variance answers, one per request point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VarianceReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Answers in request order.
    pub items: Vec<VarianceItem>,
}

/// One ray to cast through the map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ray {
    /// Ray origin in the map frame, metres.
    pub origin_m: [f64; 3],
    /// Direction in the map frame (normalised by the server; must be non-zero).
    pub direction: [f64; 3],
    /// Cast no further than this, metres.
    pub max_range_m: f64,
}

/// Rays to cast.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RayRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Rays in the map frame.
    pub rays: Vec<Ray>,
}

/// One ray answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RayItem {
    /// Expected distance from the origin to the surface, metres (absent when no hit is predicted).
    pub range_m: Option<f64>,
    /// Variance of `range_m`, square metres.
    pub range_var_m2: Option<f64>,
    /// Probability that the ray meets the surface before `max_range_m`; `None` when no map knows
    /// anything along the ray (not 0: unknown is not free).
    pub hit_probability: Option<f64>,
    /// Expected hit point in the map frame, metres.
    pub hit_point_m: Option<[f64; 3]>,
    /// Per-axis standard deviations (x, y, z) of the hit point, metres: σ_range |d| along the
    /// ray's unit direction d.
    pub hit_sigma_m: Option<[f64; 3]>,
    /// Which map answered.
    pub source: Source,
    /// How much data stands behind the hit (`none` without a hit).
    pub provenance: Provenance,
}

/// Ray answers, one per request ray.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RayReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Answers in request order.
    pub items: Vec<RayItem>,
}

/// How a view's pixels look out of the sensor (the sensor frame: x forward, y left, z up).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Camera {
    /// A spinning LiDAR: one row per ring (its elevation above the sensor's xy plane, radians,
    /// top ring first), `columns` azimuths evenly over a full turn starting straight ahead and
    /// turning left.
    Lidar {
        /// Ring elevations, radians.
        ring_elevations_rad: Vec<f64>,
        /// Azimuths per ring.
        columns: u32,
        /// Longest range, metres.
        max_range_m: f64,
    },
    /// A pinhole camera looking along the sensor's x axis, square pixels.
    Pinhole {
        /// Pixels across.
        width: u32,
        /// Pixels down.
        height: u32,
        /// Horizontal field of view, radians (in (0, π)).
        hfov_rad: f64,
        /// Longest range, metres.
        max_range_m: f64,
    },
}

impl Camera {
    /// Pixels of the image (rows × columns, without overflow): what a daemon checks against its
    /// batch limit before it builds a ray for any of them.
    pub fn pixels(&self) -> u64 {
        match self {
            Self::Lidar {
                ring_elevations_rad,
                columns,
                ..
            } => (ring_elevations_rad.len() as u64).saturating_mul(u64::from(*columns)),
            Self::Pinhole { width, height, .. } => u64::from(*width) * u64::from(*height),
        }
    }
}

/// A range image of the map as a sensor at a pose would see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Sensor position in the map frame, metres.
    pub position_m: [f64; 3],
    /// Sensor orientation in the map frame, unit quaternion (x, y, z, w).
    pub orientation_xyzw: [f64; 4],
    /// The sensor's pixels.
    pub camera: Camera,
}

/// The answer to a [`ViewRequest`]: `rows × cols` pixels, row-major from the top row (the top
/// ring, or the image's top), each the ray answer along that pixel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Pixel rows.
    pub rows: u32,
    /// Pixel columns.
    pub cols: u32,
    /// Expected range per pixel, metres (`None`: no hit predicted, or nothing known).
    pub range_m: Vec<Option<f32>>,
    /// σ of the range per pixel, metres.
    pub sigma_m: Vec<Option<f32>>,
    /// Probability of a hit before the max range per pixel (`None`: nothing known).
    pub hit_probability: Vec<Option<f32>>,
    /// Which map answered each pixel.
    pub source: Vec<Source>,
    /// How much data stands behind each pixel's hit.
    pub provenance: Vec<Provenance>,
}

/// Machine-readable error class of a failed query.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The request's protocol version is not the daemon's.
    UnsupportedVersion,
    /// The payload could not be decoded as the expected request.
    MalformedRequest,
    /// The batch exceeds the configured limit.
    BatchTooLarge,
    /// A value in the request is out of its domain (non-finite, zero direction, ...).
    InvalidArgument,
    /// The daemon has no map yet.
    NoMap,
    /// The daemon is shedding load; retry later.
    Overloaded,
    /// A bug or resource failure on the daemon's side.
    Internal,
}

/// Payload of every `reply_err`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Error class.
    pub code: ErrorCode,
    /// Human-readable detail.
    pub message: String,
}
