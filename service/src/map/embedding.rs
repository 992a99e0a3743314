//! Where the kernel sees a ray: the point its prior mean expects it to hit (docs/MATH.md
//! "Angles and kernel inputs"). Under the constant-range prior that is seed 000's range sphere,
//! so distances are chordal distances between ray directions; under the flat-ground prior it is
//! the ray's footprint on the ground plane, capped at the sphere radius near the horizon.
//!
//! A fixed map of the inputs keeps every stationary kernel positive definite. On the ground
//! plane one degree of inclination near the horizon spans metres while one degree of azimuth
//! spans centimetres; footprints measure both in metres of ground, so one length scale fits all
//! rings (the isotropic sphere needs a different one per ring and per direction).

use super::prior::Prior;
use crate::gp::sphere;

/// The map from ray angles to kernel inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Embedding {
    prior: Prior,
    radius_m: f64,
}

impl Embedding {
    /// Footprints of `prior`, capped at `radius_m` (panics on a non-positive radius: misuse).
    pub fn new(prior: Prior, radius_m: f64) -> Self {
        assert!(
            radius_m.is_finite() && radius_m > 0.0,
            "embedding radius must be positive"
        );
        Self { prior, radius_m }
    }

    /// Seed 000's range sphere of radius `radius_m`: chordal distance between directions.
    pub fn sphere(radius_m: f64) -> Self {
        Self::new(Prior::ConstantRange { range_m: radius_m }, radius_m)
    }

    /// Kernel input of the sensor-frame ray (θ, φ).
    #[inline]
    pub fn point(&self, inclination: f64, azimuth: f64) -> [f64; 3] {
        self.point_of_unit(sphere::to_sphere(inclination, azimuth, 1.0))
    }

    /// Kernel input of the sensor-frame unit direction `u` (what [`Embedding::point`] gives for
    /// its angles, without the trigonometry when the direction is at hand).
    #[inline]
    pub fn point_of_unit(&self, u: [f64; 3]) -> [f64; 3] {
        let r = match self.prior {
            Prior::ConstantRange { .. } => self.radius_m,
            Prior::FlatGround { .. } => self.prior.range(&nalgebra::Vector3::from(u)).min(self.radius_m),
        };
        [u[0] * r, u[1] * r, u[2] * r]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::kernel::distance;
    use nalgebra::UnitQuaternion;

    #[test]
    fn flat_ground_footprints_are_ground_distances_and_continuous_at_the_cap() {
        let prior = Prior::flat_ground(1.0, &UnitQuaternion::identity(), 100.0);
        let e = Embedding::new(prior, 10.0);
        // Straight down lands under the sensor; 45° down lands 1 m out.
        let down = e.point(std::f64::consts::PI, 0.0);
        assert!(down[0].abs() < 1e-12 && (down[2] + 1.0).abs() < 1e-12);
        let out = e.point(0.75 * std::f64::consts::PI, 0.0);
        assert!((out[0] - 1.0).abs() < 1e-12 && (out[2] + 1.0).abs() < 1e-12);
        // Two rings 1° apart near the horizon are metres apart; two columns 1° apart are not.
        let (t, dt) = (100f64.to_radians(), 1f64.to_radians());
        let radial = distance(&e.point(t, 0.0), &e.point(t + dt, 0.0));
        let lateral = distance(&e.point(t, 0.0), &e.point(t, dt));
        assert!(radial > 4.0 * lateral, "{radial} vs {lateral}");
        // The cap: just below and above the inclination where the footprint reaches 10 m.
        let cap = std::f64::consts::FRAC_PI_2 + (1.0f64 / 10.0).asin();
        let gap = distance(&e.point(cap + 1e-9, 0.3), &e.point(cap - 1e-9, 0.3));
        assert!(gap < 1e-6, "{gap}");
    }

    #[test]
    fn constant_range_is_the_range_sphere() {
        let e = Embedding::sphere(10.0);
        let p = e.point(1.2, -0.4);
        assert!(distance(&p, &sphere::to_sphere(1.2, -0.4, 10.0)) < 1e-12);
    }
}
