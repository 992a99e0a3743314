//! Query requests and replies (serde). Every message carries the protocol version; every batch
//! item answers the request item at the same index.

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

/// Elevation and variance layers over a regular grid (grid_map style), and the planner layers
/// derived from them when asked for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Lower-left corner (x, y) of the box in the map frame, metres.
    pub min_m: [f64; 2],
    /// Upper-right corner (x, y), metres; each coordinate above `min_m`'s.
    pub max_m: [f64; 2],
    /// Cell side, metres (positive; at most the robot's footprint radius when a derived layer
    /// is asked for).
    pub resolution_m: f64,
    /// Derived layers wanted in [`GridReply::layers`], in this order (elevation and variance
    /// always come); empty: none.
    #[serde(default)]
    pub layers: Vec<Layer>,
    /// The robot the risk and cost layers are for; `None`: the daemon's configured one.
    #[serde(default)]
    pub robot: Option<RobotModel>,
}

/// A layer derived from the map over a robot's footprint (a disc of `footprint_radius_m` around
/// each cell centre, sampled at the grid's resolution), each value with the σ the GP gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// Slope angle of the plane fitted over the footprint, radians.
    Slope,
    /// σ of `slope`, radians.
    SlopeSigma,
    /// Direction the slope faces (downhill), radians counter-clockwise from +x.
    Aspect,
    /// RMS deviation of the surface from the footprint's plane, metres.
    Roughness,
    /// σ of `roughness`, metres.
    RoughnessSigma,
    /// Largest height difference across the footprint, metres.
    Step,
    /// σ of `step`, metres.
    StepSigma,
    /// P(slope > the robot's max slope).
    SlopeRisk,
    /// P(step > the robot's max step).
    StepRisk,
    /// Share of the footprint unknown: no map answers, or the answer's σ is wider than the
    /// robot's max step.
    UnknownRisk,
    /// P(the terrain stops the robot): P(slope or step over its limit), the larger of the two
    /// (both follow from the same height errors, so they rise and fall together).
    Risk,
    /// Traversability cost in [0, 1]: `risk` and `unknown_risk` combined as independent,
    /// 1 − (1 − risk)(1 − unknown).
    TraversalCost,
    /// The traversal cost as a ROS costmap value in [`GridReply::costmap`] (0–100, 100 lethal,
    /// −1 unknown).
    Cost,
}

impl Layer {
    /// Every layer, in wire order.
    pub const ALL: [Layer; 13] = [
        Layer::Slope,
        Layer::SlopeSigma,
        Layer::Aspect,
        Layer::Roughness,
        Layer::RoughnessSigma,
        Layer::Step,
        Layer::StepSigma,
        Layer::SlopeRisk,
        Layer::StepRisk,
        Layer::UnknownRisk,
        Layer::Risk,
        Layer::TraversalCost,
        Layer::Cost,
    ];

    /// The layer's wire name (`slope_sigma`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            Layer::Slope => "slope",
            Layer::SlopeSigma => "slope_sigma",
            Layer::Aspect => "aspect",
            Layer::Roughness => "roughness",
            Layer::RoughnessSigma => "roughness_sigma",
            Layer::Step => "step",
            Layer::StepSigma => "step_sigma",
            Layer::SlopeRisk => "slope_risk",
            Layer::StepRisk => "step_risk",
            Layer::UnknownRisk => "unknown_risk",
            Layer::Risk => "risk",
            Layer::TraversalCost => "traversal_cost",
            Layer::Cost => "cost",
        }
    }

    /// The layer named `name` ([`Layer::as_str`]).
    pub fn parse(name: &str) -> Option<Layer> {
        Layer::ALL.into_iter().find(|l| l.as_str() == name)
    }
}

/// What the risk and cost layers judge by: the robot's footprint and limits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RobotModel {
    /// Radius of the disc the robot stands on, metres (slope, roughness and step are taken over it).
    pub footprint_radius_m: f64,
    /// Steepest slope the robot climbs, degrees.
    pub max_slope_deg: f64,
    /// Highest step the robot climbs, metres.
    pub max_step_m: f64,
    /// Traversal cost at and above which a cell is lethal (costmap 100).
    pub lethal_risk: f64,
}

impl RobotModel {
    /// Why this model cannot be used (`None`: it can): every field finite, the radius and
    /// limits positive, the slope below 90° and the lethal risk in (0, 1].
    pub fn problem(&self) -> Option<&'static str> {
        if !(self.footprint_radius_m.is_finite() && self.footprint_radius_m > 0.0) {
            Some("footprint_radius_m must be finite and positive")
        } else if !(self.max_slope_deg > 0.0 && self.max_slope_deg < 90.0) {
            Some("max_slope_deg must be in (0, 90)")
        } else if !(self.max_step_m.is_finite() && self.max_step_m > 0.0) {
            Some("max_step_m must be finite and positive")
        } else if !(self.lethal_risk > 0.0 && self.lethal_risk <= 1.0) {
            Some("lethal_risk must be in (0, 1]")
        } else {
            None
        }
    }
}

/// One derived layer of a [`GridReply`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridLayer {
    /// Which layer.
    pub layer: Layer,
    /// One value per cell, in the reply's cell order; `None` where it is unknown.
    pub values: Vec<Option<f32>>,
}

/// The layers of a [`GridRequest`]: `cols × rows` cells, row-major from the lower-left cell,
/// each value taken at its cell's centre; `None` where no map observed the cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Centre (x, y) of cell (0, 0), metres.
    pub origin_m: [f64; 2],
    /// Cell side, metres.
    pub resolution_m: f64,
    /// Cells along x.
    pub cols: u32,
    /// Cells along y.
    pub rows: u32,
    /// Surface height per cell, metres.
    pub elevation_m: Vec<Option<f32>>,
    /// Variance of the height per cell, square metres.
    pub variance_m2: Vec<Option<f32>>,
    /// How much data stands behind each cell's answer.
    pub provenance: Vec<Provenance>,
    /// The derived layers asked for, in request order (`cost` comes as [`GridReply::costmap`]).
    pub layers: Vec<GridLayer>,
    /// ROS `nav_msgs/OccupancyGrid` values when `cost` was asked for (else empty): 0 free to
    /// 100 lethal (traversal cost × 100, 100 at and above the robot's lethal risk), −1 unknown.
    pub costmap: Vec<i8>,
    /// The robot the risk and cost layers judged by.
    pub robot: RobotModel,
}

impl GridRequest {
    /// Cells along x and y the box holds at its resolution (`ceil` of extent / resolution), or
    /// `None` when the box or resolution is not a finite, positive size.
    pub fn shape(&self) -> Option<(u64, u64)> {
        let ext = [self.max_m[0] - self.min_m[0], self.max_m[1] - self.min_m[1]];
        let ok = self.resolution_m.is_finite()
            && self.resolution_m > 0.0
            && ext.iter().all(|e| e.is_finite() && *e > 0.0);
        let cells = |e: f64| (e / self.resolution_m).ceil();
        let (c, r) = (cells(ext[0]), cells(ext[1]));
        (ok && c < 1e9 && r < 1e9).then_some((c as u64, r as u64))
    }
}

impl GridReply {
    /// Centre (x, y) of cell (col, row), metres.
    pub fn centre(&self, col: u32, row: u32) -> [f64; 2] {
        [
            self.origin_m[0] + col as f64 * self.resolution_m,
            self.origin_m[1] + row as f64 * self.resolution_m,
        ]
    }

    /// The values of `layer`, when the reply carries it.
    pub fn layer(&self, layer: Layer) -> Option<&[Option<f32>]> {
        self.layers
            .iter()
            .find(|l| l.layer == layer)
            .map(|l| l.values.as_slice())
    }
}

/// Slope at map-frame (x, y) points: the `slope` layers of a grid cell centred on each point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// Query points (x, y) in the map frame, metres.
    pub points: Vec<[f64; 2]>,
    /// The robot whose footprint the slope is taken over; `None`: the daemon's configured one.
    #[serde(default)]
    pub robot: Option<RobotModel>,
}

/// One slope answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeItem {
    /// Slope angle of the footprint's plane, radians (absent when unknown).
    pub slope_rad: Option<f64>,
    /// σ of `slope_rad`, radians.
    pub slope_sigma_rad: Option<f64>,
    /// Direction the slope faces (downhill), radians counter-clockwise from +x.
    pub aspect_rad: Option<f64>,
    /// Unit surface normal (x, y, z) of the footprint's plane.
    pub normal: Option<[f64; 3]>,
    /// P(slope > the robot's max slope).
    pub slope_risk: Option<f64>,
    /// Why there is no value (`None` when there is one).
    pub refusal: Option<Refusal>,
}

/// Slope answers, one per request point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlopeReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Grid resolution the footprint was sampled at, metres (a grid at this resolution with a
    /// cell centred on the point gives the same values).
    pub resolution_m: f64,
    /// The robot the slope was judged for.
    pub robot: RobotModel,
    /// Answers in request order.
    pub items: Vec<SlopeItem>,
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

/// Ask for the daemon's counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
}

/// How many scans were rejected for one reason.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RejectionCount {
    /// Stable snake_case reason (see `docs/PROTOCOL.md`).
    pub reason: String,
    /// Scans rejected for it since start.
    pub count: u64,
}

/// Kernel hyperparameters in use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HyperparametersInfo {
    /// Kernel name.
    pub kernel: String,
    /// Kernel variance σ², square metres.
    pub variance: f64,
    /// Length scale on the range sphere, metres of chord.
    pub length_scale: f64,
    /// Noise variance added to every training ray on top of the sensor model, square metres.
    pub nugget: f64,
}

/// Percentiles of one latency over the daemon's most recent samples (a bounded ring).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LatencySummary {
    /// Samples since start.
    pub count: u64,
    /// Median of the recent samples, milliseconds.
    pub p50_ms: f64,
    /// 90th percentile, milliseconds.
    pub p90_ms: f64,
    /// 99th percentile, milliseconds.
    pub p99_ms: f64,
    /// Largest recent sample, milliseconds.
    pub max_ms: f64,
}

/// Server-side query latencies (receipt by a worker to reply sent), one per query kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct QueryLatencies {
    /// `query/elevation`.
    pub elevation: LatencySummary,
    /// `query/variance`.
    pub variance: LatencySummary,
    /// `query/ray`.
    pub ray: LatencySummary,
    /// `query/grid`.
    pub grid: LatencySummary,
    /// `query/view`.
    pub view: LatencySummary,
    /// `query/slope`.
    pub slope: LatencySummary,
    /// `query/sources`.
    pub sources: LatencySummary,
    /// `status`.
    pub status: LatencySummary,
}

/// The scan intake: whether it is subscribed, and what its bookkeeping did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct IngestInfo {
    /// Whether the daemon holds its iceoryx2 subscriber (false while it retries with back-off).
    pub connected: bool,
    /// Why the last attempt to subscribe failed (`None` once subscribed).
    pub error: Option<String>,
    /// Failed attempts to subscribe since start.
    pub retries: u64,
    /// Sources whose sequence number jumped beyond the restart window (counted anew, not
    /// locked out).
    pub publisher_restarts: u64,
    /// Publishers followed to a new place after agreeing scans (a relocalisation).
    pub relocations: u64,
}

/// The world aggregate's size and counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct AggregateInfo {
    /// Whether the daemon folds scans into an aggregate.
    pub enabled: bool,
    /// Fused cells held now.
    pub cells: u64,
    /// Fitted tiles held now.
    pub tiles: u64,
    /// Radius around the newest sensor position beyond which tiles are evicted, metres.
    pub radius_m: f64,
    /// Scans folded in since start.
    pub inserts: u64,
    /// Fitted scans displaced from the aggregate's queue, not fused (the window still has them).
    pub skipped: u64,
    /// Inserts that failed (the aggregate kept its previous state).
    pub failed: u64,
    /// Tiles evicted for being beyond `radius_m`.
    pub evicted_tiles: u64,
    /// Reach each scan is fused out to now, metres (shorter than 10 m when a fast sensor would
    /// otherwise outrun `aggregate.cpu_share`; 0 before the first insert).
    pub reach_m: f64,
    /// Tiles written to the site map on disk when they left the radius (checkpoints on).
    pub paged_out: u64,
    /// Tiles read back from the site map when the robot returned.
    pub paged_in: u64,
    /// Tile pages that could not be written or read.
    pub page_failures: u64,
    /// Fused scans whose cells the ledger keeps: what a pose correction can move.
    pub ledger_scans: u64,
    /// Memory the ledger holds, MiB (`aggregate.ledger_mib` bounds it).
    pub ledger_mb: f64,
    /// Cells replaced by scans that disagreed with them (published as change events).
    pub changed_cells: u64,
}

/// The daemon's state and counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Map id served.
    pub map_id: String,
    /// Seconds since the daemon started.
    pub uptime_s: f64,
    /// Scans taken from shared memory.
    pub scans_received: u64,
    /// Scans that passed validation and were fitted into the window.
    pub scans_accepted: u64,
    /// Scans rejected (sum over reasons).
    pub scans_rejected: u64,
    /// Rejections by reason (every reason listed, zeros included).
    pub rejections: Vec<RejectionCount>,
    /// Valid scans dropped because fitting fell behind (newest wins).
    pub scans_skipped: u64,
    /// Online hyperparameter updates applied since start.
    pub hyperparameter_updates: u64,
    /// Local experts whose Cholesky factorisation needed diagonal jitter since start.
    pub jittered_tiles: u64,
    /// Scans lost in transport (sequence numbers that never arrived), summed over publishers.
    pub sequence_gaps: u64,
    /// The scan intake.
    pub ingest: IngestInfo,
    /// Local maps in the window now.
    pub window_len: u32,
    /// Window capacity.
    pub window_capacity: u32,
    /// The world aggregate.
    pub aggregate: AggregateInfo,
    /// Pose corrections applied since start.
    pub corrections: u64,
    /// Hyperparameters in use.
    pub hyperparameters: HyperparametersInfo,
    /// Fit of one scan into its local map.
    pub fit_ms: LatencySummary,
    /// Scan taken from shared memory to its map answering queries.
    pub scan_to_queryable_ms: LatencySummary,
    /// One aggregate insert (cells, tile refits, eviction).
    pub aggregate_insert_ms: LatencySummary,
    /// Query handling per kind.
    pub query_ms: QueryLatencies,
    /// Queries answered successfully.
    pub queries_ok: u64,
    /// Queries answered with an error.
    pub queries_failed: u64,
    /// Batch queries answered `overloaded` after waiting past the queue deadline.
    pub queries_expired: u64,
    /// Replies dropped because too many were being sent at once (a client not reading).
    pub replies_dropped: u64,
    /// Resident set size of the daemon process, MiB (`None` where the OS does not say).
    pub rss_mb: Option<f64>,
    /// The daemon's part in a fleet: tiles published (robot) or assembled (site).
    pub fleet: crate::fleet::FleetInfo,
}

/// Published on `rangegp/<map>/events/map` each time a scan's map starts answering queries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapUpdate {
    /// Protocol version of the event.
    pub version: u32,
    /// Publisher of the scan.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Its acquisition time, ns since the Unix epoch.
    pub stamp_ns: u64,
    /// Scan taken from shared memory to queryable, milliseconds (daemon clock).
    pub latency_ms: f64,
    /// Local maps in the window now.
    pub window_len: u32,
}

/// One aggregate cell replaced because new scans disagreed with it beyond both σ.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChangedCell {
    /// The cell's centre in the map frame, metres.
    pub x_m: f64,
    /// The cell's centre y, metres.
    pub y_m: f64,
    /// Height before, metres.
    pub old_z_m: f64,
    /// Its σ, metres.
    pub old_sigma_m: f64,
    /// Height now, metres (`None`: the cell left the map: rays passed below what it held and
    /// the scan has no height of its own there; the next scan that does fills it).
    pub new_z_m: Option<f64>,
    /// Its σ, metres.
    pub new_sigma_m: Option<f64>,
}

/// Published on `rangegp/<map>/events/change` when a scan's evidence replaced aggregate cells
/// (something appeared, left or moved there).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeEvent {
    /// Protocol version of the event.
    pub version: u32,
    /// Publisher of the scan that confirmed the change.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Its acquisition time, ns since the Unix epoch.
    pub stamp_ns: u64,
    /// The cell side, metres.
    pub cell_m: f64,
    /// The cells replaced.
    pub cells: Vec<ChangedCell>,
}

/// A rigid transform of the map frame: `p ↦ rotation · p + translation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rigid {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation, unit quaternion (x, y, z, w).
    pub rotation_xyzw: [f64; 4],
}

/// One correction of past scans' poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseCorrection {
    /// The corrected pose of one scan, named by its publisher and sequence.
    Scan {
        /// Publisher id of the scan.
        publisher_id: u64,
        /// Its sequence number.
        sequence: u64,
        /// The sensor's corrected pose in the map frame.
        pose: Rigid,
    },
    /// A loop closure or a relocalisation: `transform` applied on the left (in the map frame)
    /// to the pose of every scan taken in `[from_stamp_ns, until_stamp_ns]`, of one publisher
    /// or of all.
    Transform {
        /// Only this publisher's scans (`None`: every publisher's).
        publisher_id: Option<u64>,
        /// First acquisition time moved, ns since the Unix epoch.
        from_stamp_ns: u64,
        /// Last acquisition time moved, ns (`u64::MAX`: every scan since `from_stamp_ns`).
        until_stamp_ns: u64,
        /// The correction: a pose `P` becomes `transform · P`.
        transform: Rigid,
    },
}

/// Corrected poses for past scans, applied in order (`rangegp/<map>/corrections`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CorrectionRequest {
    /// Must equal [`crate::PROTOCOL_VERSION`].
    pub version: u32,
    /// The corrections.
    pub corrections: Vec<PoseCorrection>,
}

/// What a correction changed; sent once queries see the corrected map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CorrectionReply {
    /// Protocol version of the reply.
    pub version: u32,
    /// Corrections applied since the daemon started, this one included.
    pub generation: u64,
    /// Window maps moved.
    pub window_maps_moved: u32,
    /// Scans moved in the aggregate.
    pub aggregate_scans_moved: u32,
    /// Scans the corrections name that the aggregate fused but no longer keeps the data to move
    /// (older than its ledger, or fused before a restart): their cells stay where they were.
    pub not_correctable: u32,
    /// Aggregate cells whose height changed, added or removed (in memory and on disk).
    pub cells_changed: u64,
    /// Aggregate tiles refitted in memory.
    pub tiles_refitted: u32,
    /// Tiles rewritten in the site map on disk.
    pub pages_rewritten: u32,
    /// From the request's arrival to the corrected map answering queries, milliseconds.
    pub apply_ms: f64,
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

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(min_m: [f64; 2], max_m: [f64; 2], resolution_m: f64) -> GridRequest {
        GridRequest {
            version: crate::PROTOCOL_VERSION,
            min_m,
            max_m,
            resolution_m,
            layers: Vec::new(),
            robot: None,
        }
    }

    #[test]
    fn layer_names_round_trip() {
        for layer in Layer::ALL {
            assert_eq!(Layer::parse(layer.as_str()), Some(layer));
            let json = serde_json::to_string(&layer).expect("a layer encodes");
            assert_eq!(json, format!("\"{}\"", layer.as_str()));
        }
        assert_eq!(Layer::parse("slopes"), None);
    }

    #[test]
    fn grid_shape_rounds_up_and_refuses_empty_or_non_finite_boxes() {
        assert_eq!(grid([0.0, 0.0], [10.0, 5.0], 0.5).shape(), Some((20, 10)));
        assert_eq!(grid([0.0, 0.0], [10.1, 5.0], 0.5).shape(), Some((21, 10)));
        assert_eq!(grid([0.0, 0.0], [0.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([1.0, 0.0], [0.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([0.0, 0.0], [10.0, 5.0], 0.0).shape(), None);
        assert_eq!(grid([0.0, f64::NAN], [10.0, 5.0], 0.5).shape(), None);
        assert_eq!(grid([0.0, 0.0], [1e300, 5.0], 1e-300).shape(), None);
    }
}
