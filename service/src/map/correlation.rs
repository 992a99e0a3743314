//! Prequential estimate of how the maps' height errors correlate between nearby points: what
//! turns the calibrated σ of heights into the σ of a slope (docs/ARCHITECTURE.md "Planner
//! layers").
//!
//! Pairs of a new scan's returns a footprint apart are answered by the maps as they stood before
//! the scan. For a pair (p, q) with residuals eₚ, e_q, the maps' calibrated σₚ, σ_q and the
//! returns' noise variances nₚ, n_q (independent between returns), the correlation of the maps'
//! errors is the correlation coefficient of the standardised residuals, the noise taken out of
//! their variances: ρ = Σ eₚe_q/(σₚσ_q) / √(Σ (eₚ² − nₚ)/σₚ² · Σ (e_q² − n_q)/σ_q²). It needs no
//! assumption on how wide σ is (the calibration targets coverage, not variance, and the errors
//! are heavy-tailed). The Matérn-3/2 length whose mean correlation at the pairs' separations
//! matches ρ is the one planner layers use.

use super::scales::ErrorCorrelation;
use std::collections::VecDeque;

/// Pairs are this far apart at least and at most, metres (a robot footprint's scale).
pub const PAIR_SEPARATION_M: (f64, f64) = (0.15, 0.45);
/// Pairs remembered (the oldest drop out: the estimate follows the terrain).
pub const PAIR_MEMORY: usize = 4000;
/// Pairs held before the estimate replaces the default.
pub const MIN_PAIRS: usize = 300;
/// Bounds of the estimated length, metres.
pub const LENGTH_BOUNDS_M: (f64, f64) = (0.05, 5.0);

/// One tested pair's standardised terms.
#[derive(Debug, Clone, Copy)]
struct Pair {
    /// eₚe_q / (σₚσ_q).
    cross: f64,
    /// (eₚ² − nₚ) / σₚ² and (e_q² − n_q) / σ_q².
    square: [f64; 2],
    /// Separation, metres.
    d: f64,
}

/// A tested pair of returns: their residuals against the maps, the maps' calibrated σ there,
/// the returns' noise variances along z, and their horizontal separation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairResidual {
    /// Residuals (return height minus the maps' height), metres.
    pub residual_m: [f64; 2],
    /// Calibrated σ of the maps' answers, metres.
    pub sd_m: [f64; 2],
    /// Noise variance of each return along z, m².
    pub noise_var_m2: [f64; 2],
    /// Horizontal distance between the two returns, metres.
    pub separation_m: f64,
}

/// The recent pairs and the correlation they give.
#[derive(Debug, Clone, Default)]
pub struct CorrelationLearner {
    pairs: VecDeque<Pair>,
}

impl CorrelationLearner {
    /// Adds tested pairs (those with a non-finite term or no σ are skipped).
    pub fn observe(&mut self, pairs: &[PairResidual]) {
        for p in pairs {
            let [e1, e2] = p.residual_m;
            let [s1, s2] = p.sd_m;
            let pair = Pair {
                cross: e1 * e2 / (s1 * s2),
                square: [
                    (e1 * e1 - p.noise_var_m2[0]) / (s1 * s1),
                    (e2 * e2 - p.noise_var_m2[1]) / (s2 * s2),
                ],
                d: p.separation_m,
            };
            let finite = pair.cross.is_finite() && pair.square.iter().all(|v| v.is_finite());
            if !(finite && s1 > 0.0 && s2 > 0.0 && pair.d.is_finite()) {
                continue;
            }
            if self.pairs.len() == PAIR_MEMORY {
                self.pairs.pop_front();
            }
            self.pairs.push_back(pair);
        }
    }

    /// The correlation the pairs give: the default until [`MIN_PAIRS`] are held (or while
    /// the noise leaves no error variance to correlate), then the Matérn-3/2 length whose mean
    /// correlation at the pairs' separations equals the estimated ρ (clamped to
    /// [`LENGTH_BOUNDS_M`]).
    pub fn correlation(&self) -> ErrorCorrelation {
        let [v1, v2] = self
            .pairs
            .iter()
            .fold([0.0; 2], |[a, b], p| [a + p.square[0], b + p.square[1]]);
        if self.pairs.len() < MIN_PAIRS || v1 <= 0.0 || v2 <= 0.0 {
            return ErrorCorrelation::default();
        }
        let rho = (self.pairs.iter().map(|p| p.cross).sum::<f64>() / (v1 * v2).sqrt()).clamp(0.0, 1.0);
        let n = self.pairs.len() as f64;
        let at = |length: f64| {
            let c = ErrorCorrelation { length_m: length };
            self.pairs.iter().map(|p| c.at(p.d)).sum::<f64>() / n
        };
        let (mut lo, mut hi) = (LENGTH_BOUNDS_M.0.ln(), LENGTH_BOUNDS_M.1.ln());
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if at(mid.exp()) < rho {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        ErrorCorrelation {
            length_m: (0.5 * (lo + hi)).exp(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn normal(rng: &mut impl Rng) -> f64 {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    #[test]
    fn pairs_with_a_known_correlation_give_back_its_length() {
        let truth = ErrorCorrelation { length_m: 0.8 };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut learner = CorrelationLearner::default();
        assert_eq!(learner.correlation(), ErrorCorrelation::default());
        let mut pairs = Vec::new();
        for _ in 0..PAIR_MEMORY {
            let d = rng.random_range(PAIR_SEPARATION_M.0..PAIR_SEPARATION_M.1);
            let rho = truth.at(d);
            let (s1, s2, noise) = (0.02, 0.03, 0.01f64);
            let (a, b) = (normal(&mut rng), normal(&mut rng));
            let e1 = s1 * a + noise * normal(&mut rng);
            let e2 = s2 * (rho * a + (1.0 - rho * rho).sqrt() * b) + noise * normal(&mut rng);
            pairs.push(PairResidual {
                residual_m: [e1, e2],
                sd_m: [s1, s2],
                noise_var_m2: [noise * noise; 2],
                separation_m: d,
            });
        }
        learner.observe(&pairs);
        let got = learner.correlation().length_m;
        assert!(
            (got / truth.length_m - 1.0).abs() < 0.25,
            "learnt {got} m for 0.8 m"
        );
    }
}
