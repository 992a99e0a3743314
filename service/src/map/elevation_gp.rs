//! The elevation-GP baseline of seed 000 (and seeds 001–003): z as a GP over the ground plane,
//! Matérn-3/2 plus known noise on (x, y), constant prior at the training points' mean height.
//! Built on the same exact-GP machinery as the range maps, for side-by-side evaluation.

use crate::gp::{CholeskyError, ExactGp, JitterPolicy, Kernel};

/// z(x, y) ~ GP(mean z, k) fitted to 3-D points.
#[derive(Debug, Clone)]
pub struct ElevationGp {
    gp: ExactGp,
    mean_z: f64,
    /// The points and noise variances it was fitted to (what a paged-out tile keeps, so that it
    /// comes back fitted exactly as it left).
    points: Vec<[f64; 3]>,
    noise_var: Vec<f64>,
}

impl ElevationGp {
    /// Fits to `points` (x, y, z) with per-point noise variances `noise_var` (panics on empty or
    /// mismatched input: caller's misuse).
    pub fn fit(
        points: &[[f64; 3]],
        noise_var: &[f64],
        kernel: Kernel,
        jitter: JitterPolicy,
    ) -> Result<Self, CholeskyError> {
        assert!(!points.is_empty(), "no points");
        let mean_z = points.iter().map(|p| p[2]).sum::<f64>() / points.len() as f64;
        let inputs = points.iter().map(|p| [p[0], p[1], 0.0]).collect();
        let targets: Vec<f64> = points.iter().map(|p| p[2] - mean_z).collect();
        Ok(Self {
            gp: ExactGp::fit(kernel, inputs, &targets, noise_var, jitter)?,
            mean_z,
            points: points.to_vec(),
            noise_var: noise_var.to_vec(),
        })
    }

    /// Predicted height at (x, y), mean only (O(n)).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        self.mean_z + self.gp.mean(&[x, y, 0.0])
    }

    /// Predicted height and its latent variance at (x, y).
    pub fn predict(&self, x: f64, y: f64) -> (f64, f64) {
        let (m, v) = self.gp.mean_variance(&[x, y, 0.0]);
        (self.mean_z + m, v)
    }

    /// Heights and latent variances at many (x, y) (blocked triangular solves).
    pub fn predict_batch(&self, xy: &[(f64, f64)]) -> (Vec<f64>, Vec<f64>) {
        let xs: Vec<[f64; 3]> = xy.iter().map(|&(x, y)| [x, y, 0.0]).collect();
        let (mut means, vars) = self.gp.predict_batch(&xs);
        means.iter_mut().for_each(|m| *m += self.mean_z);
        (means, vars)
    }

    /// Widens its variance where its own leave-one-out residuals say the data disagree, locally
    /// ([`ExactGp::set_local_variance_scale`]), never narrowing it below the kernel's: its
    /// targets are other models' predictions, whose agreement is no evidence of accuracy.
    pub fn widen_locally(&mut self) {
        let z = self.gp.loo_residuals();
        let scale = crate::map::tiles::loo_scale(&z);
        self.gp.set_local_variance_scale(&z, scale, 1.0);
    }

    /// The points and noise variances it was fitted to.
    pub fn training(&self) -> (&[[f64; 3]], &[f64]) {
        (&self.points, &self.noise_var)
    }

    /// The underlying GP (for likelihood-based hyperparameter fits).
    pub fn gp(&self) -> &ExactGp {
        &self.gp
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_tilted_plane_and_grows_uncertain_away_from_data() {
        let plane = |x: f64, y: f64| 0.1 * x - 0.05 * y + 0.3;
        let pts: Vec<[f64; 3]> = (0..100)
            .map(|i| {
                let (x, y) = ((i % 10) as f64 * 0.5, (i / 10) as f64 * 0.5);
                [x, y, plane(x, y)]
            })
            .collect();
        let gp = ElevationGp::fit(
            &pts,
            &vec![1e-6; pts.len()],
            Kernel::matern32(0.1, 5.0),
            JitterPolicy::default(),
        )
        .expect("fit");
        let (z, v_in) = gp.predict(2.25, 2.25);
        assert!((z - plane(2.25, 2.25)).abs() < 1e-3, "{z}");
        let (_, v_out) = gp.predict(30.0, 30.0);
        assert!(v_out > 100.0 * v_in);
    }
}
