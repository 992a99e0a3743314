//! The local range map of one scan: range as a GP over (inclination, azimuth) (seed 000 §III-A).

use super::data_index::DataIndex;
use super::embedding::Embedding;
use super::fov::FieldOfView;
use super::prior::Prior;
use super::root;
use super::tiles::{TiledGp, Tiling, TrainingRay};
use crate::gp::{sphere, CholeskyError, JitterPolicy, Kernel};
use crate::scan::ScanInput;
use nalgebra::{Isometry3, Vector3};
use rangegp_proto::msg::Provenance;
use std::f64::consts::FRAC_PI_2;
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

/// Largest angular step, radians, when sampling a vertical line for the field of view.
const FOV_STEP_RAD: f64 = 2.0 * std::f64::consts::PI / 180.0;

/// Bisections of each end of the field of view on a vertical line (in height: the bracket of
/// one angular step, at most 2°, over 2¹⁰: under 0.4 mm at 10 m).
const FOV_BISECTIONS: usize = 10;

/// The first-crossing search down the field of view's part of a vertical line steps at least
/// 1 / ELEVATION_SAMPLES of it ...
const ELEVATION_SAMPLES: usize = 24;

/// ... and at most 1 / ELEVATION_SAMPLES_MIN of it or [`ELEVATION_STEP_M`], whichever is longer.
const ELEVATION_SAMPLES_MIN: usize = 4;

/// The longest step of that search on a short stretch, metres: a long stretch's quarter steps
/// over as much; a short one (near the sensor, where the field of view ends above the ground)
/// need not be sampled finer than the rest.
const ELEVATION_STEP_M: f64 = 0.25;

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
}

/// Angle between a sensor's z axis and the map's, radians.
fn tilt_of(pose: &Isometry3<f64>) -> f64 {
    (pose.rotation * Vector3::z()).z.clamp(-1.0, 1.0).acos()
}

/// Inclination step of the shadow test's range derivative, radians (0.1°).
const SHADOW_PROBE_RAD: f64 = 1.745e-3;
/// A crossing seen at a grazing angle below this fraction of flat ground's is a shadow edge.
pub const SHADOW_GRAZING_FRACTION: f64 = 0.25;

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
            fov: FieldOfView::covering(&angles, 0.25f64.to_radians()),
            gp: Arc::new(gp),
            generation: 0,
            length_scale: params.kernel.length_scale,
            data: Arc::new(index_of(&returns, &scan.pose)),
            returns: Arc::new(returns),
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
        self.in_view(
            self.pose
                .rotation
                .inverse_transform_vector(&(p - self.sensor_position())),
        )
    }

    /// Sensor-frame vector `q` and its length, if inside the observed field of view.
    fn in_view(&self, q: Vector3<f64>) -> Option<([f64; 3], f64)> {
        let dist = q.norm();
        let v = [q.x, q.y, q.z];
        (dist > 1e-9 && dist <= self.max_range && self.fov.contains_vector(&v, dist)).then_some((v, dist))
    }

    /// Signed gap `‖p − s‖ − μ(angles of p)`: negative in free space, positive behind the surface.
    fn gap(&self, p: &Vector3<f64>) -> Option<f64> {
        let (v, dist) = self.sensor_vector(p)?;
        let (inc, az) = sphere::angles_of(v);
        // The direction is v / ‖v‖: no sine or cosine of the angles just taken.
        let u = Vector3::new(v[0] / dist, v[1] / dist, v[2] / dist);
        Some(dist - self.mean_range_along(inc, az, &u))
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

    /// Surface height at map (x, y): the first crossing of the vertical line from above
    /// (docs/MATH.md "From range to 3-D"), or `None` outside what this scan saw.
    pub fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        let (top, span) = self.vertical_fov(x, y)?;
        self.first_crossing_down(x, y, top, span)
    }

    fn first_crossing_down(&self, x: f64, y: f64, top: f64, span: f64) -> Option<HeightEstimate> {
        let gap = |t: f64| self.gap(&Vector3::new(x, y, top - t));
        // A point `g` short of the surface along its ray (or behind it, for a negative `g`) lies
        // `g · sin(depression)` above where a flat surface below would cross the line: the
        // trace's estimate of the distance left; a ray looking up says nothing of the ground
        // below.
        let s = self.sensor_position();
        let rho2 = (x - s.x).powi(2) + (y - s.y).powi(2);
        let ahead = |t: f64, g: f64| {
            let below = s.z - (top - t);
            if below <= 0.0 {
                return f64::INFINITY;
            }
            -g * below / (below * below + rho2).sqrt()
        };
        let steps = (
            (span / ELEVATION_SAMPLES_MIN as f64).max(ELEVATION_STEP_M),
            span / ELEVATION_SAMPLES as f64,
        );
        let root = root::first_crossing_traced(gap, (0.0, span), (steps.1, steps.0), ahead)?;
        let p = Vector3::new(x, y, top - root.t);
        let (inc, az, dist) = self.look_at(&p)?;
        let grazing = self.grazing((inc, az, dist), root.gap());
        if grazing < SHADOW_GRAZING_FRACTION {
            return None;
        }
        // One range variance at the crossing serves the height's and the point's σ.
        let (_, var_r) = self.predict_range(inc, az);
        let var = root::root_variance(gap, root, var_r)?;
        let w = self.pose.rotation * unit(inc, az);
        let sd_r = var_r.sqrt();
        Some(HeightEstimate {
            z: top - root.t,
            var,
            grazing,
            point_sd: [sd_r * w.x.abs(), sd_r * w.y.abs(), sd_r * w.z.abs()],
            data_m: self.data.distance(x, y),
        })
    }

    /// How much training data stands behind this map's answer at map point `p` (graded only
    /// for the answer a query returns: the nearest-datum search is O(n) per covering expert).
    pub fn provenance(&self, p: &Vector3<f64>) -> Provenance {
        self.look_at(p)
            .map_or(Provenance::None, |(inc, az, _)| self.provenance_at(inc, az))
    }

    /// How much training data stands behind the prediction along (θ, φ).
    fn provenance_at(&self, inclination: f64, azimuth: f64) -> Provenance {
        provenance_of(self.gp.nearest_datum(inclination, azimuth), self.length_scale)
    }

    /// The angle at which the rays meet the predicted surface at `p` (given as its sensor-frame
    /// inclination, azimuth and distance), as a fraction of the angle
    /// flat ground would be seen at from the same distance (infinite where it cannot be told: a
    /// surface receding slower than flat ground, or a prior that does not know the ground).
    /// Below [`SHADOW_GRAZING_FRACTION`] the crossing is the edge of a shadow rather than ground
    /// this scan saw: behind a ridge the vertical line's first crossing is where the rays start
    /// to pass over the ridge; the range jumps there (the map smooths the jump into a steep
    /// ramp), and the crossing's height is the shadow line, not the ground. Only under the
    /// flat-ground prior (it knows the sensor height). `gap_at_p`, the gap already evaluated
    /// at `p`, gives the mean range there, and the rate takes one more evaluation instead of two.
    fn grazing(&self, (inc, az, dist): (f64, f64, f64), gap_at_p: Option<f64>) -> f64 {
        let Prior::FlatGround { height_m, .. } = self.prior else {
            return f64::INFINITY;
        };
        // Inclination is measured from the sensor's zenith: a smaller one looks farther out.
        let step = SHADOW_PROBE_RAD;
        let rate = match gap_at_p {
            Some(g) => (dist - g - self.mean_range(inc + step, az)) / step,
            None => (self.mean_range(inc - step, az) - self.mean_range(inc + step, az)) / (2.0 * step),
        };
        let flat = (height_m / dist).clamp(-1.0, 1.0).asin();
        if rate <= 0.0 || flat <= 0.0 {
            return f64::INFINITY;
        }
        dist.atan2(rate) / flat
    }

    /// The part of the vertical line at (x, y) inside the observed field of view, as its top z
    /// and length (angles only: cheap), or `None` when it misses the field of view.
    ///
    /// Seen from the sensor, the line sweeps half a great circle, elevation ψ ↦ z = ρ tan ψ.
    /// The sensor frame's inclination differs from π/2 − ψ by at most the sensor's tilt, which
    /// bounds the ψ that can lie in the band; that arc is sampled at steps finer than the band
    /// (a great-circle arc crossing the band spans at least its width, so none is stepped over)
    /// and both ends are bisected.
    fn vertical_fov(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let s = self.sensor_position();
        let rho = (x - s.x).hypot(y - s.y);
        if rho >= self.max_range || rho < 1e-6 {
            return None;
        }
        let tilt = self.tilt;
        let (band_lo, band_hi) = self.fov.inclination();
        let half = (self.max_range * self.max_range - rho * rho).sqrt();
        let reach = half.atan2(rho);
        let psi_top = (FRAC_PI_2 - band_lo + tilt).min(reach);
        let psi_bottom = (FRAC_PI_2 - band_hi - tilt).max(-reach);
        if psi_top <= psi_bottom {
            return None;
        }
        let z_at = |psi: f64| s.z + rho * psi.tan();
        // The line in the sensor frame, a + z e: what `sensor_vector` tests, without a rotation
        // per point.
        let a = self
            .pose
            .rotation
            .inverse_transform_vector(&Vector3::new(x - s.x, y - s.y, -s.z));
        let e = self.pose.rotation.inverse_transform_vector(&Vector3::z());
        let sees_z = |z: f64| self.in_view(a + z * e).is_some();
        let sees = |psi: f64| sees_z(z_at(psi));
        let step = (0.5 * (band_hi - band_lo)).min(FOV_STEP_RAD);
        let n = ((psi_top - psi_bottom) / step).ceil().max(2.0) as usize;
        let psi = |k: usize| psi_top - (psi_top - psi_bottom) * k as f64 / n as f64;
        let first = (0..=n).find(|&k| sees(psi(k)))?;
        let last = (first..=n).rev().find(|&k| sees(psi(k)))?;
        // Each end bisected in height (z is monotone in ψ: no tangent per step).
        let edge = |inside: f64, outside: f64| {
            let (mut a, mut b) = (z_at(inside), z_at(outside));
            for _ in 0..FOV_BISECTIONS {
                let m = 0.5 * (a + b);
                if sees_z(m) {
                    a = m;
                } else {
                    b = m;
                }
            }
            a
        };
        let top = if first == 0 {
            z_at(psi(0))
        } else {
            edge(psi(first), psi(first - 1))
        };
        let bottom = if last == n {
            z_at(psi(n))
        } else {
            edge(psi(last), psi(last + 1))
        };
        (top > bottom).then_some((top, top - bottom))
    }

    /// Casts a map-frame ray (unit `dir`) through this map's surface up to `max_range`.
    /// `None` when no point of the ray lies in this scan's field of view.
    pub fn cast(
        &self,
        origin: Vector3<f64>,
        dir: Vector3<f64>,
        max_range: f64,
        sd_factor: &dyn Fn(&Vector3<f64>) -> f64,
    ) -> Option<RayEstimate> {
        let point = |t: f64| origin + dir * t;
        let samples = ((max_range / 0.05).ceil() as usize).clamp(32, 400);
        let gap = |t: f64| self.gap(&point(t));
        if let Some(root) = root::first_crossing(gap, 0.0, max_range, samples) {
            let t = root.t;
            let (inc, az, _) = self.look_at(&point(t))?;
            let (_, var_r) = self.predict_range(inc, az);
            let f = sd_factor(&point(t));
            let band = root::band_variance(
                gap,
                root,
                f * var_r.sqrt(),
                max_range / samples as f64 / 4.0,
                0.0,
                max_range,
            );
            let var = (f * f * self.root_variance(gap, &point(t), root)?).max(band);
            let hit_probability = distrs::Normal::cdf((max_range - t) / var.sqrt().max(1e-12), 0.0, 1.0);
            let (inc, az, _) = self.look_at(&point(t))?;
            return Some(RayEstimate {
                range: Some(t),
                range_var: Some(var),
                hit_probability,
                provenance: self.provenance_at(inc, az),
            });
        }
        // No crossing: the hit probability is set by the closest approach to the surface.
        let mut closest: Option<(f64, f64, f64, Vector3<f64>)> = None;
        for k in 0..=samples {
            let p = point(max_range * k as f64 / samples as f64);
            if let Some((inc, az, dist)) = self.look_at(&p) {
                let g = dist - self.mean_range(inc, az);
                if closest.is_none_or(|c| g > c.0) {
                    closest = Some((g, inc, az, p));
                }
            }
        }
        let (g, inc, az, p) = closest?;
        let (_, var_r) = self.predict_range(inc, az);
        let sd = sd_factor(&p) * var_r.sqrt();
        Some(RayEstimate {
            range: None,
            range_var: None,
            hit_probability: distrs::Normal::cdf(g / sd.max(1e-12), 0.0, 1.0),
            provenance: Provenance::None,
        })
    }
}

/// The kernel-input map of `scan`'s local map (its prior's footprints).
pub fn embedding_of(scan: &ScanInput, params: &MapParams) -> Embedding {
    Embedding::new(
        prior_of(scan, params),
        params.sphere_radius_m.unwrap_or(scan.max_range_m),
    )
}

/// The prior mean a scan is fitted with.
fn prior_of(scan: &ScanInput, params: &MapParams) -> Prior {
    match params.prior {
        PriorKind::FlatGround { sensor_height_m } => {
            Prior::flat_ground(sensor_height_m, &scan.pose.rotation, scan.max_range_m)
        }
        PriorKind::ConstantRange { range_m } => Prior::ConstantRange { range_m },
    }
}

/// The even stride that keeps at most `cap` of `scan`'s rays.
fn training_stride(scan: &ScanInput, cap: usize) -> usize {
    scan.rays.len().div_ceil(cap.max(1)).max(1)
}

/// The sensor-frame points of the rays [`training_rays`] takes (the same stride).
fn training_returns(scan: &ScanInput, cap: usize) -> impl Iterator<Item = Vector3<f64>> + '_ {
    scan.rays
        .iter()
        .step_by(training_stride(scan, cap))
        .map(|r| unit(r.inclination, r.azimuth) * r.range)
}

/// The map-frame ground index of sensor-frame `returns` seen from `pose`.
fn index_of(returns: &[[f32; 3]], pose: &Isometry3<f64>) -> DataIndex {
    let ground: Vec<[f64; 3]> = returns
        .iter()
        .map(|p| {
            let m = pose * nalgebra::Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [m.x, m.y, m.z]
        })
        .collect();
    DataIndex::new(&ground)
}

/// At most `cap` returned rays of `scan` (an even stride) as training rays: residuals from the
/// prior divided by the prior's amplitude, noise variances divided by its square.
fn training_rays(scan: &ScanInput, prior: &Prior, params: &MapParams, cap: usize) -> Vec<TrainingRay> {
    scan.rays
        .iter()
        .step_by(training_stride(scan, cap))
        .map(|r| {
            let u = unit(r.inclination, r.azimuth);
            let a = prior.amplitude(&u);
            let t = params.target;
            // d value / d r at the measurement, for the noise through the transform.
            let slope = 1.0 / t.back(t.of(r.range)).1;
            TrainingRay {
                inclination: r.inclination,
                azimuth: r.azimuth,
                residual: (t.of(r.range) - t.of(prior.range(&u))) / a,
                noise_var: (scan.range_sd(r.range).powi(2) + params.nugget_m2) * (slope / a).powi(2),
            }
        })
        .collect()
}

/// A scan's rays as a hyperparameter-learning sample: the `cap` rays nearest (on the sphere)
/// to a centre ray that moves with the scan's sequence number, as points on the range sphere,
/// residuals from the prior mean, and noise variances. A compact patch keeps the scan's own ray
/// density, so the length scale is not biased by thinning (an even stride over the scan is).
pub fn hyper_sample(scan: &ScanInput, params: &MapParams, cap: usize) -> HyperSample {
    let prior = prior_of(scan, params);
    let embedding = embedding_of(scan, params);
    let mut rays = training_rays(scan, &prior, params, usize::MAX);
    if rays.len() > cap {
        let centre = rays[(scan.sequence as usize).wrapping_mul(2_654_435_761) % rays.len()];
        let c = sphere::to_sphere(centre.inclination, centre.azimuth, 1.0);
        let dist = |r: &TrainingRay| {
            crate::gp::kernel::distance(&c, &sphere::to_sphere(r.inclination, r.azimuth, 1.0))
        };
        rays.select_nth_unstable_by(cap - 1, |a, b| dist(a).total_cmp(&dist(b)));
        rays.truncate(cap);
    }
    HyperSample {
        inputs: rays
            .iter()
            .map(|r| embedding.point(r.inclination, r.azimuth))
            .collect(),
        targets: rays.iter().map(|r| r.residual).collect(),
        noise_var: rays.iter().map(|r| r.noise_var).collect(),
    }
}

/// Training data for one hyperparameter update, owned so it can cross threads.
#[derive(Debug, Clone, PartialEq)]
pub struct HyperSample {
    /// Points on the range sphere.
    pub inputs: Vec<[f64; 3]>,
    /// Range residuals from the prior mean, metres.
    pub targets: Vec<f64>,
    /// Noise variances, m².
    pub noise_var: Vec<f64>,
}

impl HyperSample {
    /// Borrowed view for the likelihood code.
    pub fn as_training_set(&self) -> crate::gp::likelihood::TrainingSet<'_> {
        crate::gp::likelihood::TrainingSet {
            inputs: &self.inputs,
            targets: &self.targets,
            noise_var: &self.noise_var,
        }
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
    use crate::map::test_support::{params, scan_of};
    use nalgebra::{Translation3, UnitQuaternion};
    use rangegp_sim::{CraterParams, Heightmap};

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
