//! Where a line meets one scan's range surface: heights down the vertical line, rays, and the
//! shadow and provenance tests that grade them.

use super::{provenance_of, unit, HeightEstimate, LocalRangeMap, RayEstimate};
use crate::map::prior::Prior;
use crate::map::root;
use nalgebra::Vector3;
use rangegp_proto::msg::Provenance;
use std::f64::consts::FRAC_PI_2;

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

/// Within this horizontal distance of the sensor an answer's rise is taken over this distance,
/// metres ([`LocalRangeMap::rise`]).
pub const RISE_MIN_DISTANCE_M: f64 = 1.0;

/// Inclination step of the shadow test's range derivative, radians (0.1°).
const SHADOW_PROBE_RAD: f64 = 1.745e-3;
/// A crossing seen at a grazing angle below this fraction of flat ground's is a shadow edge.
const SHADOW_GRAZING_FRACTION: f64 = 0.25;

impl LocalRangeMap {
    /// Surface height at map (x, y): the first crossing of the vertical line from above
    /// (docs/MATH.md "From range to 3-D"), or `None` outside what this scan saw.
    pub fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        let (top, span) = self.vertical_fov(x, y)?;
        self.first_crossing_down(x, y, top, span)
    }

    fn first_crossing_down(&self, x: f64, y: f64, top: f64, span: f64) -> Option<HeightEstimate> {
        let gap = |t: f64| self.search_gap(&Vector3::new(x, y, top - t));
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
        let w = self.pose.rotation * unit(inc, az);
        let sd_r = var_r.sqrt();
        let z = top - root.t;
        let var = root::root_variance(gap, root, var_r)?;
        // The height of the data nearest the answer: how far the answer departs from it, and
        // how far it lies off the robot's level.
        let near = self.data.height_near(x, y).unwrap_or(z);
        Some(HeightEstimate {
            z,
            var,
            grazing,
            point_sd: [sd_r * w.x.abs(), sd_r * w.y.abs(), sd_r * w.z.abs()],
            data_m: self.data.distance(x, y),
            rise: self.rise(near, rho2.sqrt()),
            departure: z - near,
        })
    }

    /// [`HeightEstimate::rise`] of an answer `rho_m` from the sensor whose nearest data lie at
    /// height `near` ([`DataIndex::height_near`]; the answer's own height for a map that keeps
    /// no index): from the data rather than the answer, which far from data drifts toward the
    /// prior's level ground, so the answers that err most would look level. Within [`RISE_MIN_DISTANCE_M`] of
    /// the sensor the rise is taken over that distance (a grade at the robot's feet says nothing
    /// of its level); 0 where the scan showed no ground under the robot.
    ///
    /// [`DataIndex::height_near`]: crate::map::data_index::DataIndex::height_near
    fn rise(&self, near: f64, rho_m: f64) -> f64 {
        self.ground_z()
            .map_or(0.0, |g| (near - g) / rho_m.max(RISE_MIN_DISTANCE_M))
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
        let sees_z = |z: f64| self.in_band(a + z * e).is_some();
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
        let gap = |t: f64| self.search_gap(&point(t));
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
