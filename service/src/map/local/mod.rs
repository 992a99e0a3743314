//! The local range map of one scan: range as a GP over (inclination, azimuth) (seed 000 §III-A).

mod surface;
mod training;

pub use training::{embedding_of, hyper_sample, HyperSample};
use training::{ground_of, index_of, prior_of, training_rays, training_returns};

use super::data_index::DataIndex;
use super::embedding::Embedding;
use super::fov::FieldOfView;
use super::prior::Prior;
use super::root;
use super::tiles::{TiledGp, Tiling};
use crate::gp::{sphere, CholeskyError, JitterPolicy, Kernel};
use crate::scan::ScanInput;
use nalgebra::{Isometry3, Vector3};
use rangegp_proto::msg::Provenance;
use std::sync::Arc;
use thiserror::Error;

/// Which prior mean to build a map with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PriorKind {
    /// Flat ground this far below the sensor, metres.
    FlatGround {
        /// Sensor height above ground, metres.
        sensor_height_m: f64,
    },
    /// Constant range, metres.
    ConstantRange {
        /// The constant, metres.
        range_m: f64,
    },
}

/// The quantity the GP models along each ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RangeTarget {
    /// Range (seed 000).
    #[default]
    Range,
    /// Inverse range 1/r: every plane is linear in the ray direction (1/r = n·u / d), so walls,
    /// roofs and grazing views that bend the range steeply stay straight (docs/ARCHITECTURE.md).
    InverseRange,
}

/// Smallest inverse range a prediction is clamped to, 1/m (a 1 km ray).
const MIN_INVERSE_RANGE: f64 = 1e-3;

impl RangeTarget {
    /// The modelled value of range `r`.
    fn of(self, r: f64) -> f64 {
        match self {
            RangeTarget::Range => r,
            RangeTarget::InverseRange => 1.0 / r,
        }
    }
    /// Range of a modelled value and the factor d r / d value (for the delta method).
    fn back(self, v: f64) -> (f64, f64) {
        match self {
            RangeTarget::Range => (v, 1.0),
            RangeTarget::InverseRange => {
                let r = 1.0 / v.max(MIN_INVERSE_RANGE);
                (r, r * r)
            }
        }
    }
}

/// Everything needed to fit a local map besides the scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapParams {
    /// Kernel on the range sphere.
    pub kernel: Kernel,
    /// Kernel inputs are the prior's expected hit points, capped at this range (the range-sphere
    /// radius under the constant-range prior), metres; `None`: the scan's maximum range.
    pub sphere_radius_m: Option<f64>,
    /// Noise variance added to every training ray on top of the sensor model, m².
    pub nugget_m2: f64,
    /// At most this many rays of a scan train its experts (an even stride over the scan).
    pub max_training_rays: usize,
    /// How the scan is cut into local experts.
    pub tiling: Tiling,
    /// Prior mean.
    pub prior: PriorKind,
    /// What the GP models along a ray.
    pub target: RangeTarget,
    /// Cholesky jitter policy.
    pub jitter: JitterPolicy,
    /// How each expert's variance is calibrated to its own data.
    pub variance_calibration: crate::map::tiles::VarianceCalibration,
    /// Keep the training returns and index where they lie ([`LocalRangeMap::data`]), so that
    /// answers carry their distance from data (what the unseen relief needs; without it every
    /// answer counts as [`super::data_index::MAX_DATA_DISTANCE_M`] from data, at no cost).
    pub index_data: bool,
    /// End the view half a ring above the scan's highest return in each azimuth
    /// ([`FieldOfView::covering`]; `gp.view_ceiling`).
    pub view_ceiling: bool,
}

/// Why a scan could not be turned into a map.
#[derive(Debug, Error, PartialEq)]
pub enum FitError {
    /// The scan has no returned ray.
    #[error("scan has no returned rays")]
    NoReturns,
    /// The covariance matrix could not be factored.
    #[error(transparent)]
    Cholesky(#[from] CholeskyError),
}

/// A predicted surface height with its variance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeightEstimate {
    /// Height, metres.
    pub z: f64,
    /// Variance, m² (delta method through the range variance).
    pub var: f64,
    /// How squarely the sensor's rays meet the surface there, as a fraction of the angle at
    /// which they would meet flat ground from the same distance (infinite where not measured):
    /// small near the edge of a shadow, where the surface is the map's smoothing of a jump.
    pub grazing: f64,
    /// Per-axis σ (x, y, z) of the surface point along the sensor's ray there, metres (seed 000
    /// Table I); a height field's is (0, 0, σ_z).
    pub point_sd: [f64; 3],
    /// Horizontal distance from the answer to the nearest datum of the map that gave it, metres
    /// (0 for a height field's fused cells; the search's cap for a map that keeps no index): what
    /// the GP's angular σ does not see.
    pub data_m: f64,
    /// How far the ground at the answer lies above the ground under the sensor that gave it,
    /// over its horizontal distance from that sensor (the grade of the line between the two; 0
    /// for a height field's): ground off the robot's level errs more than level ground at the
    /// same range, which the σ calibration tells apart (docs/EVALUATION.md "Calibration", step
    /// 15).
    pub rise: f64,
    /// The answer's height less the height of its map's data nearest it, metres (0 for a
    /// height field's): an answer that moved far from what was measured beside it may be off
    /// by as much, which the σ calibration weighs by range (docs/EVALUATION.md "Calibration",
    /// step 16).
    pub departure: f64,
}

/// A predicted hit along a ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayEstimate {
    /// Expected distance to the surface, metres (`None`: no crossing before the max range).
    pub range: Option<f64>,
    /// Variance of `range`, m².
    pub range_var: Option<f64>,
    /// Probability that the surface is met before the max range.
    pub hit_probability: f64,
    /// How much data stands behind the hit (`None` without a hit).
    pub provenance: Provenance,
}

/// Within this fraction of the correlation length of a datum, an answer is `observed`: a
/// Matérn-3/2 kernel correlates it with that datum at 0.9 or more.
pub const OBSERVED_FRACTION: f64 = 0.3;

/// The provenance of an answer `distance_m` from the nearest datum of a model whose
/// correlation length is `length_m`: observed within [`OBSERVED_FRACTION`] of it, interpolated
/// within it, extrapolated beyond.
pub fn provenance_of(distance_m: f64, length_m: f64) -> Provenance {
    if distance_m <= OBSERVED_FRACTION * length_m {
        Provenance::Observed
    } else if distance_m <= length_m {
        Provenance::Interpolated
    } else {
        Provenance::Extrapolated
    }
}

/// One scan's range GP, placed in the map frame by the scan's pose.
#[derive(Debug, Clone)]
pub struct LocalRangeMap {
    /// Publisher of the scan.
    pub publisher_id: u64,
    /// Sequence number of the scan.
    pub sequence: u64,
    /// Acquisition time, ns.
    pub stamp_ns: u64,
    pose: Isometry3<f64>,
    /// Angle between the sensor's z axis and the map's, radians (bounds every vertical search).
    tilt: f64,
    prior: Prior,
    target: RangeTarget,
    max_range: f64,
    fov: FieldOfView,
    // Shared: a corrected pose re-anchors a map without copying its experts.
    gp: Arc<TiledGp>,
    /// Pose corrections this map's pose reflects (see `map::correction`).
    generation: u64,
    /// The kernel's length scale, kernel-input metres (what provenance is graded against).
    length_scale: f64,
    /// The training returns in the sensor's frame (a corrected pose re-indexes them).
    returns: Arc<Vec<[f32; 3]>>,
    /// Where the training returns lie on the map's ground, for [`HeightEstimate::data_m`].
    data: Arc<DataIndex>,
    /// The ground under the robot in the sensor's frame ([`training::ground_of`]), for
    /// [`HeightEstimate::rise`].
    ground: Option<Vector3<f64>>,
}

/// Angle between a sensor's z axis and the map's, radians: how far a pose leans from level.
pub fn tilt_of(pose: &Isometry3<f64>) -> f64 {
    (pose.rotation * Vector3::z()).z.clamp(-1.0, 1.0).acos()
}

impl LocalRangeMap {
    /// Fits the range GP of `scan` (seed 000 eqs. 9–10 with a heteroscedastic diagonal).
    pub fn fit(scan: &ScanInput, params: &MapParams) -> Result<Self, FitError> {
        if scan.rays.is_empty() {
            return Err(FitError::NoReturns);
        }
        let prior = prior_of(scan, params);
        let train = training_rays(scan, &prior, params, params.max_training_rays);
        let mut gp = TiledGp::fit(
            &train,
            params.kernel,
            Embedding::new(prior, params.sphere_radius_m.unwrap_or(scan.max_range_m)),
            params.tiling,
            params.jitter,
        )?;
        gp.calibrate(params.variance_calibration);
        let angles: Vec<(f64, f64)> = scan.rays.iter().map(|r| (r.inclination, r.azimuth)).collect();
        let returns: Vec<[f32; 3]> = if params.index_data {
            training_returns(scan, params.max_training_rays)
                .map(|p| [p.x as f32, p.y as f32, p.z as f32])
                .collect()
        } else {
            Vec::new()
        };
        Ok(Self {
            publisher_id: scan.publisher_id,
            sequence: scan.sequence,
            stamp_ns: scan.stamp_ns,
            pose: scan.pose,
            tilt: tilt_of(&scan.pose),
            prior,
            target: params.target,
            max_range: scan.max_range_m,
            fov: FieldOfView::covering(&angles, 0.25f64.to_radians(), params.view_ceiling),
            gp: Arc::new(gp),
            generation: 0,
            length_scale: params.kernel.length_scale,
            data: Arc::new(index_of(&returns, &scan.pose)),
            returns: Arc::new(returns),
            ground: ground_of(scan),
        })
    }

    /// The same map placed at a corrected sensor pose, reflecting `generation` corrections: the
    /// range GP lives in the sensor's frame, so a new pose moves the whole map exactly.
    pub fn reanchored(&self, pose: Isometry3<f64>, generation: u64) -> Self {
        Self {
            pose,
            tilt: tilt_of(&pose),
            generation,
            data: Arc::new(index_of(&self.returns, &pose)),
            ..self.clone()
        }
    }

    /// The sensor's pose in the map frame.
    pub fn pose(&self) -> &Isometry3<f64> {
        &self.pose
    }

    /// Pose corrections this map's pose reflects.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// The same map marked as reflecting `generation` corrections (none of which named it).
    pub fn with_generation(mut self, generation: u64) -> Self {
        self.generation = generation;
        self
    }

    /// Where this map's training returns lie in the map frame.
    pub fn data(&self) -> &DataIndex {
        &self.data
    }

    /// Height of the ground under the robot in the map frame, as the scan's nearest returns show
    /// it (`None`: the scan had none).
    pub fn ground_z(&self) -> Option<f64> {
        self.ground.map(|g| (self.pose * nalgebra::Point3::from(g)).z)
    }

    /// Sensor position in the map frame.
    pub fn sensor_position(&self) -> Vector3<f64> {
        self.pose.translation.vector
    }

    /// Sensor maximum range, metres.
    pub fn max_range(&self) -> f64 {
        self.max_range
    }

    /// Training rays over all experts (rays in tile overlaps counted once per tile).
    pub fn training_rays(&self) -> usize {
        self.gp.training_rays()
    }

    /// Local experts (tiles) of this map.
    pub fn tiles(&self) -> usize {
        self.gp.tiles()
    }

    /// Predicted range mean and latent variance along the sensor-frame direction (θ, φ).
    pub fn predict_range(&self, inclination: f64, azimuth: f64) -> (f64, f64) {
        let residual = self.gp.mean_variance(inclination, azimuth);
        self.to_range(inclination, azimuth, residual)
    }

    /// Range mean and variance of the GP's residual mean and variance along (θ, φ).
    fn to_range(&self, inclination: f64, azimuth: f64, (resid, var): (f64, f64)) -> (f64, f64) {
        let u = unit(inclination, azimuth);
        let a = self.prior.amplitude(&u);
        let (range, slope) = self.target.back(self.target.of(self.prior.range(&u)) + a * resid);
        (range, a * a * var * slope * slope)
    }

    /// [`Self::predict_range`] of many sensor-frame directions (θ, φ) at once (each expert's
    /// factor is read once per block of its rays rather than once per ray).
    pub fn predict_ranges(&self, angles: &[(f64, f64)]) -> Vec<(f64, f64)> {
        self.gp
            .mean_variance_batch(angles)
            .into_iter()
            .zip(angles)
            .map(|(residual, &(inclination, azimuth))| self.to_range(inclination, azimuth, residual))
            .collect()
    }

    /// The predicted surface point along sensor direction (θ, φ), in the map frame, with its
    /// per-axis standard deviations s_r |w_x|, s_r |w_y|, s_r |w_z| (seed 000 Table I).
    pub fn point(&self, inclination: f64, azimuth: f64) -> ([f64; 3], [f64; 3]) {
        let (range, var) = self.predict_range(inclination, azimuth);
        let w = self.pose.rotation * unit(inclination, azimuth);
        let p = self.sensor_position() + w * range;
        let s = var.sqrt();
        ([p.x, p.y, p.z], [s * w.x.abs(), s * w.y.abs(), s * w.z.abs()])
    }

    /// Tiles whose Cholesky factorisation needed diagonal jitter.
    pub fn jittered_tiles(&self) -> usize {
        self.gp.jittered_tiles()
    }

    /// Mean range only (O(n)).
    fn mean_range(&self, inclination: f64, azimuth: f64) -> f64 {
        self.mean_range_along(inclination, azimuth, &unit(inclination, azimuth))
    }

    /// Mean range along the ray (θ, φ) whose sensor-frame unit direction `u` is at hand.
    fn mean_range_along(&self, inclination: f64, azimuth: f64, u: &Vector3<f64>) -> f64 {
        let value = self.target.of(self.prior.range(u))
            + self.prior.amplitude(u) * self.gp.mean_along(inclination, azimuth, [u.x, u.y, u.z]);
        self.target.back(value).0
    }

    /// Sensor-frame angles and distance of map point `p`, if inside the observed field of view.
    fn look_at(&self, p: &Vector3<f64>) -> Option<(f64, f64, f64)> {
        let (v, dist) = self.sensor_vector(p)?;
        let (inc, az) = sphere::angles_of(v);
        Some((inc, az, dist))
    }

    /// Sensor-frame vector to map point `p` and its length, if inside the observed field of
    /// view (no inverse trigonometry: the membership test of every search).
    fn sensor_vector(&self, p: &Vector3<f64>) -> Option<([f64; 3], f64)> {
        self.in_view(self.to_sensor(p))
    }

    /// Map point `p` as a sensor-frame vector from the sensor.
    fn to_sensor(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.pose
            .rotation
            .inverse_transform_vector(&(p - self.sensor_position()))
    }

    /// Sensor-frame vector `q` and its length, if inside the observed field of view.
    fn in_view(&self, q: Vector3<f64>) -> Option<([f64; 3], f64)> {
        self.in_band(q)
            .filter(|(v, dist)| self.fov.under_ceiling(v, *dist))
    }

    /// [`Self::in_view`] without the view's ceiling ([`FieldOfView::band_holds`]): where the
    /// searches for a first crossing run, so one the map carried into the sky is found and then
    /// refused by the view at the crossing.
    fn in_band(&self, q: Vector3<f64>) -> Option<([f64; 3], f64)> {
        let dist = q.norm();
        let v = [q.x, q.y, q.z];
        (dist > 1e-9 && dist <= self.max_range && self.fov.band_holds(&v, dist)).then_some((v, dist))
    }

    /// Signed gap `‖p − s‖ − μ(angles of p)` of map point `p`, metres: how far it lies behind
    /// this scan's mean surface along the sensor's ray through it (negative in free space the
    /// scan saw through), or `None` outside its field of view; also whether this view agrees with
    /// a surface another map put at `p`.
    pub fn gap(&self, p: &Vector3<f64>) -> Option<f64> {
        self.sensor_vector(p).map(|(v, dist)| self.gap_of(v, dist))
    }

    /// [`Self::gap`] wherever the band and arc hold, above the view's ceiling too: the gap a
    /// search for the first crossing steps along.
    fn search_gap(&self, p: &Vector3<f64>) -> Option<f64> {
        self.in_band(self.to_sensor(p))
            .map(|(v, dist)| self.gap_of(v, dist))
    }

    /// The gap of the sensor-frame vector `v` of length `dist`.
    fn gap_of(&self, v: [f64; 3], dist: f64) -> f64 {
        let (inc, az) = sphere::angles_of(v);
        // The direction is v / ‖v‖: no sine or cosine of the angles just taken.
        let u = Vector3::new(v[0] / dist, v[1] / dist, v[2] / dist);
        dist - self.mean_range_along(inc, az, &u)
    }

    /// Delta-method variance of `root` (at map point `p`) of `gap`.
    fn root_variance(
        &self,
        gap: impl Fn(f64) -> Option<f64>,
        p: &Vector3<f64>,
        root: root::Root,
    ) -> Option<f64> {
        let (inc, az, _) = self.look_at(p)?;
        let (_, var_r) = self.predict_range(inc, az);
        root::root_variance(gap, root, var_r)
    }
}

/// Sensor-frame unit direction of (θ, φ).
fn unit(inclination: f64, azimuth: f64) -> Vector3<f64> {
    let [x, y, z] = sphere::to_sphere(inclination, azimuth, 1.0);
    Vector3::new(x, y, z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{self, params, scan_of};
    use nalgebra::{Translation3, UnitQuaternion};
    use rangegp_sim::{CraterParams, Heightmap, ScannerPreset};

    #[test]
    fn provenance_grades_distance_against_the_correlation_length() {
        assert_eq!(provenance_of(0.0, 1.0), Provenance::Observed);
        assert_eq!(provenance_of(0.3, 1.0), Provenance::Observed);
        assert_eq!(provenance_of(0.31, 1.0), Provenance::Interpolated);
        assert_eq!(provenance_of(1.0, 1.0), Provenance::Interpolated);
        assert_eq!(provenance_of(1.01, 1.0), Provenance::Extrapolated);
        assert_eq!(provenance_of(f64::INFINITY, 1.0), Provenance::Extrapolated);
    }

    #[test]
    fn flat_ground_is_recovered_exactly_and_unseen_places_are_refused() {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5),
        );
        let map = LocalRangeMap::fit(&scan_of(&terrain, pose), &params()).expect("fit");
        for (x, y) in [(3.0, 2.0), (5.0, 4.0), (1.5, 2.5)] {
            let e = map.elevation(x, y).expect("observed");
            assert!(e.z.abs() < 2e-3, "z at ({x},{y}) = {}", e.z);
            assert!(e.var > 0.0 && e.var.sqrt() < 0.05);
        }
        // Behind the sensor (the seed-000 scanner looks ±90° around its heading) and beyond 10 m.
        assert!(map.elevation(-3.0, -2.0).is_none());
        assert!(map.elevation(12.0, 8.0).is_none());
    }

    #[test]
    fn ground_past_an_edge_where_the_rays_came_back_empty_is_refused() {
        // Level ground to x = 6 m, then a drop to 5 m below: the seed-000 scanner's rings that
        // look past the edge return nothing within its 10 m. Its map carries the level ground
        // over the drop (and answers 5 m too high) unless the view has its ceiling
        // (`gp.view_ceiling`, the default): nothing above the highest return in an azimuth is in
        // view.
        let (size, res) = (40.0, 0.05);
        let n = (size / res) as usize + 1;
        let z: Vec<f64> = (0..n * n)
            .map(|k| (-4.0 * ((k % n) as f64 * res - size / 2.0 - 6.0)).clamp(-5.0, 0.0))
            .collect();
        let terrain = Heightmap::from_grid(size, res, z);
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.75), UnitQuaternion::identity());
        let scan = scan_of(&terrain, pose);
        let open = MapParams {
            view_ceiling: false,
            ..params()
        };
        let open = LocalRangeMap::fit(&scan, &open).expect("fit");
        let far = open.elevation(8.0, 0.0).expect("carried over the drop");
        assert!(far.z.abs() < 0.1, "without the ceiling z {} at (8, 0)", far.z);
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        let near = map.elevation(4.0, 0.5).expect("level ground before the edge");
        assert!(near.z.abs() < 0.01, "z {} before the edge", near.z);
        for (x, y) in [(8.0, 0.0), (9.0, 1.0), (7.5, -2.0)] {
            assert!(
                map.elevation(x, y).is_none(),
                "({x}, {y}), 5 m down, answered {:?}",
                map.elevation(x, y).map(|e| e.z)
            );
        }
    }

    #[test]
    fn the_ceiling_only_refuses_answers_it_never_moves_one() {
        // Rough relief seen by a VLP-16: the searches run in the band and the arc, and a first
        // crossing above the ceiling is refused, not replaced by a crossing lower down the line
        // (which, past a crest, is the foot of the map's ramp over the shadow). So every answer
        // with the ceiling is the answer without it, and the ceiling refuses some.
        let terrain = test_support::family_terrain("fbm-h08-30deg", 2, 120.0);
        let ground = terrain.height(0.0, 0.0).expect("the centre lies on the terrain");
        let pose = Isometry3::translation(0.0, 0.0, ground + 0.75);
        let scan = test_support::scan_by(&ScannerPreset::vlp16(), &terrain, pose);
        let params = MapParams {
            sphere_radius_m: Some(ScannerPreset::vlp16().max_range_m),
            ..params()
        };
        let open = MapParams {
            view_ceiling: false,
            ..params
        };
        let (map, open) = (
            LocalRangeMap::fit(&scan, &params).expect("fit"),
            LocalRangeMap::fit(&scan, &open).expect("fit"),
        );
        let (mut same, mut refused) = (0, 0);
        for i in 0..60 {
            for j in 0..60 {
                let (x, y) = (-45.0 + 1.5 * i as f64, -45.0 + 1.5 * j as f64);
                match (map.elevation(x, y), open.elevation(x, y)) {
                    (Some(a), Some(b)) => {
                        assert!(a.z == b.z && a.var == b.var, "({x}, {y}) {} vs {}", a.z, b.z);
                        same += 1;
                    }
                    (Some(a), None) => panic!("({x}, {y}) answered {} only under the ceiling", a.z),
                    (None, Some(_)) => refused += 1,
                    (None, None) => {}
                }
            }
        }
        assert!(
            same > 1000 && refused > 10,
            "{same} answered alike, {refused} refused"
        );
    }

    #[test]
    fn the_ground_under_the_robot_and_the_rise_of_ground_off_its_level() {
        // A plane falling 5 % along x, the sensor 1.1 m above it (the prior assumes 0.75 m:
        // the ground is read from the returns, not from the config), tilted 3° about y.
        let (size, res) = (40.0, 0.05);
        let n = (size / res) as usize + 1;
        let z: Vec<f64> = (0..n * n)
            .map(|k| -0.05 * ((k % n) as f64 * res - size / 2.0))
            .collect();
        let terrain = Heightmap::from_grid(size, res, z);
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 1.1),
            UnitQuaternion::from_euler_angles(0.0, 3f64.to_radians(), 0.0),
        );
        let map = LocalRangeMap::fit(&scan_of(&terrain, pose), &params()).expect("fit");
        let ground = map.ground_z().expect("near returns");
        assert!(ground.abs() < 0.05, "ground under the robot at {ground}");
        // Down the slope the ground lies below the robot's level by 5 % of the distance.
        let e = map.elevation(6.0, 0.5).expect("observed");
        assert!((e.rise + 0.05).abs() < 0.01, "{e:?}");
        let e = map.elevation(6.0, -0.5).expect("observed");
        assert!((e.rise + 0.05).abs() < 0.01, "{e:?}");
        // A corrected pose carries the ground along: 2 m up, the ground is 2 m up.
        let moved = map.reanchored(
            Isometry3::from_parts(Translation3::new(0.0, 0.0, 3.1), pose.rotation),
            1,
        );
        let lifted = moved.ground_z().expect("near returns");
        assert!((lifted - ground - 2.0).abs() < 1e-9);
    }

    #[test]
    fn ground_in_the_shadow_of_a_ridge_is_refused_or_covered() {
        // Flat ground with a 40 cm ridge across the view at x ∈ [4, 4.3]: from 0.75 m up, the
        // ground from the ridge to about 9 m is hidden.
        let (size, res) = (40.0, 0.05);
        let n = (size / res) as usize + 1;
        let z: Vec<f64> = (0..n * n)
            .map(|k| {
                let x = (k % n) as f64 * res - size / 2.0;
                if (4.0..=4.3).contains(&x) {
                    0.4
                } else {
                    0.0
                }
            })
            .collect();
        let terrain = Heightmap::from_grid(size, res, z);
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.75), UnitQuaternion::identity());
        let map = LocalRangeMap::fit(&scan_of(&terrain, pose), &params()).expect("fit");
        let front = map.elevation(3.5, 0.3).expect("ground in front of the ridge");
        assert!(front.z.abs() < 0.01, "{front:?}");
        for x in [5.0, 5.5, 6.0, 6.5, 7.0, 7.5] {
            if let Some(e) = map.elevation(x, 0.3) {
                assert!(e.z.abs() <= 3.0 * e.var.sqrt(), "hidden ground at x = {x}: {e:?}");
            }
        }
    }

    #[test]
    fn ray_cast_meets_the_cratered_ground_from_an_unvisited_origin() {
        let terrain = Heightmap::cratered(11, &CraterParams::sized(40.0));
        let pose = rangegp_sim::level_pose(&terrain, 0.0, 0.0, 0.0, 0.75);
        let ground = pose.translation.z - 0.75;
        let map = LocalRangeMap::fit(&scan_of(&terrain, pose), &params()).expect("fit");
        let origin = Vector3::new(1.0, 0.5, ground + 1.2);
        let dir = Vector3::new(1.0, 0.1, -0.35).normalize();
        let truth = terrain.cast(origin, dir, 10.0).expect("ground hit");
        let est = map.cast(origin, dir, 10.0, &|_| 1.0).expect("in view");
        let range = est.range.expect("hit");
        let sd = est.range_var.expect("variance").sqrt();
        assert!((range - truth).abs() < 0.1, "{range} vs {truth}");
        assert!((range - truth).abs() < 4.0 * sd + 0.01);
        assert!(est.hit_probability > 0.99);
        let up = map.cast(origin, Vector3::new(1.0, 0.0, 0.05).normalize(), 3.0, &|_| 1.0);
        assert!(up.is_none_or(|e| e.range.is_none() && e.hit_probability < 0.5));
    }

    #[test]
    fn per_axis_sigma_follows_the_ray_direction() {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        );
        let map = LocalRangeMap::fit(&scan_of(&terrain, pose), &params()).expect("fit");
        let (inc, az) = (100f64.to_radians(), 0.2);
        let (p, sigma) = map.point(inc, az);
        assert!(p[2].abs() < 2e-3, "flat ground at z = 0, got {}", p[2]);
        let (_, var) = map.predict_range(inc, az);
        let w = pose.rotation * unit(inc, az);
        for axis in 0..3 {
            assert!((sigma[axis] - var.sqrt() * w[axis].abs()).abs() < 1e-15);
        }
        // Oblique view: most of the range uncertainty is horizontal (seed 000's finding).
        assert!(sigma[2] < sigma[0].hypot(sigma[1]));
    }
}
