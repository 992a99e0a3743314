//! What a scan trains: its prior, its kernel inputs, the rays it fits (an even stride under the
//! cap) and the patch it gives the hyperparameter learner.

use super::{unit, MapParams, PriorKind};
use crate::gp::sphere;
use crate::map::data_index::DataIndex;
use crate::map::embedding::Embedding;
use crate::map::plane;
use crate::map::prior::Prior;
use crate::map::tiles::TrainingRay;
use crate::scan::ScanInput;
use nalgebra::{Isometry3, Vector3};

/// The kernel-input map of `scan`'s local map (its prior's footprints).
pub fn embedding_of(scan: &ScanInput, params: &MapParams) -> Embedding {
    Embedding::new(
        prior_of(scan, params),
        params.sphere_radius_m.unwrap_or(scan.max_range_m),
    )
}

/// The prior mean a scan is fitted with.
pub(super) fn prior_of(scan: &ScanInput, params: &MapParams) -> Prior {
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

/// Share of a scan's returns, the nearest to the sensor horizontally, that show the ground under
/// the robot ([`ground_of`]): one in this many.
pub const NEAR_GROUND_SHARE: usize = 10;

/// The ground under the robot as the scan shows it, in the sensor's frame, with no sensor
/// height assumed: the plane through the nearest 1/[`NEAR_GROUND_SHARE`] of `scan`'s returns
/// (horizontal distance, map-frame heights; [`plane::Returns`]), taken at the sensor's
/// horizontal position. A plane rather than their median height: a scanner that looks ahead
/// sees its nearest ground metres in front, which on a slope lies off the robot's level.
/// `None` without returns.
pub(super) fn ground_of(scan: &ScanInput) -> Option<Vector3<f64>> {
    let mut near: Vec<(f64, Vector3<f64>, f64)> = scan
        .rays
        .iter()
        .map(|r| {
            let dir = scan.pose.rotation * unit(r.inclination, r.azimuth);
            let m = dir * r.range;
            (m.x.hypot(m.y), m, (scan.range_sd(r.range) * dir.z).powi(2))
        })
        .filter(|(rho, m, _)| rho.is_finite() && m.z.is_finite())
        .collect();
    if near.is_empty() {
        return None;
    }
    let k = (near.len() / NEAR_GROUND_SHARE).max(1);
    near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
    let mut returns = plane::Returns::default();
    for (_, m, noise_var) in &near[..k] {
        returns.add(m.x, m.y, m.z, *noise_var);
    }
    let height = returns.plane()?.z;
    Some(scan.pose.rotation.inverse() * Vector3::new(0.0, 0.0, height))
}

/// The sensor-frame points of the rays [`training_rays`] takes (the same stride).
pub(super) fn training_returns(scan: &ScanInput, cap: usize) -> impl Iterator<Item = Vector3<f64>> + '_ {
    scan.rays
        .iter()
        .step_by(training_stride(scan, cap))
        .map(|r| unit(r.inclination, r.azimuth) * r.range)
}

/// The map-frame ground index of sensor-frame `returns` seen from `pose`.
pub(super) fn index_of(returns: &[[f32; 3]], pose: &Isometry3<f64>) -> DataIndex {
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
pub(super) fn training_rays(
    scan: &ScanInput,
    prior: &Prior,
    params: &MapParams,
    cap: usize,
) -> Vec<TrainingRay> {
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
