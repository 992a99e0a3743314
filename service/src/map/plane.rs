//! Returns read as the height of the ground at a centre: a plane through them (Bayesian least
//! squares with a prior on its slope), so that returns of two scans that fell on different
//! parts of a sloping aggregate cell still measure the same height, a cell whose returns cannot
//! pin its plane down says so in its variance, and a scan's nearest returns give the ground
//! under its sensor.

use nalgebra::{Matrix3, Vector3};

/// Prior σ of a plane's slope, rise over run: about 30°, the steepest ground a rover maps
/// (a plane the returns do not pin down across, as along one ring, borrows this much doubt).
pub const SLOPE_PRIOR_SD: f64 = 0.58;

/// Returns about a centre (one scan's in one aggregate cell, or near its sensor), as sums.
#[derive(Debug, Clone, Copy, Default)]
pub struct Returns {
    n: u32,
    // The first return's height: every other is summed relative to it (heights may be far
    // from zero; their squares must not swamp their spread).
    z0: f64,
    sx: f64,
    sy: f64,
    sxx: f64,
    sxy: f64,
    syy: f64,
    sz: f64,
    sxz: f64,
    syz: f64,
    szz: f64,
    noise_var: f64,
}

impl Returns {
    /// Adds a return at offset (dx, dy) from the centre, height z, with its noise
    /// variance, m².
    pub fn add(&mut self, dx: f64, dy: f64, z: f64, noise_var: f64) {
        if self.n == 0 {
            self.z0 = z;
        }
        let z = z - self.z0;
        self.n += 1;
        self.sx += dx;
        self.sy += dy;
        self.sxx += dx * dx;
        self.sxy += dx * dy;
        self.syy += dy * dy;
        self.sz += z;
        self.sxz += dx * z;
        self.syz += dy * z;
        self.szz += z * z;
        self.noise_var += noise_var;
    }

    /// Returns summed.
    pub fn count(&self) -> u32 {
        self.n
    }

    /// The plane through the returns: its height at the centre with its variance (the returns'
    /// own scatter about the plane, roughness among them, at least their noise, through
    /// the posterior of the fit) and its slope. `None` without returns or where the fit is
    /// singular (non-finite input).
    pub fn plane(&self) -> Option<Plane> {
        if self.n == 0 {
            return None;
        }
        let n = f64::from(self.n);
        let gram = Matrix3::new(
            n, self.sx, self.sy, //
            self.sx, self.sxx, self.sxy, //
            self.sy, self.sxy, self.syy,
        );
        let rhs = Vector3::new(self.sz, self.sxz, self.syz);
        let noise = (self.noise_var / n).max(1e-8);
        let fit = |var: f64| -> Option<(Vector3<f64>, f64)> {
            let prior = 1.0 / (SLOPE_PRIOR_SD * SLOPE_PRIOR_SD);
            let precision = gram / var + Matrix3::from_diagonal(&Vector3::new(0.0, prior, prior));
            let cov = precision.try_inverse()?;
            let beta = cov * rhs / var;
            Some((beta, cov[(0, 0)]))
        };
        let (beta, _) = fit(noise)?;
        // Scatter about the plane: Σ(z − Xβ)² = zᵀz − 2βᵀXᵀz + βᵀXᵀXβ.
        let rss = (self.szz - 2.0 * beta.dot(&rhs) + beta.dot(&(gram * beta))).max(0.0);
        let scatter = if self.n > 3 { rss / (n - 3.0) } else { 0.0 };
        let (beta, var) = fit(noise.max(scatter))?;
        let plane = Plane {
            z: self.z0 + beta[0],
            var: var.max(1e-8),
            slope: [beta[1], beta[2]],
        };
        [plane.z, plane.var, plane.slope[0], plane.slope[1]]
            .iter()
            .all(|v| v.is_finite())
            .then_some(plane)
    }
}

/// A plane through returns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Height at the centre, metres.
    pub z: f64,
    /// Its variance, m².
    pub var: f64,
    /// Rise over run along x and y.
    pub slope: [f64; 2],
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sloping_cell_reads_its_centre_height_from_either_side() {
        // Ground rising 0.3 m per metre along x, 100 m up: returns on the left half only, then
        // on the right half only.
        let ground = |x: f64| 100.0 + 0.3 * x;
        let mut left = Returns::default();
        let mut right = Returns::default();
        for k in 0..6 {
            let y = -0.1 + 0.04 * k as f64;
            left.add(-0.1, y, ground(-0.1), 1e-6);
            left.add(-0.05, y, ground(-0.05), 1e-6);
            right.add(0.05, y, ground(0.05), 1e-6);
            right.add(0.1, y, ground(0.1), 1e-6);
        }
        let Plane { z: zl, var: vl, .. } = left.plane().expect("returns");
        let Plane {
            z: zr,
            var: vr,
            slope,
        } = right.plane().expect("returns");
        assert!(
            (zl - 100.0).abs() < 1e-3 && (zr - 100.0).abs() < 1e-3,
            "{zl} {zr}"
        );
        assert!(vl < 1e-4 && vr < 1e-4);
        assert!(
            (slope[0] - 0.3).abs() < 1e-3 && slope[1].abs() < 1e-3,
            "{slope:?}"
        );
        // The highest return, the old statistic, differs by 4.5 cm between the two views.
        assert!((ground(0.1) - ground(-0.05)) > 0.04);
    }

    #[test]
    fn returns_along_one_line_off_the_centre_borrow_the_slope_prior() {
        let mut line = Returns::default();
        for k in 0..8 {
            line.add(-0.1 + 0.03 * k as f64, 0.11, 0.5, 1e-6);
        }
        let Plane { z, var, .. } = line.plane().expect("returns");
        assert!((z - 0.5).abs() < 1e-6);
        // Nothing says how the ground runs across the line: 0.11 m at up to ~30°.
        assert!(var.sqrt() > 0.04, "σ {}", var.sqrt());
        assert!(Returns::default().plane().is_none());
    }

    #[test]
    fn rough_returns_widen_the_variance_beyond_their_noise() {
        let mut smooth = Returns::default();
        let mut rough = Returns::default();
        for k in 0..16 {
            let (x, y) = (
                -0.1 + 0.2 * (k % 4) as f64 / 3.0,
                -0.1 + 0.2 * (k / 4) as f64 / 3.0,
            );
            smooth.add(x, y, 0.0, 1e-4);
            rough.add(x, y, if k % 2 == 0 { 0.05 } else { -0.05 }, 1e-4);
        }
        let vs = smooth.plane().expect("returns").var;
        let vr = rough.plane().expect("returns").var;
        assert!(vr > 2.0 * vs, "{vr} vs {vs}");
    }
}
