//! Prior mean functions of the range GP (seed 000 eqs. 7–8, general form in docs/MATH.md).

use nalgebra::{UnitQuaternion, Vector3};

/// Expected range before seeing data, as a function of the ray direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Prior {
    /// A sphere of constant range (underground, walls, overhangs).
    ConstantRange {
        /// The constant, metres.
        range_m: f64,
    },
    /// Flat ground `height_m` below the sensor, seen through the sensor's roll and pitch.
    FlatGround {
        /// Sensor height above the ground plane, metres.
        height_m: f64,
        /// Rotation taking sensor-frame directions into a gravity-aligned frame (yaw ignored).
        tilt: UnitQuaternion<f64>,
        /// Range used at or above the horizon and as the upper clamp, metres.
        max_range_m: f64,
    },
}

impl Prior {
    /// Flat ground below a sensor with orientation `orientation` (map frame, z up).
    pub fn flat_ground(height_m: f64, orientation: &UnitQuaternion<f64>, max_range_m: f64) -> Self {
        let (roll, pitch, _) = orientation.euler_angles();
        Prior::FlatGround {
            height_m,
            tilt: UnitQuaternion::from_euler_angles(roll, pitch, 0.0),
            max_range_m,
        }
    }

    /// Prior range along the sensor-frame unit direction `u`.
    pub fn range(&self, u: &Vector3<f64>) -> f64 {
        match *self {
            Prior::ConstantRange { range_m } => range_m,
            Prior::FlatGround {
                height_m,
                tilt,
                max_range_m,
            } => {
                let wz = (tilt * u).z;
                if wz < 0.0 {
                    (height_m / -wz).clamp(0.0, max_range_m)
                } else {
                    max_range_m
                }
            }
        }
    }
}

impl Prior {
    /// Scale of the GP residual along `u`, dimensionless (docs/MATH.md "Prior means and the
    /// modelled residual"): the range GP models residual / amplitude, so its kernel is
    /// a(u) a(u′) k(u, u′).
    ///
    /// Over flat ground a height change dz moves the range by dz / |w_z| = dz · prior / height:
    /// residuals near the horizon are tens of times larger than under the sensor, and one
    /// stationary σ² cannot fit both. Dividing by prior / height makes the modelled quantity a
    /// height-like residual of one scale everywhere. The constant-range prior has amplitude 1.
    pub fn amplitude(&self, u: &Vector3<f64>) -> f64 {
        match *self {
            Prior::ConstantRange { .. } => 1.0,
            Prior::FlatGround { height_m, .. } => (self.range(u) / height_m).max(1.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_flat_ground_is_seed000_eq8() {
        let p = Prior::flat_ground(0.75, &UnitQuaternion::identity(), 10.0);
        let below = 10f64.to_radians();
        let u = Vector3::new(below.cos(), 0.0, -below.sin());
        assert!((p.range(&u) - 0.75 / below.sin()).abs() < 1e-12);
        assert_eq!(p.range(&Vector3::new(1.0, 0.0, 0.0)), 10.0);
        assert_eq!(p.range(&Vector3::new(1.0, 0.0, -0.001).normalize()), 10.0);
    }

    #[test]
    fn pitched_sensor_matches_seed000_eq7() {
        // Eq. 7: m = s_z / (sinθ cosφ sinβ − cosθ cosβ) for a sensor pitched by β (nose down > 0).
        let beta: f64 = 0.1;
        let orientation = UnitQuaternion::from_euler_angles(0.0, beta, 0.0);
        let p = Prior::flat_ground(0.75, &orientation, 100.0);
        for (theta, phi) in [(1.75f64, 0.2f64), (1.9, -0.7), (1.65, 0.0)] {
            let u = Vector3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos());
            let eq7 = 0.75 / (theta.sin() * phi.cos() * beta.sin() - theta.cos() * beta.cos());
            assert!((p.range(&u) - eq7).abs() < 1e-9, "{} vs {eq7}", p.range(&u));
        }
    }
}
