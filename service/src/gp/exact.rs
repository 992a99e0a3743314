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
    /// Squared standardised leave-one-out residuals of the training points, when the variance
    /// scale follows them locally ([`ExactGp::set_local_variance_scale`]).
    local_z2: Option<Vec<f64>>,
    /// The least local variance factor.
    local_floor: f64,
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
            local_z2: None,
            local_floor: LOCAL_SCALE_BOUNDS.0,
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
        let coords: [&[f64]; D] = std::array::from_fn(|k| self.inputs.coord(k));
        (0..self.inputs.len())
            .map(|i| {
                x.iter()
                    .zip(&coords)
                    .fold(0.0, |d, (xk, c)| d + (c[i] - xk) * (c[i] - xk))
            })
            .fold(f64::INFINITY, f64::min)
            .sqrt()
    }

    /// Posterior mean and latent variance k(x,x) − ‖L⁻¹ k*‖² at `x` (O(n²)); never negative.
    ///
    /// The kernel column in one vector pass, then a column-oriented forward substitution over
    /// L's packed columns (an axpy per column, `gp::vector`), into one scratch vector.
    pub fn mean_variance(&self, x: &[f64; D]) -> (f64, f64) {
        let mut v = vec![0.0; self.inputs.len()];
        self.kernel.values(x, &self.inputs, &mut v);
        let mean = v.iter().zip(&self.alpha).map(|(k, a)| k * a).sum();
        let prior = self.kernel.diagonal(x);
        let scale = self.scale_at(&v, prior);
        let explained = vector::forward_explained(&self.factor_packed, &mut v);
        (mean, scale * (prior - explained).max(0.0))
    }
}

/// Exponent on the kernel correlation that weights a training point's residual in the local
/// variance factor (higher: more local).
pub const LOCAL_SHARPNESS: i32 = 4;
/// Pseudo-points at the whole GP's factor in the local variance factor.
pub const LOCAL_PRIOR_WEIGHT: f64 = 4.0;
/// Bounds of a local variance factor.
pub const LOCAL_SCALE_BOUNDS: (f64, f64) = (0.05, 1e6);

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

    /// Makes the variance factor local: at a query point it is the mean of the training points'
    /// squared standardised leave-one-out residuals `z` (one per training point), weighted by
    /// their kernel correlation with the point raised to [`LOCAL_SHARPNESS`], together with
    /// [`LOCAL_PRIOR_WEIGHT`] pseudo-points at the whole GP's `scale`. Where the data are rough
    /// the variance widens, where the kernel explains them it narrows; far from every training
    /// point it is the whole GP's. The factor never falls below `floor` (at least
    /// [`LOCAL_SCALE_BOUNDS`]`.0`): 1 where the training targets are not independent measurements
    /// and their agreement proves nothing. Panics on a length mismatch or a non-positive scale
    /// (misuse).
    pub fn set_local_variance_scale(&mut self, z: &[f64], scale: f64, floor: f64) {
        assert_eq!(z.len(), self.inputs.len(), "one residual per training point");
        self.set_variance_scale(scale.max(floor));
        self.local_z2 = Some(z.iter().map(|v| v * v).collect());
        self.local_floor = floor.max(LOCAL_SCALE_BOUNDS.0);
    }

    /// The variance factor at a point whose kernel column is `column` and prior variance
    /// `prior`.
    fn scale_at(&self, column: &[f64], prior: f64) -> f64 {
        let Some(z2) = &self.local_z2 else {
            return self.variance_scale;
        };
        let inv = if prior > 0.0 { 1.0 / prior } else { 0.0 };
        let (mut sw, mut swz) = (0.0, 0.0);
        for (k, z) in column.iter().zip(z2) {
            let r = (k * inv).clamp(0.0, 1.0);
            let w = r.powi(LOCAL_SHARPNESS);
            sw += w;
            swz += w * z;
        }
        let s = (swz + LOCAL_PRIOR_WEIGHT * self.variance_scale) / (sw + LOCAL_PRIOR_WEIGHT);
        s.clamp(self.local_floor, LOCAL_SCALE_BOUNDS.1)
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
            let mut scales = Vec::with_capacity(block.len());
            for (j, x) in block.iter().enumerate() {
                means.push((0..n).map(|i| kstar[(i, j)] * self.alpha[i]).sum());
                scales.push(self.scale_at(kstar.col_as_slice(j), self.kernel.diagonal(x)));
            }
            solve_lower_triangular_in_place(factor.as_ref(), kstar.as_mut(), Par::Seq);
            for (j, x) in block.iter().enumerate() {
                let explained: f64 = (0..n).map(|i| kstar[(i, j)] * kstar[(i, j)]).sum();
                vars.push(scales[j] * (self.kernel.diagonal(x) - explained).max(0.0));
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
    fn a_local_variance_scale_widens_where_the_residuals_are_large_and_nowhere_else() {
        // A line of points: smooth on the left, a sharp zigzag the kernel cannot follow on the
        // right.
        let xs: Vec<[f64; 3]> = (0..60).map(|i| [i as f64 * 0.1, 0.0, 0.0]).collect();
        let ys: Vec<f64> = xs
            .iter()
            .enumerate()
            .map(|(i, x)| {
                if x[0] < 3.0 {
                    0.1 * x[0]
                } else {
                    0.3 + 0.05 * ((i % 2) as f64 - 0.5)
                }
            })
            .collect();
        let noise = vec![1e-6; xs.len()];
        let fitted = ExactGp::fit(
            Kernel::matern32(0.05, 0.5),
            xs,
            &ys,
            &noise,
            JitterPolicy::default(),
        )
        .expect("fit");
        let z = fitted.loo_residuals();
        let scale = 2.0;
        let (mut uniform, mut local) = (fitted.clone(), fitted);
        uniform.set_variance_scale(scale);
        local.set_local_variance_scale(&z, scale, 0.0);
        let ratio = |x: f64| {
            let p = [x, 0.0, 0.0];
            local.mean_variance(&p).1 / uniform.mean_variance(&p).1
        };
        assert!(ratio(1.05) < 0.5, "smooth side: {}", ratio(1.05));
        assert!(ratio(4.55) > 2.0, "rough side: {}", ratio(4.55));
        // Far from every point, the whole GP's factor.
        assert!((ratio(40.0) - 1.0).abs() < 1e-6, "far: {}", ratio(40.0));
        // The batched path applies the same factor.
        let probes = [[1.05, 0.0, 0.0], [4.55, 0.0, 0.0], [2.97, 0.1, 0.0]];
        let (means, vars) = local.predict_batch(&probes);
        for (k, p) in probes.iter().enumerate() {
            let (m, v) = local.mean_variance(p);
            assert!((means[k] - m).abs() < 1e-12 && (vars[k] - v).abs() <= 1e-9 * v);
        }
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
