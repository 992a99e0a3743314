//! Seed 000's aggregate (§III-B): one exact GP over α = (θ, φ, x, y, z, γ). Ray angles and the
//! heading enter through chordal distance (points on circles of radius R), the sensor position
//! through Euclidean distance; the prior mean depends on the angles alone. Every insert refits
//! the whole GP (O(n³)), as in the paper; `max_points` bounds it.

use super::{Aggregate, AggregateError};
use crate::gp::{sphere, ExactGp, JitterPolicy, Kernel};
use crate::map::local::{HeightEstimate, LocalRangeMap};
use crate::map::prior::Prior;
use crate::map::root;
use crate::scan::ScanInput;
use nalgebra::{Isometry3, Vector3};

/// Kernel input: R·u (3), position (3), R·(cos γ, sin γ) (2).
type Features = [f64; 8];

/// Settings of the pose-augmented GP.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseGpParams {
    /// Kernel over the 8-D features (the local range GP's, seed 000 reused them).
    pub kernel: Kernel,
    /// Radius of the circles angles and heading live on, metres.
    pub sphere_radius_m: f64,
    /// Sensor height of the flat-ground prior, metres.
    pub sensor_height_m: f64,
    /// Noise added to every ray on top of the sensor model, m².
    pub nugget_m2: f64,
    /// Most training rays held (the model refuses more).
    pub max_points: usize,
}

/// The pose-augmented range GP.
#[derive(Debug, Clone)]
pub struct PoseAugmentedGp {
    params: PoseGpParams,
    inputs: Vec<Features>,
    targets: Vec<f64>,
    noise: Vec<f64>,
    poses: Vec<Isometry3<f64>>,
    max_range: f64,
    inclination_box: (f64, f64),
    azimuth_box: (f64, f64),
    gp: Option<ExactGp<8>>,
}

/// The flat-ground prior of seed 000 eq. 8 (level sensor, angles alone).
fn prior(params: &PoseGpParams, max_range: f64) -> Prior {
    Prior::flat_ground(
        params.sensor_height_m,
        &nalgebra::UnitQuaternion::identity(),
        max_range,
    )
}

fn heading(pose: &Isometry3<f64>) -> f64 {
    pose.rotation.euler_angles().2
}

impl PoseAugmentedGp {
    /// An empty model.
    pub fn new(params: PoseGpParams) -> Self {
        Self {
            params,
            inputs: Vec::new(),
            targets: Vec::new(),
            noise: Vec::new(),
            poses: Vec::new(),
            max_range: 0.0,
            inclination_box: (f64::INFINITY, f64::NEG_INFINITY),
            azimuth_box: (f64::INFINITY, f64::NEG_INFINITY),
            gp: None,
        }
    }

    fn features(&self, pose: &Isometry3<f64>, inclination: f64, azimuth: f64) -> Features {
        let r = self.params.sphere_radius_m;
        let u = sphere::to_sphere(inclination, azimuth, r);
        let p = pose.translation.vector;
        let g = heading(pose);
        [u[0], u[1], u[2], p.x, p.y, p.z, r * g.cos(), r * g.sin()]
    }

    /// Predicted range and latent variance of the ray (θ, φ) of a sensor at `pose`; `None`
    /// until two scans are in (the model needs more than one pose).
    pub fn predict_range(&self, pose: &Isometry3<f64>, inclination: f64, azimuth: f64) -> Option<(f64, f64)> {
        let gp = self.gp.as_ref()?;
        let u = Vector3::from(sphere::to_sphere(inclination, azimuth, 1.0));
        let (m, v) = gp.mean_variance(&self.features(pose, inclination, azimuth));
        Some((prior(&self.params, self.max_range).range(&u) + m, v))
    }

    /// Predicted ranges of many rays of one pose (blocked triangular solves).
    pub fn predict_ranges(
        &self,
        pose: &Isometry3<f64>,
        angles: &[(f64, f64)],
    ) -> Option<(Vec<f64>, Vec<f64>)> {
        let gp = self.gp.as_ref()?;
        let xs: Vec<Features> = angles.iter().map(|&(t, p)| self.features(pose, t, p)).collect();
        let (mut means, vars) = gp.predict_batch(&xs);
        let pr = prior(&self.params, self.max_range);
        for (m, &(t, p)) in means.iter_mut().zip(angles) {
            *m += pr.range(&Vector3::from(sphere::to_sphere(t, p, 1.0)));
        }
        Some((means, vars))
    }

    fn mean_range(&self, gp: &ExactGp<8>, pose: &Isometry3<f64>, inclination: f64, azimuth: f64) -> f64 {
        let u = Vector3::from(sphere::to_sphere(inclination, azimuth, 1.0));
        prior(&self.params, self.max_range).range(&u) + gp.mean(&self.features(pose, inclination, azimuth))
    }

    /// Sensor-frame angles and distance of `p` from a sensor at `pose`, inside the angle box the
    /// training rays cover.
    fn look_at(&self, pose: &Isometry3<f64>, p: &Vector3<f64>) -> Option<(f64, f64, f64)> {
        let q = pose
            .rotation
            .inverse_transform_vector(&(p - pose.translation.vector));
        let dist = q.norm();
        let (inc, az) = sphere::angles_of([q.x, q.y, q.z]);
        let inside = (self.inclination_box.0..=self.inclination_box.1).contains(&inc)
            && (self.azimuth_box.0..=self.azimuth_box.1).contains(&az);
        (dist > 1e-9 && dist <= self.max_range && inside).then_some((inc, az, dist))
    }
}

impl Aggregate for PoseAugmentedGp {
    fn name(&self) -> &'static str {
        "seed-000 pose-augmented GP"
    }

    fn insert(&mut self, scan: &ScanInput, _local: &LocalRangeMap) -> Result<(), AggregateError> {
        if self.inputs.len() + scan.rays.len() > self.params.max_points {
            return Err(AggregateError::Full {
                limit: self.params.max_points,
            });
        }
        self.max_range = self.max_range.max(scan.max_range_m);
        let pr = prior(&self.params, self.max_range);
        for r in &scan.rays {
            let u = Vector3::from(sphere::to_sphere(r.inclination, r.azimuth, 1.0));
            self.inputs
                .push(self.features(&scan.pose, r.inclination, r.azimuth));
            self.targets.push(r.range - pr.range(&u));
            self.noise
                .push(scan.range_sd(r.range).powi(2) + self.params.nugget_m2);
            self.inclination_box = (
                self.inclination_box.0.min(r.inclination),
                self.inclination_box.1.max(r.inclination),
            );
            self.azimuth_box = (
                self.azimuth_box.0.min(r.azimuth),
                self.azimuth_box.1.max(r.azimuth),
            );
        }
        self.poses.push(scan.pose);
        if self.poses.len() >= 2 {
            self.gp = Some(ExactGp::fit(
                self.params.kernel,
                self.inputs.clone(),
                &self.targets,
                &self.noise,
                JitterPolicy::default(),
            )?);
        }
        Ok(())
    }

    /// The surface under (x, y) as seen by a virtual sensor at the nearest visited pose: the
    /// first crossing of the vertical line with the predicted range surface, delta-method variance.
    fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        let gp = self.gp.as_ref()?;
        let pose = self.poses.iter().min_by(|a, b| {
            let d = |p: &Isometry3<f64>| (p.translation.x - x).hypot(p.translation.y - y);
            d(a).total_cmp(&d(b))
        })?;
        let s = pose.translation.vector;
        let rho = (x - s.x).hypot(y - s.y);
        // Height of the ray at inclination θ above the sensor where it crosses the vertical line.
        let rise = |inc: f64| rho / inc.tan();
        let (top, bottom) = (
            s.z + rise(self.inclination_box.0) + 0.05,
            s.z + rise(self.inclination_box.1) - 0.05,
        );
        let point = |t: f64| Vector3::new(x, y, top - t);
        let gap = |t: f64| {
            let p = point(t);
            self.look_at(pose, &p)
                .map(|(inc, az, dist)| dist - self.mean_range(gp, pose, inc, az))
        };
        let root = root::first_crossing(gap, 0.0, (top - bottom).max(0.1), 32)?;
        let t = root.t;
        let (inc, az, _) = self.look_at(pose, &point(t))?;
        let (_, var_r) = self.predict_range(pose, inc, az)?;
        let var = root::root_variance(gap, root, var_r)?;
        Some(HeightEstimate {
            z: top - t,
            var,
            grazing: f64::INFINITY,
            point_sd: [0.0, 0.0, var.sqrt()],
            data_m: 0.0,
            rise: 0.0,
            departure: 0.0,
        })
    }

    fn len(&self) -> usize {
        self.inputs.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{params, scan_of};
    use nalgebra::{Translation3, UnitQuaternion};
    use rangegp_sim::Heightmap;

    fn model(max_points: usize) -> PoseAugmentedGp {
        PoseAugmentedGp::new(PoseGpParams {
            kernel: Kernel::matern32(5e-4, 0.97),
            sphere_radius_m: 10.0,
            sensor_height_m: 0.75,
            nugget_m2: 1e-6,
            max_points,
        })
    }

    fn scan(terrain: &Heightmap, x: f64) -> (ScanInput, LocalRangeMap) {
        let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.75), UnitQuaternion::identity());
        let scan = scan_of(terrain, pose);
        let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
        (scan, local)
    }

    #[test]
    fn two_scans_of_flat_ground_give_level_ground() {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let mut gp = model(10_000);
        let (a, la) = scan(&terrain, 0.0);
        gp.insert(&a, &la).expect("first");
        assert!(gp.elevation(3.0, 0.0).is_none(), "one pose is not a model yet");
        let (b, lb) = scan(&terrain, 2.0);
        gp.insert(&b, &lb).expect("second");
        assert_eq!(gp.len(), a.rays.len() + b.rays.len());
        // At least 2.8 m ahead of the nearest pose: the lowest ring (−15°) meets the ground there.
        for (x, y) in [(6.0, 1.0), (7.0, -2.0), (9.0, 0.5)] {
            let e = gp.elevation(x, y).expect("in view");
            assert!(e.z.abs() < 0.01, "z at ({x}, {y}) = {}", e.z);
            assert!(e.var > 0.0);
        }
    }

    #[test]
    fn a_full_model_refuses_the_scan_and_keeps_what_it_had() {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let (a, la) = scan(&terrain, 0.0);
        let mut gp = model(a.rays.len() + 10);
        gp.insert(&a, &la).expect("fits");
        let (b, lb) = scan(&terrain, 2.0);
        assert_eq!(
            gp.insert(&b, &lb),
            Err(AggregateError::Full {
                limit: a.rays.len() + 10
            })
        );
        assert_eq!(gp.len(), a.rays.len());
    }
}
