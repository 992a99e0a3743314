//! An exact GP regression: K + Σ = L Lᵀ, α = (K + Σ)⁻¹ y; posterior mean and latent variance.

use super::cholesky::{factor_with_jitter, CholeskyError, JitterPolicy};
use super::kernel::Kernel;
use super::points::Points;
use super::vector;
use faer::linalg::triangular_solve::{solve_lower_triangular_in_place, solve_upper_triangular_in_place};
use faer::{Mat, Par};

/// A fitted exact GP over points in R^D (D = 3 for range maps and elevation tiles), targets
/// already de-meaned.
#[derive(Debug, Clone)]
pub struct ExactGp<const D: usize = 3> {
    kernel: Kernel,
    inputs: Points<D>,
    /// Lower Cholesky factor of K + Σ, packed by columns: rows j..n of column j, for every j
    /// (half the memory of a square matrix, and one unbroken stream for the variance's solve).
    factor_packed: Vec<f64>,
    alpha: Vec<f64>,
    jitter: f64,
    log_marginal_likelihood: f64,
    /// Factor on every latent variance (1 unless calibrated: [`ExactGp::set_variance_scale`]).
    variance_scale: f64,
}

impl<const D: usize> ExactGp<D> {
    /// Fits the GP to `targets` (residuals from the prior mean) at `inputs`, with per-point noise
    /// variances `noise_var` (the heteroscedastic diagonal Σ).
    ///
    /// Panics if the three slices differ in length or are empty (caller's misuse).
    pub fn fit(
        kernel: Kernel,
        inputs: Vec<[f64; D]>,
        targets: &[f64],
        noise_var: &[f64],
        jitter: JitterPolicy,
    ) -> Result<Self, CholeskyError> {
        let n = inputs.len();
        assert!(n > 0, "a GP needs at least one training point");
        assert_eq!(targets.len(), n, "one target per input");
        assert_eq!(noise_var.len(), n, "one noise variance per input");
        // Column by column in one vector pass each (`Kernel::values`); the factorisation reads
        // only the lower triangle.
        let points = Points::new(&inputs);
        let mut k = Mat::<f64>::zeros(n, n);
        for j in 0..n {
            kernel.values(&inputs[j], &points, k.col_as_slice_mut(j));
            k[(j, j)] = kernel.diagonal(&inputs[j]) + noise_var[j];
        }
        let (llt, jitter_used) = factor_with_jitter(&k, jitter)?;
        let factor = llt.L().to_owned();
        let mut rhs = Mat::from_fn(n, 1, |i, _| targets[i]);
        solve_lower_triangular_in_place(factor.as_ref(), rhs.as_mut(), Par::Seq);
        let quad: f64 = (0..n).map(|i| rhs[(i, 0)] * rhs[(i, 0)]).sum();
        let log_det_half: f64 = (0..n).map(|i| factor[(i, i)].ln()).sum();
        solve_upper_triangular_in_place(factor.transpose(), rhs.as_mut(), Par::Seq);
        let alpha = (0..n).map(|i| rhs[(i, 0)]).collect();
        let log_marginal_likelihood =
            -0.5 * quad - log_det_half - 0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln();
        let factor_packed = (0..n)
            .flat_map(|j| (j..n).map(move |i| (i, j)))
            .map(|(i, j)| factor[(i, j)])
            .collect();
        Ok(Self {
            kernel,
            factor_packed,
            alpha,
            inputs: points,
            jitter: jitter_used,
            log_marginal_likelihood,
            variance_scale: 1.0,
        })
    }

    /// Training points.
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    /// Always false: a fitted GP has at least one training point.
    pub fn is_empty(&self) -> bool {
        self.inputs.is_empty()
    }

    /// The kernel in use.
    pub fn kernel(&self) -> &Kernel {
        &self.kernel
    }

    /// Diagonal jitter the factorisation needed (0 when none).
    pub fn jitter(&self) -> f64 {
        self.jitter
    }

    /// log p(y | X, θ) of the training data.
    pub fn log_marginal_likelihood(&self) -> f64 {
        self.log_marginal_likelihood
    }

    /// Posterior mean of the residual at `x`: k*ᵀ α (O(n)).
    pub fn mean(&self, x: &[f64; D]) -> f64 {
        self.kernel.weighted_sum(x, &self.inputs, &self.alpha)
    }

    /// Euclidean distance from `x` to the nearest training input (O(n); infinite without any).
    pub fn nearest_input_distance(&self, x: &[f64; D]) -> f64 {
        let mut d2 = vec![0.0; self.inputs.len()];
        for (k, xk) in x.iter().enumerate() {
            for (d, c) in d2.iter_mut().zip(self.inputs.coord(k)) {
                *d += (c - xk) * (c - xk);
            }
        }
        d2.into_iter().fold(f64::INFINITY, f64::min).sqrt()
    }

    /// Posterior mean and latent variance k(x,x) − ‖L⁻¹ k*‖² at `x` (O(n²)); never negative.
    ///
    /// The kernel column in one vector pass, then a column-oriented forward substitution over
    /// L's packed columns (an axpy per column, `gp::vector`), into one scratch vector.
    pub fn mean_variance(&self, x: &[f64; D]) -> (f64, f64) {
        let mut v = vec![0.0; self.inputs.len()];
        self.kernel.values(x, &self.inputs, &mut v);
        let mean = v.iter().zip(&self.alpha).map(|(k, a)| k * a).sum();
        let explained = vector::forward_explained(&self.factor_packed, &mut v);
        (
            mean,
            self.variance_scale * (self.kernel.diagonal(x) - explained).max(0.0),
        )
    }
}

impl<const D: usize> ExactGp<D> {
    /// Standardised leave-one-out residuals zᵢ = αᵢ / √[(K + Σ)⁻¹]ᵢᵢ of the training targets
    /// (Rasmussen & Williams 2006, eq. 5.12): each target predicted from all the others, divided
    /// by that prediction's standard deviation. N(0, 1) when the model is right; their mean square
    /// is the factor by which (K + Σ) must be scaled for the data to agree. One triangular inverse
    /// of the factor (n³/3).
    pub fn loo_residuals(&self) -> Vec<f64> {
        let n = self.inputs.len();
        let mut inverse = Mat::<f64>::identity(n, n);
        solve_lower_triangular_in_place(self.unpacked_factor().as_ref(), inverse.as_mut(), Par::Seq);
        // (K + Σ)⁻¹ = L⁻ᵀ L⁻¹, so its diagonal is the squared norm of each column of L⁻¹.
        (0..n)
            .map(|i| {
                let column = &inverse.col_as_slice(i)[i..];
                let diag: f64 = column.iter().map(|v| v * v).sum();
                self.alpha[i] / diag.sqrt()
            })
            .collect()
    }

    /// Multiplies every latent variance by `scale` (positive, finite; panics otherwise): the
    /// posterior of (K + Σ) scaled by `scale`, whose mean is unchanged.
    pub fn set_variance_scale(&mut self, scale: f64) {
        assert!(
            scale.is_finite() && scale > 0.0,
            "variance scale must be positive"
        );
        self.variance_scale = scale;
    }

    /// The factor on every latent variance.
    pub fn variance_scale(&self) -> f64 {
        self.variance_scale
    }

    /// The packed factor as a square lower-triangular matrix (for faer's multi-column solves).
    fn unpacked_factor(&self) -> Mat<f64> {
        let n = self.inputs.len();
        let mut factor = Mat::<f64>::zeros(n, n);
        let mut packed = self.factor_packed.iter();
        for j in 0..n {
            for (f, p) in factor.col_as_slice_mut(j)[j..].iter_mut().zip(&mut packed) {
                *f = *p;
            }
        }
        factor
    }

    /// Posterior means and latent variances at many points: one multi-column triangular solve
    /// per block of 256 queries (BLAS-3), for grids and benchmarks.
    pub fn predict_batch(&self, xs: &[[f64; D]]) -> (Vec<f64>, Vec<f64>) {
        let n = self.inputs.len();
        let mut means = Vec::with_capacity(xs.len());
        let mut vars = Vec::with_capacity(xs.len());
        let factor = self.unpacked_factor();
        for block in xs.chunks(256) {
            let mut kstar = Mat::<f64>::zeros(n, block.len());
            for (j, x) in block.iter().enumerate() {
                self.kernel.values(x, &self.inputs, kstar.col_as_slice_mut(j));
            }
            for j in 0..block.len() {
                means.push((0..n).map(|i| kstar[(i, j)] * self.alpha[i]).sum());
            }
            solve_lower_triangular_in_place(factor.as_ref(), kstar.as_mut(), Par::Seq);
            for (j, x) in block.iter().enumerate() {
                let explained: f64 = (0..n).map(|i| kstar[(i, j)] * kstar[(i, j)]).sum();
                vars.push(self.variance_scale * (self.kernel.diagonal(x) - explained).max(0.0));
            }
        }
        (means, vars)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loo_residuals_match_refitting_without_each_point() {
        let k = Kernel::matern32(0.7, 0.9);
        let xs: Vec<[f64; 3]> = (0..9)
            .map(|i| [i as f64 * 0.4, (i as f64 * 0.7).sin(), 0.0])
            .collect();
        let ys: Vec<f64> = xs.iter().map(|x| (2.0 * x[0]).sin() + 0.3 * x[1]).collect();
        let noise = vec![0.01; xs.len()];
        let gp = ExactGp::fit(k, xs.clone(), &ys, &noise, JitterPolicy::default()).expect("fit");
        let z = gp.loo_residuals();
        for i in 0..xs.len() {
            let keep: Vec<usize> = (0..xs.len()).filter(|&j| j != i).collect();
            let sub = ExactGp::fit(
                k,
                keep.iter().map(|&j| xs[j]).collect(),
                &keep.iter().map(|&j| ys[j]).collect::<Vec<_>>(),
                &vec![0.01; keep.len()],
                JitterPolicy::default(),
            )
            .expect("fit without i");
            let (m, v) = sub.mean_variance(&xs[i]);
            let want = (ys[i] - m) / (v + noise[i]).sqrt();
            assert!((z[i] - want).abs() < 1e-8, "point {i}: {} vs {want}", z[i]);
        }
        let mut scaled = gp.clone();
        scaled.set_variance_scale(4.0);
        let probe = [1.1, 0.2, 0.0];
        let ((m1, v1), (m4, v4)) = (gp.mean_variance(&probe), scaled.mean_variance(&probe));
        assert_eq!(m1, m4);
        assert!((v4 - 4.0 * v1).abs() < 1e-15);
    }

    #[test]
    fn one_point_gp_matches_the_closed_form() {
        let k = Kernel::matern32(1.5, 0.8);
        let x0 = [0.0, 0.0, 1.0];
        let noise = 0.01;
        let gp = ExactGp::fit(k, vec![x0], &[0.7], &[noise], JitterPolicy::default()).expect("fit");
        let x = [0.3, 0.0, 1.0];
        let kx = k.between(&x0, &[0.3, 0.0, 1.0]);
        let (m, v) = gp.mean_variance(&x);
        assert!((m - kx / (1.5 + noise) * 0.7).abs() < 1e-14);
        assert!((v - (1.5 - kx * kx / (1.5 + noise))).abs() < 1e-14);
        let lml = -0.5 * 0.49 / 1.51 - 0.5 * 1.51f64.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln();
        assert!((gp.log_marginal_likelihood() - lml).abs() < 1e-14);
    }

    /// Fixture made by `service/tests/fixtures/make_gp_fixture.py`, an independent pure-Python
    /// implementation (its own Cholesky), so a wrong kernel or a wrong solve fails here.
    #[test]
    fn matches_the_independent_reference_fixture() {
        #[derive(serde::Deserialize)]
        struct Fixture {
            variance: f64,
            length_scale: f64,
            train_x: Vec<[f64; 3]>,
            train_y: Vec<f64>,
            noise_var: Vec<f64>,
            test_x: Vec<[f64; 3]>,
            mean: Vec<f64>,
            var: Vec<f64>,
            lml: f64,
        }
        let f: Fixture = serde_json::from_str(include_str!("../../tests/fixtures/gp_matern32.json"))
            .expect("fixture parses");
        let gp = ExactGp::fit(
            Kernel::matern32(f.variance, f.length_scale),
            f.train_x.clone(),
            &f.train_y,
            &f.noise_var,
            JitterPolicy::default(),
        )
        .expect("fit");
        assert_eq!(gp.jitter(), 0.0);
        let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-12);
        assert!(rel(gp.log_marginal_likelihood(), f.lml) < 1e-9);
        for (i, x) in f.test_x.iter().enumerate() {
            let (m, v) = gp.mean_variance(x);
            assert!(rel(m, f.mean[i]) < 1e-9, "mean {i}: {m} vs {}", f.mean[i]);
            assert!(rel(v, f.var[i]) < 1e-7, "var {i}: {v} vs {}", f.var[i]);
            assert!((gp.mean(x) - m).abs() < 1e-12);
        }
        let (means, vars) = gp.predict_batch(&f.test_x);
        for (i, x) in f.test_x.iter().enumerate() {
            let (m, v) = gp.mean_variance(x);
            assert!((means[i] - m).abs() < 1e-12 && (vars[i] - v).abs() < 1e-12);
        }
    }
}
