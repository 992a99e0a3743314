//! Log marginal likelihood of a GP and its analytic gradient in (log σ², log ℓ)
//! (seed 001 eq. 13, seed 002 eq. 6; Rasmussen & Williams eq. 5.9).

use super::cholesky::{factor_with_jitter, CholeskyError, JitterPolicy};
use super::kernel::Kernel;
use faer::linalg::triangular_solve::{solve_lower_triangular_in_place, solve_upper_triangular_in_place};
use faer::{Mat, Par};

/// Training data of a GP: inputs, de-meaned targets and per-point noise variances.
#[derive(Debug, Clone, Copy)]
pub struct TrainingSet<'a> {
    /// Inputs.
    pub inputs: &'a [[f64; 3]],
    /// Targets minus the prior mean.
    pub targets: &'a [f64],
    /// Noise variance of each target (the heteroscedastic diagonal).
    pub noise_var: &'a [f64],
}

impl TrainingSet<'_> {
    fn check(&self) {
        assert!(!self.inputs.is_empty(), "a GP needs at least one training point");
        assert_eq!(self.targets.len(), self.inputs.len(), "one target per input");
        assert_eq!(
            self.noise_var.len(),
            self.inputs.len(),
            "one noise variance per input"
        );
    }
}

/// log p(y | X, θ) = −½ yᵀα − Σ log Lᵢᵢ − n/2 log 2π and ∂/∂(log σ², log ℓ) =
/// ½ tr((ααᵀ − K⁻¹) ∂K/∂θ). O(n³): meant for the few hundred rays of a hyperparameter step.
pub fn lml_with_gradient(kernel: &Kernel, data: TrainingSet<'_>) -> Result<(f64, [f64; 2]), CholeskyError> {
    data.check();
    let n = data.inputs.len();
    let mut k = Mat::<f64>::zeros(n, n);
    let mut dk = [Mat::<f64>::zeros(n, n), Mat::<f64>::zeros(n, n)];
    for j in 0..n {
        for i in j..n {
            let (v, g) = kernel.with_gradient(&data.inputs[i], &data.inputs[j]);
            k[(i, j)] = v;
            k[(j, i)] = v;
            for p in 0..2 {
                dk[p][(i, j)] = g[p];
                dk[p][(j, i)] = g[p];
            }
        }
        k[(j, j)] += data.noise_var[j];
    }
    let (llt, _) = factor_with_jitter(&k, JitterPolicy::default())?;
    let l = llt.L();
    let mut alpha = Mat::from_fn(n, 1, |i, _| data.targets[i]);
    solve_lower_triangular_in_place(l, alpha.as_mut(), Par::Seq);
    let quad: f64 = (0..n).map(|i| alpha[(i, 0)] * alpha[(i, 0)]).sum();
    solve_upper_triangular_in_place(l.transpose(), alpha.as_mut(), Par::Seq);
    let log_det_half: f64 = (0..n).map(|i| l[(i, i)].ln()).sum();
    let lml = -0.5 * quad - log_det_half - 0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln();
    let mut inv = Mat::<f64>::identity(n, n);
    solve_lower_triangular_in_place(l, inv.as_mut(), Par::Seq);
    solve_upper_triangular_in_place(l.transpose(), inv.as_mut(), Par::Seq);
    let mut grad = [0.0; 2];
    for j in 0..n {
        for i in 0..n {
            let w = alpha[(i, 0)] * alpha[(j, 0)] - inv[(i, j)];
            grad[0] += w * dk[0][(i, j)];
            grad[1] += w * dk[1][(i, j)];
        }
    }
    Ok((lml, [0.5 * grad[0], 0.5 * grad[1]]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::kernel::KernelFamily;
    use crate::gp::sphere::to_sphere;

    fn data() -> (Vec<[f64; 3]>, Vec<f64>, Vec<f64>) {
        let mut inputs = Vec::new();
        let mut targets = Vec::new();
        for i in 0..60 {
            let t = 1.6 + 0.004 * (i % 12) as f64 * 4.0;
            let p = -1.2 + 0.045 * i as f64;
            inputs.push(to_sphere(t, p, 10.0));
            targets.push((3.0 * p).sin() * 0.4 + 0.1 * (7.0 * t).cos());
        }
        let noise = targets.iter().map(|_| 1e-4).collect();
        (inputs, targets, noise)
    }

    #[test]
    fn gradient_equals_finite_differences() {
        let (x, y, s) = data();
        let set = TrainingSet {
            inputs: &x,
            targets: &y,
            noise_var: &s,
        };
        for family in [
            KernelFamily::Matern32,
            KernelFamily::Matern52,
            KernelFamily::SquaredExponential,
        ] {
            let k = Kernel::new(family, 0.9, 1.1);
            let (_, grad) = lml_with_gradient(&k, set).expect("lml");
            let h = 1e-5;
            let at = |dv: f64, dl: f64| {
                lml_with_gradient(&k.with(0.9 * f64::exp(dv), 1.1 * f64::exp(dl)), set)
                    .expect("lml")
                    .0
            };
            let fd = [
                (at(h, 0.0) - at(-h, 0.0)) / (2.0 * h),
                (at(0.0, h) - at(0.0, -h)) / (2.0 * h),
            ];
            for p in 0..2 {
                let rel = (grad[p] - fd[p]).abs() / fd[p].abs().max(1e-6);
                assert!(
                    rel < 1e-5,
                    "{family:?} ∂{p}: analytic {} vs fd {}",
                    grad[p],
                    fd[p]
                );
            }
        }
    }

    #[test]
    fn lml_equals_the_exact_gp_fit() {
        let (x, y, s) = data();
        let k = Kernel::matern32(0.9, 1.1);
        let (lml, _) = lml_with_gradient(
            &k,
            TrainingSet {
                inputs: &x,
                targets: &y,
                noise_var: &s,
            },
        )
        .expect("lml");
        let gp = crate::gp::ExactGp::fit(k, x, &y, &s, JitterPolicy::default()).expect("fit");
        assert!((lml - gp.log_marginal_likelihood()).abs() < 1e-9);
    }

    /// Fixture from `service/tests/fixtures/make_sklearn_fixture.py` (scikit-learn 1.9.1).
    #[test]
    fn matches_scikit_learn_to_1e6_relative() {
        #[derive(serde::Deserialize)]
        struct Case {
            family: String,
            alpha: Option<f64>,
            variance: f64,
            length_scale: f64,
            lml: f64,
            lml_gradient: Vec<f64>,
            mean: Vec<f64>,
            std: Vec<f64>,
        }
        #[derive(serde::Deserialize)]
        struct Fixture {
            train_x: Vec<[f64; 3]>,
            train_y: Vec<f64>,
            noise_var: Vec<f64>,
            test_x: Vec<[f64; 3]>,
            cases: Vec<Case>,
        }
        let f: Fixture =
            serde_json::from_str(include_str!("../../tests/fixtures/sklearn_gp.json")).expect("fixture");
        let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-9);
        for c in &f.cases {
            let family = match c.family.as_str() {
                "matern32" => KernelFamily::Matern32,
                "matern52" => KernelFamily::Matern52,
                "squared_exponential" => KernelFamily::SquaredExponential,
                "rational_quadratic" => KernelFamily::RationalQuadratic {
                    alpha: c.alpha.expect("alpha"),
                },
                other => panic!("unknown family {other}"),
            };
            let k = Kernel::new(family, c.variance, c.length_scale);
            let set = TrainingSet {
                inputs: &f.train_x,
                targets: &f.train_y,
                noise_var: &f.noise_var,
            };
            let (lml, grad) = lml_with_gradient(&k, set).expect("lml");
            assert!(rel(lml, c.lml) < 1e-6, "{}: lml {lml} vs {}", c.family, c.lml);
            for (p, (got, want)) in grad.iter().zip(&c.lml_gradient).enumerate() {
                assert!(rel(*got, *want) < 1e-6, "{}: grad {p} {got} vs {want}", c.family);
            }
            let gp = crate::gp::ExactGp::fit(
                k,
                f.train_x.clone(),
                &f.train_y,
                &f.noise_var,
                JitterPolicy::default(),
            )
            .expect("fit");
            for (i, x) in f.test_x.iter().enumerate() {
                let (m, v) = gp.mean_variance(x);
                assert!(
                    rel(m, c.mean[i]) < 1e-6,
                    "{}: mean {i} {m} vs {}",
                    c.family,
                    c.mean[i]
                );
                assert!(
                    rel(v, c.std[i] * c.std[i]) < 1e-6,
                    "{}: var {i} {v} vs {}",
                    c.family,
                    c.std[i] * c.std[i]
                );
            }
        }
    }
}
