//! Rover paths: a sequence of sensor poses over a terrain.

use crate::terrain::Heightmap;
use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// A rover path: planar waypoints with headings, lifted onto the terrain at the mount height.
#[derive(Debug, Clone, PartialEq)]
pub struct Path {
    /// (x, y, heading) of each pose, metres and radians.
    pub waypoints: Vec<[f64; 3]>,
}

impl Path {
    /// A smooth seeded wander of `count` poses `step_m` apart, turning at most `max_turn_rad`
    /// per step and steering back towards the centre when closer than 15 m to the map edge.
    pub fn wander(seed: u64, terrain: &Heightmap, count: usize, step_m: f64, max_turn_rad: f64) -> Self {
        let mut rng = Pcg64::seed_from_u64(seed);
        let limit = terrain.half_extent() - 15.0;
        let (mut x, mut y) = (0.0f64, 0.0f64);
        let mut heading: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let mut waypoints = Vec::with_capacity(count);
        for _ in 0..count {
            waypoints.push([x, y, heading]);
            let to_centre = (-y).atan2(-x);
            let turn = if x.abs() > limit || y.abs() > limit {
                wrap(to_centre - heading).clamp(-max_turn_rad, max_turn_rad)
            } else {
                rng.random_range(-max_turn_rad..max_turn_rad)
            };
            heading = wrap(heading + turn);
            x += step_m * heading.cos();
            y += step_m * heading.sin();
        }
        Self { waypoints }
    }

    /// Sensor pose at waypoint `i`: level, yawed to the heading, `mount_height_m` above ground.
    pub fn pose(&self, terrain: &Heightmap, i: usize, mount_height_m: f64) -> Isometry3<f64> {
        let [x, y, heading] = self.waypoints[i];
        level_pose(terrain, x, y, heading, mount_height_m)
    }

    /// Sensor pose at waypoint `i` on a chassis `chassis_m` long and wide that rests on the
    /// ground ([`chassis_pose`]), or level ([`Path::pose`]) when `chassis_m` is `None`.
    pub fn pose_on(
        &self,
        terrain: &Heightmap,
        i: usize,
        mount_height_m: f64,
        chassis_m: Option<f64>,
    ) -> Isometry3<f64> {
        let [x, y, heading] = self.waypoints[i];
        match chassis_m {
            Some(length_m) => chassis_pose(terrain, x, y, heading, mount_height_m, length_m),
            None => level_pose(terrain, x, y, heading, mount_height_m),
        }
    }
}

/// A level sensor over map (x, y), yawed to `heading`, `mount_height_m` above the ground there
/// (above z = 0 off the map).
pub fn level_pose(terrain: &Heightmap, x: f64, y: f64, heading: f64, mount_height_m: f64) -> Isometry3<f64> {
    let ground = terrain.height(x, y).unwrap_or(0.0);
    Isometry3::from_parts(
        Translation3::new(x, y, ground + mount_height_m),
        UnitQuaternion::from_euler_angles(0.0, 0.0, heading),
    )
}

/// A sensor on a square chassis `length_m` a side centred on map (x, y) and yawed to `heading`,
/// whose wheels rest on the ground: the chassis takes the plane through the heights under its
/// four corners (pitch from front against back, roll from left against right) and the sensor
/// stands `mount_height_m` along the chassis' up axis above that plane's centre. On a 25° slope
/// a real rover's sensor tilts by as much; [`level_pose`] keeps it level. Heights off the map
/// are taken as z = 0.
///
/// # Panics
/// If `length_m` is not positive and finite (a caller's misuse).
pub fn chassis_pose(
    terrain: &Heightmap,
    x: f64,
    y: f64,
    heading: f64,
    mount_height_m: f64,
    length_m: f64,
) -> Isometry3<f64> {
    assert!(
        length_m.is_finite() && length_m > 0.0,
        "chassis length {length_m} m"
    );
    let (s, c) = heading.sin_cos();
    let half = 0.5 * length_m;
    let at = |along: f64, across: f64| {
        terrain
            .height(x + along * c - across * s, y + along * s + across * c)
            .unwrap_or(0.0)
    };
    let (front_left, front_right) = (at(half, half), at(half, -half));
    let (back_left, back_right) = (at(-half, half), at(-half, -half));
    let rise_along = 0.5 * (front_left + front_right - back_left - back_right) / length_m;
    let rise_across = 0.5 * (front_left + back_left - front_right - back_right) / length_m;
    let centre = 0.25 * (front_left + front_right + back_left + back_right);
    let forward = Vector3::new(c, s, rise_along).normalize();
    let up = forward.cross(&Vector3::new(-s, c, rise_across)).normalize();
    let left = up.cross(&forward);
    let rotation = Rotation3::from_basis_unchecked(&[forward, left, up]);
    Isometry3::from_parts(
        Translation3::from(Vector3::new(x, y, centre) + up * mount_height_m),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

fn wrap(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wander_stays_on_the_map_with_fixed_steps() {
        let t = Heightmap::flat(100.0, 0.5, 0.0);
        let p = Path::wander(4, &t, 400, 1.0, 0.3);
        for w in p.waypoints.windows(2) {
            let d = (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]);
            assert!((d - 1.0).abs() < 1e-9);
        }
        assert!(p.waypoints.iter().all(|w| w[0].abs() < 45.0 && w[1].abs() < 45.0));
    }

    #[test]
    fn a_chassis_on_a_slope_tilts_with_it_and_stands_level_on_flat_ground() {
        let flat = Heightmap::flat(40.0, 0.1, 1.0);
        let level = chassis_pose(&flat, 2.0, 3.0, 0.7, 0.75, 1.0);
        let expected = level_pose(&flat, 2.0, 3.0, 0.7, 0.75);
        assert!((level.translation.vector - expected.translation.vector).norm() < 1e-9);
        assert!(level.rotation.angle_to(&expected.rotation) < 1e-9);

        // z = 0.5 x: a 26.6° slope rising to +x. Heading along +x pitches the nose up, heading
        // along +y rolls the chassis; the sensor stands off the slope along its normal.
        let n = 401;
        let slope = Heightmap::from_grid(
            40.0,
            0.1,
            (0..n * n).map(|k| 0.5 * (-20.0 + 0.1 * (k % n) as f64)).collect(),
        );
        let grade = 0.5f64.atan();
        let up_hill = chassis_pose(&slope, 1.0, 0.0, 0.0, 0.75, 1.0);
        let nose = up_hill.rotation * Vector3::x();
        assert!((nose.z.asin() - grade).abs() < 1e-5, "pitch {}", nose.z.asin());
        let across = chassis_pose(&slope, 1.0, 0.0, std::f64::consts::FRAC_PI_2, 0.75, 1.0);
        let nose = across.rotation * Vector3::x();
        let left = across.rotation * Vector3::y();
        assert!(
            nose.z.abs() < 1e-9 && (left.z.asin() + grade).abs() < 1e-5,
            "roll {}",
            left.z.asin()
        );
        let normal = Vector3::new(-0.5, 0.0, 1.0).normalize();
        for pose in [up_hill, across] {
            let foot = pose.translation.vector - normal * 0.75;
            assert!(
                (foot - Vector3::new(1.0, 0.0, 0.5)).norm() < 1e-5,
                "foot {foot:?}"
            );
        }
    }
}
