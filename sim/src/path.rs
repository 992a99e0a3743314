//! Rover paths: a sequence of sensor poses over a terrain.

use crate::terrain::Heightmap;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
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
}
