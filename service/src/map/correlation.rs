//! Prequential estimate of how the maps' height errors correlate between nearby points: what
//! turns the calibrated σ of heights into the σ of a slope (docs/ARCHITECTURE.md "Planner
//! layers").
//!
//! Pairs of a new scan's returns a footprint apart are answered by the maps as they stood before
//! the scan. For a pair (p, q) with residuals eₚ, e_q, the maps' calibrated σₚ, σ_q and the
//! returns' noise variances nₚ, n_q (independent between returns), each residual is standardised
//! by its whole predicted spread, zₚ = eₚ / √(σₚ² + nₚ), and clipped to ±[`CLIP_SD`]; the noise's
//! share of its variance is mₚ = nₚ / (σₚ² + nₚ). The correlation of the maps' errors is then
//! ρ = Σ zₚz_q / √(Σ (zₚ² − mₚ) · Σ (z_q² − m_q)): the correlation of the residuals with the noise
//! taken out of their variances. It needs no assumption on how wide σ is (a σ off by a factor k
//! scales both sides alike; the calibration targets coverage, not variance). The clip keeps a
//! few wild pairs of heavy-tailed errors from deciding it, and the whole spread keeps pairs whose
//! returns' noise dwarfs σ from swamping the sums (divided by σ alone, a pair with σ of a
//! millimetre and 3 cm of noise adds a square that is noise 900 times over: such sums cancel to
//! nearly nothing and ρ runs to 1). The Matérn-3/2 length whose mean correlation at the pairs'
//! separations matches ρ is the one planner layers use.

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
/// Standardised residuals are clipped to ± this (a Gaussian's lose under 0.1 % of their
/// variance; a heavy tail's few wild pairs lose their hold on the sums).
pub const CLIP_SD: f64 = 4.0;

/// One tested pair's standardised terms.
#[derive(Debug, Clone, Copy)]
struct Pair {
    /// zₚz_q.
    cross: f64,
    /// zₚ² − mₚ and z_q² − m_q.
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
            let [s1, s2] = p.sd_m;
            let [n1, n2] = p.noise_var_m2;
            if !(s1 > 0.0 && s2 > 0.0 && n1 >= 0.0 && n2 >= 0.0) {
                continue;
            }
            let (v1, v2) = (s1 * s1 + n1, s2 * s2 + n2);
            let [z1, z2] = [p.residual_m[0] / v1.sqrt(), p.residual_m[1] / v2.sqrt()]
                .map(|z| z.clamp(-CLIP_SD, CLIP_SD));
            let pair = Pair {
                cross: z1 * z2,
                square: [z1 * z1 - n1 / v1, z2 * z2 - n2 / v2],
                d: p.separation_m,
            };
            let finite = pair.cross.is_finite() && pair.square.iter().all(|v| v.is_finite());
            if !(finite && pair.d.is_finite()) {
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
        self.learnt().unwrap_or_default()
    }

    /// [`Self::correlation`] where it is learnt from the pairs; `None` where it is the default.
    pub fn learnt(&self) -> Option<ErrorCorrelation> {
        let [v1, v2] = self
            .pairs
            .iter()
            .fold([0.0; 2], |[a, b], p| [a + p.square[0], b + p.square[1]]);
        if self.pairs.len() < MIN_PAIRS || v1 <= 0.0 || v2 <= 0.0 {
            return None;
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
        Some(ErrorCorrelation {
            length_m: (0.5 * (lo + hi)).exp(),
        })
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
        let pairs = pairs(truth, [0.02, 0.03], 0.01, PAIR_MEMORY, &mut rng);
        learner.observe(&pairs);
        let got = learner.correlation().length_m;
        assert!(
            (got / truth.length_m - 1.0).abs() < 0.25,
            "learnt {got} m for 0.8 m"
        );
    }

    /// Pairs of errors correlated by `truth`, the errors of sd `sd` plus the returns' noise of sd
    /// `noise`, at separations across the learner's range.
    fn pairs(
        truth: ErrorCorrelation,
        sd: [f64; 2],
        noise: f64,
        count: usize,
        rng: &mut impl Rng,
    ) -> Vec<PairResidual> {
        (0..count)
            .map(|_| {
                let d = rng.random_range(PAIR_SEPARATION_M.0..PAIR_SEPARATION_M.1);
                let rho = truth.at(d);
                let (a, b) = (normal(rng), normal(rng));
                PairResidual {
                    residual_m: [
                        sd[0] * a + noise * normal(rng),
                        sd[1] * (rho * a + (1.0 - rho * rho).sqrt() * b) + noise * normal(rng),
                    ],
                    sd_m: sd,
                    noise_var_m2: [noise * noise; 2],
                    separation_m: d,
                }
            })
            .collect()
    }

    #[test]
    fn pairs_whose_noise_dwarfs_sigma_and_two_wild_pairs_do_not_decide_the_length() {
        let truth = ErrorCorrelation { length_m: 0.25 };
        assert_ne!(truth, ErrorCorrelation::default());
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        // Where the maps are sure (σ 1 mm) and the returns noisy (3 cm), as a VLP-16's near
        // its own data; the rest as elsewhere.
        let mut all = pairs(truth, [0.02; 2], 0.01, 2200, &mut rng);
        all.extend(pairs(truth, [0.001; 2], 0.03, 1760, &mut rng));
        // Two wild pairs: both returns a metre off the same way (a shadow's edge), 50 σ.
        all.extend((0..2).map(|k| PairResidual {
            residual_m: [1.0; 2],
            sd_m: [0.02; 2],
            noise_var_m2: [1e-4; 2],
            separation_m: 0.2 + 0.1 * k as f64,
        }));
        use rand::seq::SliceRandom;
        all.shuffle(&mut rng);
        let mut learner = CorrelationLearner::default();
        learner.observe(&all);
        let got = learner.correlation().length_m;
        assert!(
            (got / truth.length_m - 1.0).abs() < 0.25,
            "learnt {got} m for {} m",
            truth.length_m
        );
    }
}
