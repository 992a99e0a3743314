//! The range sphere of seed 000 (eqs. 3–5): ray angles as points on a sphere of radius R_max,
//! so that kernels on chordal distance stay positive definite.

/// Point on the range sphere of radius `r_max` for inclination θ (polar, from +z) and azimuth φ.
#[inline]
pub fn to_sphere(inclination: f64, azimuth: f64, r_max: f64) -> [f64; 3] {
    let (st, ct) = inclination.sin_cos();
    let (sp, cp) = azimuth.sin_cos();
    [r_max * st * cp, r_max * st * sp, r_max * ct]
}

/// Inclination and azimuth of a sensor-frame vector (which need not be unit length).
#[inline]
pub fn angles_of(v: [f64; 3]) -> (f64, f64) {
    let norm = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    ((v[2] / norm).clamp(-1.0, 1.0).acos(), v[1].atan2(v[0]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_round_trip_and_chord_matches_geometry() {
        let (t, p) = (1.7, -0.4);
        let x = to_sphere(t, p, 10.0);
        let (t2, p2) = angles_of(x);
        assert!((t - t2).abs() < 1e-12 && (p - p2).abs() < 1e-12);
        // Two rays 1° apart in azimuth on the horizon: chord = 2 R sin(0.5°).
        let a = to_sphere(std::f64::consts::FRAC_PI_2, 0.0, 10.0);
        let b = to_sphere(std::f64::consts::FRAC_PI_2, 1f64.to_radians(), 10.0);
        let chord = crate::gp::kernel::distance(&a, &b);
        assert!((chord - 20.0 * 0.5f64.to_radians().sin()).abs() < 1e-12);
    }
}
