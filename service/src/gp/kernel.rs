//! Covariance kernels over points of R^D (kernel inputs of the range maps, the ground plane, the
//! pose-augmented aggregate), with analytic
//! derivatives with respect to log σ² and log ℓ for marginal-likelihood optimisation.

use super::points::Points;
use super::vector::{self, Profile};
use serde::{Deserialize, Serialize};

/// Kernel families (docs/MATH.md "Kernels"; seeds 000, 001, 002, 004).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "family")]
pub enum KernelFamily {
    /// Matérn ν = 3/2 (seed 000 eq. 6, scikit-learn convention): σ²(1 + s) e^(−s), s = √3 d/ℓ.
    Matern32,
    /// Matérn ν = 5/2: σ²(1 + s + s²/3) e^(−s), s = √5 d/ℓ.
    Matern52,
    /// Squared exponential: σ² exp(−d²/2ℓ²).
    SquaredExponential,
    /// Rational quadratic (seed 001 eq. 12): σ²(1 + d²/2αℓ²)^(−α).
    RationalQuadratic {
        /// Scale-mixture parameter α > 0 (fixed, not optimised).
        alpha: f64,
    },
    /// Neural-network / arcsine kernel (seed 002 eq. 5) with Σ = diag(1, ℓ⁻², ℓ⁻², ℓ⁻²):
    /// σ² asin(2 x̃ᵀΣx̃′ / √((1 + 2x̃ᵀΣx̃)(1 + 2x̃′ᵀΣx̃′))), x̃ = (1, x). Not stationary.
    ArcSine,
}

/// A kernel: family, variance σ² and length scale ℓ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kernel {
    /// Family.
    pub family: KernelFamily,
    /// Variance σ² (scikit-learn's "constant value").
    pub variance: f64,
    /// Length scale ℓ, in the units of the inputs.
    pub length_scale: f64,
}

/// Euclidean distance between two points of R^D.
#[inline]
pub fn distance<const D: usize>(a: &[f64; D], b: &[f64; D]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

#[inline]
fn dot<const D: usize>(a: &[f64; D], b: &[f64; D]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

impl Kernel {
    /// Builds a kernel; panics on non-positive or non-finite parameters (caller's misuse).
    pub fn new(family: KernelFamily, variance: f64, length_scale: f64) -> Self {
        assert!(
            variance.is_finite() && variance > 0.0,
            "kernel variance must be positive, got {variance}"
        );
        assert!(
            length_scale.is_finite() && length_scale > 0.0,
            "length scale must be positive, got {length_scale}"
        );
        if let KernelFamily::RationalQuadratic { alpha } = family {
            assert!(
                alpha.is_finite() && alpha > 0.0,
                "rational-quadratic alpha must be positive"
            );
        }
        Self {
            family,
            variance,
            length_scale,
        }
    }

    /// Matérn-3/2, the default of the range GP.
    pub fn matern32(variance: f64, length_scale: f64) -> Self {
        Self::new(KernelFamily::Matern32, variance, length_scale)
    }

    /// The same family with other hyperparameters.
    pub fn with(&self, variance: f64, length_scale: f64) -> Self {
        Self::new(self.family, variance, length_scale)
    }

    /// Prior variance at `x`, k(x, x).
    #[inline]
    pub fn diagonal<const D: usize>(&self, x: &[f64; D]) -> f64 {
        match self.family {
            KernelFamily::ArcSine => self.between(x, x),
            _ => self.variance,
        }
    }

    /// Covariance between two points.
    #[inline]
    pub fn between<const D: usize>(&self, a: &[f64; D], b: &[f64; D]) -> f64 {
        match self.family {
            KernelFamily::ArcSine => self.variance * self.arcsine_z(a, b).0.asin(),
            _ => self.variance * self.unit_stationary(distance(a, b)).0,
        }
    }

    /// The exponential families as a function of squared distance (the vector paths), or
    /// `None` for the families evaluated one pair at a time.
    fn profile(&self) -> Option<Profile> {
        let l = self.length_scale;
        match self.family {
            KernelFamily::Matern32 => Some(Profile::Matern32 { c: 3f64.sqrt() / l }),
            KernelFamily::Matern52 => Some(Profile::Matern52 { c: 5f64.sqrt() / l }),
            KernelFamily::SquaredExponential => Some(Profile::SquaredExponential { c: 0.5 / (l * l) }),
            KernelFamily::RationalQuadratic { .. } | KernelFamily::ArcSine => None,
        }
    }

    /// Σᵢ k(x, xᵢ) wᵢ, the posterior mean's inner product and the hot loop of every map query
    /// (panics when the lengths differ: misuse). The exponential families go four inputs at a
    /// time through `gp::vector`; the others one by one through [`Self::between`].
    pub fn weighted_sum<const D: usize>(&self, x: &[f64; D], inputs: &Points<D>, weights: &[f64]) -> f64 {
        assert_eq!(inputs.len(), weights.len(), "one weight per input");
        match self.profile() {
            Some(p) => self.variance * vector::weighted_sum(p, x, inputs, weights),
            None => (0..inputs.len())
                .map(|i| self.between(x, &inputs.get(i)) * weights[i])
                .sum(),
        }
    }

    /// k(x, xᵢ) into `out[i]` for every input: the kernel column of a variance (panics when the
    /// lengths differ: misuse).
    pub fn values<const D: usize>(&self, x: &[f64; D], inputs: &Points<D>, out: &mut [f64]) {
        assert_eq!(inputs.len(), out.len(), "one output per input");
        match self.profile() {
            Some(p) => {
                vector::values(p, x, inputs, out);
                out.iter_mut().for_each(|v| *v *= self.variance);
            }
            None => {
                for (i, o) in out.iter_mut().enumerate() {
                    *o = self.between(x, &inputs.get(i));
                }
            }
        }
    }

    /// Covariance and its derivatives with respect to (log σ², log ℓ).
    #[inline]
    pub fn with_gradient<const D: usize>(&self, a: &[f64; D], b: &[f64; D]) -> (f64, [f64; 2]) {
        match self.family {
            KernelFamily::ArcSine => {
                let (z, dz_dlog_ell) = self.arcsine_z(a, b);
                let k = self.variance * z.asin();
                let dk = self.variance / (1.0 - z * z).max(1e-300).sqrt() * dz_dlog_ell;
                (k, [k, dk])
            }
            _ => {
                let (unit, dunit) = self.unit_stationary(distance(a, b));
                let k = self.variance * unit;
                (k, [k, self.variance * dunit])
            }
        }
    }

    /// Unit-variance stationary kernel at distance `d` and its derivative in log ℓ.
    #[inline]
    fn unit_stationary(&self, d: f64) -> (f64, f64) {
        let l = self.length_scale;
        match self.family {
            KernelFamily::Matern32 => {
                let s = 3f64.sqrt() * d / l;
                let e = (-s).exp();
                ((1.0 + s) * e, s * s * e)
            }
            KernelFamily::Matern52 => {
                let s = 5f64.sqrt() * d / l;
                let e = (-s).exp();
                ((1.0 + s + s * s / 3.0) * e, s * s * (1.0 + s) / 3.0 * e)
            }
            KernelFamily::SquaredExponential => {
                let r2 = d * d / (l * l);
                let k = (-0.5 * r2).exp();
                (k, k * r2)
            }
            KernelFamily::RationalQuadratic { alpha } => {
                let u = d * d / (2.0 * alpha * l * l);
                let base = 1.0 + u;
                (base.powf(-alpha), 2.0 * u * alpha * base.powf(-alpha - 1.0))
            }
            KernelFamily::ArcSine => unreachable!("arcsine is not stationary"),
        }
    }

    /// The arcsine kernel's argument z and dz/d log ℓ.
    #[inline]
    fn arcsine_z<const D: usize>(&self, a: &[f64; D], b: &[f64; D]) -> (f64, f64) {
        let lambda = 1.0 / (self.length_scale * self.length_scale);
        let (ab, aa, bb) = (dot(a, b), dot(a, a), dot(b, b));
        let num = 2.0 * (1.0 + lambda * ab);
        let pa = 1.0 + 2.0 * (1.0 + lambda * aa);
        let pb = 1.0 + 2.0 * (1.0 + lambda * bb);
        let root = (pa * pb).sqrt();
        let z = (num / root).clamp(-1.0, 1.0);
        let dz_dlambda = 2.0 * ab / root - z * (aa / pa + bb / pb);
        (z, dz_dlambda * (-2.0 * lambda))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FAMILIES: [KernelFamily; 5] = [
        KernelFamily::Matern32,
        KernelFamily::Matern52,
        KernelFamily::SquaredExponential,
        KernelFamily::RationalQuadratic { alpha: 0.7 },
        KernelFamily::ArcSine,
    ];

    #[test]
    fn weighted_sums_and_values_match_the_scalar_kernel_for_every_family() {
        let mut rng = rand_pcg::Pcg64::new(7, 11);
        use rand::Rng;
        for family in FAMILIES {
            let k = Kernel::new(family, 1.7, 0.6);
            for n in [0, 1, 3, 4, 5, 128, 131] {
                let inputs: Vec<[f64; 3]> = (0..n)
                    .map(|_| std::array::from_fn(|_| rng.random_range(-3.0..3.0)))
                    .collect();
                let weights: Vec<f64> = (0..n).map(|_| rng.random_range(-50.0..50.0)).collect();
                let x = [0.3, -0.2, 1.1];
                let scalar: f64 = inputs
                    .iter()
                    .zip(&weights)
                    .map(|(xi, w)| k.between(&x, xi) * w)
                    .sum();
                let scale: f64 = weights.iter().map(|w| w.abs()).sum::<f64>().max(1.0);
                let points = Points::new(&inputs);
                let got = k.weighted_sum(&x, &points, &weights);
                assert!(
                    (got - scalar).abs() <= 1e-13 * scale,
                    "{family:?} n={n}: {got} vs {scalar}"
                );
                let mut values = vec![0.0; n];
                k.values(&x, &points, &mut values);
                for (v, xi) in values.iter().zip(&inputs) {
                    assert!((v - k.between(&x, xi)).abs() <= 1e-15 * k.variance, "{family:?}");
                }
            }
        }
    }

    #[test]
    fn matern32_matches_the_closed_form_at_known_distances() {
        let k = Kernel::matern32(2.0, 0.5);
        assert_eq!(k.between(&[0.0; 3], &[0.0; 3]), 2.0);
        // d = ℓ/√3 ⇒ s = 1 ⇒ k = σ² · 2 / e.
        let d = 0.5 / 3f64.sqrt();
        assert!((k.between(&[0.0; 3], &[d, 0.0, 0.0]) - 4.0 / std::f64::consts::E).abs() < 1e-15);
    }

    #[test]
    fn other_families_match_their_closed_forms() {
        let (a, b) = ([0.1, 0.2, 0.3], [0.4, -0.2, 0.9]);
        let d = distance(&a, &b);
        let se = Kernel::new(KernelFamily::SquaredExponential, 1.5, 0.8).between(&a, &b);
        assert!((se - 1.5 * (-d * d / (2.0 * 0.64)).exp()).abs() < 1e-15);
        let rq = Kernel::new(KernelFamily::RationalQuadratic { alpha: 2.0 }, 1.0, 0.8).between(&a, &b);
        assert!((rq - (1.0 + d * d / (4.0 * 0.64)).powf(-2.0)).abs() < 1e-15);
        let s = 5f64.sqrt() * d / 0.8;
        let m52 = Kernel::new(KernelFamily::Matern52, 1.0, 0.8).between(&a, &b);
        assert!((m52 - (1.0 + s + s * s / 3.0) * (-s).exp()).abs() < 1e-15);
        // Arcsine with ℓ = 1: z = 2(1 + a·b)/√((3 + 2a·a)(3 + 2b·b)).
        let z = 2.0 * (1.0 + dot(&a, &b)) / ((3.0 + 2.0 * dot(&a, &a)) * (3.0 + 2.0 * dot(&b, &b))).sqrt();
        let nn = Kernel::new(KernelFamily::ArcSine, 1.0, 1.0).between(&a, &b);
        assert!((nn - z.asin()).abs() < 1e-15);
    }

    #[test]
    fn gradients_equal_finite_differences() {
        let (a, b) = ([0.3, -0.1, 0.5], [0.9, 0.4, 0.2]);
        for family in FAMILIES {
            let k = Kernel::new(family, 1.7, 0.6);
            let (value, grad) = k.with_gradient(&a, &b);
            assert!((value - k.between(&a, &b)).abs() < 1e-15);
            let h = 1e-6;
            let bump = |dv: f64, dl: f64| {
                Kernel::new(family, 1.7 * f64::exp(dv), 0.6 * f64::exp(dl)).between(&a, &b)
            };
            let fd = [
                (bump(h, 0.0) - bump(-h, 0.0)) / (2.0 * h),
                (bump(0.0, h) - bump(0.0, -h)) / (2.0 * h),
            ];
            for i in 0..2 {
                let rel = (grad[i] - fd[i]).abs() / fd[i].abs().max(1e-8);
                assert!(rel < 1e-6, "{family:?} ∂{i}: {} vs {}", grad[i], fd[i]);
            }
        }
    }
}
