//! Cholesky factorisation of covariance matrices with a bounded jitter policy (docs/MATH.md
//! "Posterior").

use faer::{linalg::solvers::Llt, Mat, Side};
use thiserror::Error;

/// How much diagonal jitter to try when a factorisation fails.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JitterPolicy {
    /// First jitter, relative to the mean diagonal.
    pub initial_relative: f64,
    /// Factor applied per retry.
    pub growth: f64,
    /// Retries after the jitter-free attempt.
    pub max_retries: u32,
}

impl Default for JitterPolicy {
    fn default() -> Self {
        Self {
            initial_relative: 1e-8,
            growth: 10.0,
            max_retries: 5,
        }
    }
}

/// The matrix could not be factored.
#[derive(Debug, Error, PartialEq)]
pub enum CholeskyError {
    /// Not positive definite even with the largest jitter allowed.
    #[error("matrix not positive definite after {retries} jitter retries (last jitter {last_jitter:e})")]
    NotPositiveDefinite {
        /// Retries made.
        retries: u32,
        /// Largest jitter added to the diagonal.
        last_jitter: f64,
    },
    /// The matrix holds NaN or infinity.
    #[error("matrix has non-finite entries")]
    NonFinite,
}

/// Factors `k` = L Lᵀ (lower), adding jitter to the diagonal on failure per `policy`.
/// Returns the factor and the jitter that was needed (0 when none).
pub fn factor_with_jitter(k: &Mat<f64>, policy: JitterPolicy) -> Result<(Llt<f64>, f64), CholeskyError> {
    let n = k.nrows();
    assert_eq!(n, k.ncols(), "covariance matrix must be square");
    let mut diag_sum = 0.0;
    for i in 0..n {
        diag_sum += k[(i, i)];
    }
    if !diag_sum.is_finite() {
        return Err(CholeskyError::NonFinite);
    }
    if let Ok(llt) = k.llt(Side::Lower) {
        return Ok((llt, 0.0));
    }
    let mean_diag = (diag_sum / n.max(1) as f64).abs().max(f64::MIN_POSITIVE);
    let mut jitter = policy.initial_relative * mean_diag;
    let mut work = k.clone();
    for retry in 1..=policy.max_retries {
        for i in 0..n {
            work[(i, i)] = k[(i, i)] + jitter;
        }
        if let Ok(llt) = work.llt(Side::Lower) {
            return Ok((llt, jitter));
        }
        if retry < policy.max_retries {
            jitter *= policy.growth;
        }
    }
    Err(CholeskyError::NotPositiveDefinite {
        retries: policy.max_retries,
        last_jitter: jitter,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duplicate_rows_are_rescued_by_jitter() {
        // Rank-one matrix: plain Cholesky fails, jitter makes it positive definite.
        let k = Mat::from_fn(3, 3, |_, _| 1.0);
        let (_, jitter) = factor_with_jitter(&k, JitterPolicy::default()).expect("jittered");
        assert!(jitter > 0.0);
    }

    #[test]
    fn indefinite_matrix_is_an_error_not_a_panic() {
        let k = Mat::from_fn(2, 2, |i, j| if i == j { -1.0 } else { 0.0 });
        assert!(matches!(
            factor_with_jitter(&k, JitterPolicy::default()),
            Err(CholeskyError::NotPositiveDefinite { retries: 5, .. })
        ));
        let nan = Mat::from_fn(2, 2, |_, _| f64::NAN);
        assert_eq!(
            factor_with_jitter(&nan, JitterPolicy::default()).err(),
            Some(CholeskyError::NonFinite)
        );
    }
}
