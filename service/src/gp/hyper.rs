//! Hyperparameter learning: maximise the log marginal likelihood over (log σ², log ℓ) with
//! L-BFGS (argmin, More–Thuente line search), bounded by a smooth sigmoid reparametrisation.
//! [`OnlineHyperparameters`] is the per-scan mode: warm start, a few iterations, smoothing.

use super::kernel::Kernel;
use super::likelihood::{lml_with_gradient, TrainingSet};
use argmin::core::{CostFunction, Executor, Gradient, State};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;
use thiserror::Error;

/// Box bounds of the hyperparameters (natural units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HyperBounds {
    /// (min, max) of σ².
    pub variance: (f64, f64),
    /// (min, max) of ℓ (seed 000 capped ℓ at 50).
    pub length_scale: (f64, f64),
}

impl Default for HyperBounds {
    fn default() -> Self {
        Self {
            variance: (1e-4, 1e3),
            length_scale: (1e-2, 50.0),
        }
    }
}

/// Result of a hyperparameter fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HyperFit {
    /// Optimal σ².
    pub variance: f64,
    /// Optimal ℓ.
    pub length_scale: f64,
    /// log marginal likelihood there.
    pub lml: f64,
    /// L-BFGS iterations run.
    pub iterations: u64,
}

/// The fit failed numerically.
#[derive(Debug, Error)]
pub enum HyperError {
    /// The likelihood could not be evaluated (singular matrix) or the optimiser failed.
    #[error("hyperparameter optimisation failed: {0}")]
    Optimiser(String),
}

/// Maps an unconstrained u to log θ in [lo, hi] and back.
#[derive(Debug, Clone, Copy)]
struct Squash {
    lo: f64,
    hi: f64,
}

impl Squash {
    fn new((lo, hi): (f64, f64)) -> Self {
        assert!(lo > 0.0 && hi > lo, "bounds must satisfy 0 < lo < hi");
        Self {
            lo: lo.ln(),
            hi: hi.ln(),
        }
    }
    fn log_theta(&self, u: f64) -> f64 {
        self.lo + (self.hi - self.lo) / (1.0 + (-u).exp())
    }
    fn dlog_du(&self, u: f64) -> f64 {
        let s = 1.0 / (1.0 + (-u).exp());
        (self.hi - self.lo) * s * (1.0 - s)
    }
    fn u_of(&self, log_theta: f64) -> f64 {
        let s = ((log_theta - self.lo) / (self.hi - self.lo)).clamp(1e-9, 1.0 - 1e-9);
        (s / (1.0 - s)).ln()
    }
}

struct Problem<'a> {
    kernel: Kernel,
    data: TrainingSet<'a>,
    squash: [Squash; 2],
}

impl Problem<'_> {
    fn kernel_at(&self, u: &[f64]) -> Kernel {
        self.kernel.with(
            self.squash[0].log_theta(u[0]).exp(),
            self.squash[1].log_theta(u[1]).exp(),
        )
    }
    fn eval(&self, u: &[f64]) -> Result<(f64, Vec<f64>), argmin::core::Error> {
        let (lml, g) = lml_with_gradient(&self.kernel_at(u), self.data)
            .map_err(|e| argmin::core::Error::msg(e.to_string()))?;
        Ok((
            -lml,
            vec![
                -g[0] * self.squash[0].dlog_du(u[0]),
                -g[1] * self.squash[1].dlog_du(u[1]),
            ],
        ))
    }
}

impl CostFunction for Problem<'_> {
    type Param = Vec<f64>;
    type Output = f64;
    fn cost(&self, u: &Self::Param) -> Result<f64, argmin::core::Error> {
        Ok(self.eval(u)?.0)
    }
}

impl Gradient for Problem<'_> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;
    fn gradient(&self, u: &Self::Param) -> Result<Vec<f64>, argmin::core::Error> {
        Ok(self.eval(u)?.1)
    }
}

/// Maximises the log marginal likelihood starting from `start`'s hyperparameters, at most
/// `max_iters` L-BFGS iterations, inside `bounds`.
pub fn fit_hyperparameters(
    start: &Kernel,
    data: TrainingSet<'_>,
    bounds: HyperBounds,
    max_iters: u64,
) -> Result<HyperFit, HyperError> {
    let squash = [Squash::new(bounds.variance), Squash::new(bounds.length_scale)];
    let u0 = vec![
        squash[0].u_of(start.variance.ln()),
        squash[1].u_of(start.length_scale.ln()),
    ];
    let problem = Problem {
        kernel: *start,
        data,
        squash,
    };
    let linesearch = MoreThuenteLineSearch::new();
    let solver = LBFGS::new(linesearch, 7)
        .with_tolerance_grad(1e-6)
        .and_then(|s| s.with_tolerance_cost(1e-10))
        .map_err(|e| HyperError::Optimiser(e.to_string()))?;
    let result = Executor::new(problem, solver)
        .configure(|state| state.param(u0).max_iters(max_iters))
        .run()
        .map_err(|e| HyperError::Optimiser(e.to_string()))?;
    let state = result.state();
    let u = state
        .get_best_param()
        .ok_or_else(|| HyperError::Optimiser("no parameter was evaluated".into()))?;
    let kernel = Problem {
        kernel: *start,
        data,
        squash,
    }
    .kernel_at(u);
    Ok(HyperFit {
        variance: kernel.variance,
        length_scale: kernel.length_scale,
        lml: -state.get_best_cost(),
        iterations: state.get_iter(),
    })
}

/// Online hyperparameters: each scan warm-starts a short L-BFGS run from the current estimate,
/// and the estimate moves towards its result by exponential smoothing in log space.
#[derive(Debug, Clone, PartialEq)]
pub struct OnlineHyperparameters {
    kernel: Kernel,
    bounds: HyperBounds,
    iterations: u64,
    smoothing: f64,
    updates: u64,
}

impl OnlineHyperparameters {
    /// Starts from `initial`; each update runs `iterations` L-BFGS steps and moves the estimate by
    /// `smoothing` ∈ (0, 1] of the way (the first update moves all the way).
    pub fn new(initial: Kernel, bounds: HyperBounds, iterations: u64, smoothing: f64) -> Self {
        assert!(smoothing > 0.0 && smoothing <= 1.0, "smoothing must be in (0, 1]");
        Self {
            kernel: initial,
            bounds,
            iterations,
            smoothing,
            updates: 0,
        }
    }

    /// The current estimate.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// Updates applied so far.
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// One update from one scan's training subset.
    pub fn update(&mut self, data: TrainingSet<'_>) -> Result<HyperFit, HyperError> {
        let fit = fit_hyperparameters(&self.kernel, data, self.bounds, self.iterations)?;
        let eta = if self.updates == 0 { 1.0 } else { self.smoothing };
        let blend = |old: f64, new: f64| ((1.0 - eta) * old.ln() + eta * new.ln()).exp();
        self.kernel = self.kernel.with(
            blend(self.kernel.variance, fit.variance),
            blend(self.kernel.length_scale, fit.length_scale),
        );
        self.updates += 1;
        Ok(fit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::likelihood::lml_with_gradient;
    use crate::gp::sphere::to_sphere;

    /// 150 rays on the seed-000 field of view with ranges drawn from a GP prior with
    /// σ² = 2, ℓ = 1.2 (so the likelihood has an interior maximum near them).
    fn data() -> (Vec<[f64; 3]>, Vec<f64>, Vec<f64>) {
        use faer::Mat;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(42);
        let x: Vec<[f64; 3]> = (0..150)
            .map(|_| {
                to_sphere(
                    rng.random_range(1.571..1.833),
                    rng.random_range(-1.571..1.571),
                    10.0,
                )
            })
            .collect();
        let truth = Kernel::matern32(2.0, 1.2);
        let noise = 1e-4;
        let k = Mat::from_fn(x.len(), x.len(), |i, j| {
            truth.between(&x[i], &x[j]) + if i == j { noise } else { 0.0 }
        });
        let (llt, _) = crate::gp::factor_with_jitter(&k, crate::gp::JitterPolicy::default()).expect("chol");
        let z: Vec<f64> = (0..x.len())
            .map(|_| rangegp_sim::sensor::standard_normal(&mut rng))
            .collect();
        let l = llt.L();
        let y = (0..x.len())
            .map(|i| (0..=i).map(|j| l[(i, j)] * z[j]).sum())
            .collect();
        (x, y, vec![noise; 150])
    }

    #[test]
    fn lbfgs_reaches_a_stationary_maximum_inside_the_bounds() {
        let (x, y, s) = data();
        let set = TrainingSet {
            inputs: &x,
            targets: &y,
            noise_var: &s,
        };
        let start = Kernel::matern32(2.5, 0.15);
        let fit = fit_hyperparameters(&start, set, HyperBounds::default(), 100).expect("fit");
        let (start_lml, _) = lml_with_gradient(&start, set).expect("lml");
        assert!(
            fit.lml > start_lml + 1.0,
            "no improvement: {} vs {start_lml}",
            fit.lml
        );
        let (lml, grad) = lml_with_gradient(&start.with(fit.variance, fit.length_scale), set).expect("lml");
        assert!((lml - fit.lml).abs() < 1e-8);
        assert!(
            grad[0].abs() < 1e-2 && grad[1].abs() < 1e-2,
            "gradient at optimum {grad:?}"
        );
        // Neighbours in log space are no better.
        for (dv, dl) in [(0.05, 0.0), (-0.05, 0.0), (0.0, 0.05), (0.0, -0.05)] {
            let k = start.with(fit.variance * f64::exp(dv), fit.length_scale * f64::exp(dl));
            assert!(lml_with_gradient(&k, set).expect("lml").0 <= fit.lml + 1e-9);
        }
    }

    #[test]
    fn bounds_hold_when_the_optimum_is_outside() {
        let (x, y, s) = data();
        let set = TrainingSet {
            inputs: &x,
            targets: &y,
            noise_var: &s,
        };
        let bounds = HyperBounds {
            variance: (1e-2, 1e2),
            length_scale: (5.0, 50.0),
        };
        let fit = fit_hyperparameters(&Kernel::matern32(1.0, 10.0), set, bounds, 60).expect("fit");
        assert!(fit.length_scale >= 5.0 - 1e-9 && fit.length_scale <= 50.0 + 1e-9);
        assert!(fit.variance >= 1e-2 - 1e-12 && fit.variance <= 1e2 + 1e-9);
    }

    #[test]
    fn online_updates_converge_to_the_batch_optimum_on_stationary_data() {
        let (x, y, s) = data();
        let set = TrainingSet {
            inputs: &x,
            targets: &y,
            noise_var: &s,
        };
        let batch = fit_hyperparameters(&Kernel::matern32(2.5, 0.15), set, HyperBounds::default(), 200)
            .expect("batch");
        let mut online =
            OnlineHyperparameters::new(Kernel::matern32(2.5, 0.15), HyperBounds::default(), 3, 0.3);
        for _ in 0..15 {
            online.update(set).expect("update");
        }
        let k = online.kernel();
        assert!(
            (k.length_scale / batch.length_scale).ln().abs() < 0.05,
            "{} vs {}",
            k.length_scale,
            batch.length_scale
        );
        assert!(
            (k.variance / batch.variance).ln().abs() < 0.1,
            "{} vs {}",
            k.variance,
            batch.variance
        );
    }
}
