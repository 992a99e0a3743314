//! Odometry that drifts: the poses a robot's dead reckoning would report along a true path,
//! for the pose-correction evaluation (a loop closure then restores the true poses).

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// How dead reckoning errs per metre travelled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryDrift {
    /// Error of each step's measured length, as a fraction (0.01: 1 % of the distance).
    pub scale_error: f64,
    /// Heading error gained per metre, radians (turning every later step).
    pub heading_rad_per_m: f64,
    /// Height error gained per metre, metres.
    pub climb_per_m: f64,
}

impl OdometryDrift {
    /// Wheel odometry of the issue: 1 % of the distance, 2° of heading per 100 m, 0.2 % in
    /// height.
    pub fn wheels() -> Self {
        Self {
            scale_error: 0.01,
            heading_rad_per_m: 2f64.to_radians() / 100.0,
            climb_per_m: 0.002,
        }
    }

    /// The poses dead reckoning reports along `truth` (starting from its first pose): each
    /// step's motion measured `1 + scale_error` long and turned by the heading error so far.
    pub fn apply(&self, truth: &[Isometry3<f64>]) -> Vec<Isometry3<f64>> {
        let Some(first) = truth.first() else {
            return Vec::new();
        };
        let mut out = vec![*first];
        let (mut heading, mut position) = (0.0f64, first.translation.vector);
        for pair in truth.windows(2) {
            let step = pair[1].translation.vector - pair[0].translation.vector;
            let flat = step.xy().norm();
            heading += self.heading_rad_per_m * flat;
            let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading);
            position +=
                turn * step * (1.0 + self.scale_error) + Vector3::new(0.0, 0.0, self.climb_per_m * flat);
            out.push(Isometry3::from_parts(
                Translation3::from(position),
                turn * pair[1].rotation,
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_straight_drive_drifts_by_the_scale_and_the_heading_error() {
        let truth: Vec<Isometry3<f64>> = (0..=100)
            .map(|k| Isometry3::translation(k as f64, 0.0, 0.0))
            .collect();
        let drift = OdometryDrift::wheels();
        let odo = drift.apply(&truth);
        let end = odo[100].translation.vector;
        // 101 m along x (1 % long), bent left by the heading error: ~½ · 100 m · 2° ≈ 1.75 m.
        assert!((end.x - 101.0).abs() < 0.1, "{end}");
        assert!((end.y - 1.75).abs() < 0.1, "{end}");
        assert!((end.z - 0.2).abs() < 1e-9, "{end}");
        let (_, _, yaw) = odo[100].rotation.euler_angles();
        assert!((yaw - 2f64.to_radians()).abs() < 1e-9);
        assert_eq!(odo[0], truth[0]);
    }
}
