//! Accuracy and calibration scores of a set of predictions against ground truth (docs/MATH.md
//! "Metrics"; seed 003 eqs. 26–27, seed 004 Table I): RMSE, median and maximum absolute error,
//! NLPD, 68 % / 95 % interval coverage and AUSE.

use serde::Serialize;

/// One prediction scored against the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Predicted mean.
    pub mean: f64,
    /// Predicted standard deviation (> 0).
    pub sd: f64,
    /// True value.
    pub truth: f64,
}

/// Scores of a set of samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scores {
    /// Samples scored.
    pub count: usize,
    /// Root mean squared error.
    pub rmse: f64,
    /// Median absolute error.
    pub median_abs: f64,
    /// Largest absolute error (L∞).
    pub max_abs: f64,
    /// Mean predicted standard deviation.
    pub mean_sd: f64,
    /// Mean negative log predictive density, −log N(truth | mean, sd²).
    pub nlpd: f64,
    /// Fraction of truths inside mean ± 1 sd.
    pub coverage68: f64,
    /// Fraction of truths inside mean ± 1.96 sd.
    pub coverage95: f64,
    /// Share of errors within 2.576 sd.
    pub coverage99: f64,
    /// Area between the sparsification curve ordered by predicted sd and the oracle curve ordered
    /// by true error (mean absolute error, 50 steps; 0 is a perfect ranking), same units as the data.
    pub ause: f64,
}

/// Mean, sample standard deviation and median of a set of values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MeanSd {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation.
    pub sd: f64,
    /// Median (what a log-space smoother tracks when the spread is skewed).
    pub median: f64,
    /// Geometric mean exp(mean ln v) (NaN unless every value is positive): the average of scale
    /// parameters, robust to the odd scan whose optimum runs to a bound.
    pub geometric_mean: f64,
}

impl MeanSd {
    /// Summary of `v` (panics on an empty slice: caller's misuse).
    pub fn of(v: &[f64]) -> Self {
        assert!(!v.is_empty(), "no values to summarise");
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len().max(2) - 1) as f64;
        let mut sorted = v.to_vec();
        sorted.sort_by(f64::total_cmp);
        let geometric_mean = if sorted[0] > 0.0 {
            (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp()
        } else {
            f64::NAN
        };
        Self {
            mean,
            sd: var.sqrt(),
            median: median_of_sorted(&sorted),
            geometric_mean,
        }
    }

    /// Coefficient of variation sd / mean.
    pub fn cv(&self) -> f64 {
        self.sd / self.mean
    }
}

/// Steps of the sparsification curves.
const AUSE_STEPS: usize = 50;

impl Scores {
    /// Scores `samples`; `None` when there are none.
    ///
    /// Panics on a non-positive or non-finite sd (the caller's model is broken).
    pub fn of(samples: &[Sample]) -> Option<Self> {
        if samples.is_empty() {
            return None;
        }
        for s in samples {
            assert!(
                s.sd.is_finite() && s.sd > 0.0,
                "predicted sd must be positive, got {}",
                s.sd
            );
        }
        let n = samples.len() as f64;
        let errs: Vec<f64> = samples.iter().map(|s| (s.mean - s.truth).abs()).collect();
        let mut sorted = errs.clone();
        sorted.sort_by(f64::total_cmp);
        let within = |k: f64| {
            samples
                .iter()
                .filter(|s| (s.mean - s.truth).abs() <= k * s.sd)
                .count() as f64
                / n
        };
        let nlpd = samples
            .iter()
            .map(|s| {
                let z = (s.truth - s.mean) / s.sd;
                0.5 * (std::f64::consts::TAU * s.sd * s.sd).ln() + 0.5 * z * z
            })
            .sum::<f64>()
            / n;
        Some(Self {
            count: samples.len(),
            rmse: (errs.iter().map(|e| e * e).sum::<f64>() / n).sqrt(),
            median_abs: median_of_sorted(&sorted),
            max_abs: sorted[sorted.len() - 1],
            mean_sd: samples.iter().map(|s| s.sd).sum::<f64>() / n,
            nlpd,
            coverage68: within(1.0),
            coverage95: within(1.959_964),
            coverage99: within(2.575_829),
            ause: ause(samples, &errs),
        })
    }
}

fn median_of_sorted(v: &[f64]) -> f64 {
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// Mean absolute error left after removing the first `k` entries of `order` (most uncertain or
/// largest error first), for k = 0, n/50, 2n/50, …
fn sparsification(errs: &[f64], order: &[usize]) -> Vec<f64> {
    let n = errs.len();
    (0..AUSE_STEPS)
        .map(|step| {
            let removed = step * n / AUSE_STEPS;
            let kept = &order[removed..];
            kept.iter().map(|&i| errs[i]).sum::<f64>() / kept.len() as f64
        })
        .collect()
}

fn ause(samples: &[Sample], errs: &[f64]) -> f64 {
    let mut by_sd: Vec<usize> = (0..samples.len()).collect();
    by_sd.sort_by(|&a, &b| samples[b].sd.total_cmp(&samples[a].sd));
    let mut by_err: Vec<usize> = (0..samples.len()).collect();
    by_err.sort_by(|&a, &b| errs[b].total_cmp(&errs[a]));
    let (model, oracle) = (sparsification(errs, &by_sd), sparsification(errs, &by_err));
    model.iter().zip(&oracle).map(|(m, o)| m - o).sum::<f64>() / AUSE_STEPS as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(mean: f64, sd: f64, truth: f64) -> Sample {
        Sample { mean, sd, truth }
    }

    #[test]
    fn closed_form_values() {
        let s = Scores::of(&[sample(1.0, 1.0, 1.0), sample(0.0, 1.0, 3.0)]).expect("two");
        assert!((s.rmse - (4.5f64).sqrt()).abs() < 1e-12);
        assert!((s.median_abs - 1.5).abs() < 1e-12);
        assert_eq!(s.max_abs, 3.0);
        let half_log_tau = 0.5 * std::f64::consts::TAU.ln();
        assert!((s.nlpd - (half_log_tau + 0.5 * 9.0 / 2.0)).abs() < 1e-12);
        assert_eq!(s.coverage68, 0.5);
        assert_eq!(s.coverage95, 0.5);
        assert!(Scores::of(&[]).is_none());
    }

    #[test]
    fn gaussian_errors_with_true_sd_cover_at_nominal_rates() {
        use rand::SeedableRng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let samples: Vec<Sample> = (0..40_000)
            .map(|i| {
                let sd = 0.5 + (i % 7) as f64 * 0.3;
                sample(sd * rangegp_sim::sensor::standard_normal(&mut rng), sd, 0.0)
            })
            .collect();
        let s = Scores::of(&samples).expect("some");
        assert!((s.coverage68 - 0.6827).abs() < 0.01, "{}", s.coverage68);
        assert!((s.coverage95 - 0.95).abs() < 0.005, "{}", s.coverage95);
    }

    #[test]
    fn ause_is_zero_for_a_perfect_ranking_and_positive_for_a_reversed_one() {
        let perfect: Vec<Sample> = (1..=100).map(|i| sample(i as f64, i as f64, 0.0)).collect();
        assert!(Scores::of(&perfect).expect("some").ause.abs() < 1e-12);
        let reversed: Vec<Sample> = (1..=100).map(|i| sample(i as f64, 1.0 / i as f64, 0.0)).collect();
        assert!(Scores::of(&reversed).expect("some").ause > 10.0);
    }
}
