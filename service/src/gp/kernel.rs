//! Covariance kernels on Euclidean (chordal) distance.

/// Matérn ν = 3/2 in the scikit-learn convention: k(d) = σ² (1 + √3 d/ℓ) exp(−√3 d/ℓ).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Matern32 {
    /// Kernel variance σ² (scikit-learn's "constant value").
    pub variance: f64,
    /// Length scale ℓ, in the units of the distance.
    pub length_scale: f64,
}

impl Matern32 {
    /// Builds the kernel; panics on non-positive or non-finite parameters (caller's misuse).
    pub fn new(variance: f64, length_scale: f64) -> Self {
        assert!(
            variance.is_finite() && variance > 0.0,
            "kernel variance must be positive, got {variance}"
        );
        assert!(
            length_scale.is_finite() && length_scale > 0.0,
            "length scale must be positive, got {length_scale}"
        );
        Self {
            variance,
            length_scale,
        }
    }

    /// Covariance at distance `d` ≥ 0.
    #[inline]
    pub fn at(&self, d: f64) -> f64 {
        let s = 3f64.sqrt() * d / self.length_scale;
        self.variance * (1.0 + s) * (-s).exp()
    }

    /// Covariance between two points.
    #[inline]
    pub fn between(&self, a: &[f64; 3], b: &[f64; 3]) -> f64 {
        self.at(distance(a, b))
    }
}

/// Euclidean distance between two 3-vectors.
#[inline]
pub fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let (dx, dy, dz) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    (dx * dx + dy * dy + dz * dz).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_the_closed_form_at_known_distances() {
        let k = Matern32::new(2.0, 0.5);
        assert_eq!(k.at(0.0), 2.0);
        // d = ℓ/√3 ⇒ s = 1 ⇒ k = σ² · 2 / e.
        let d = 0.5 / 3f64.sqrt();
        assert!((k.at(d) - 4.0 / std::f64::consts::E).abs() < 1e-15);
        assert!(k.at(10.0) < 1e-10);
    }
}
