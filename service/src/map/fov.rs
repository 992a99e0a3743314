//! The angular field of view a scan actually observed, so maps never answer outside it.

use std::f64::consts::{PI, TAU};

/// Inclination interval × azimuth arc (the arc may wrap through ±π).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldOfView {
    inclination: (f64, f64),
    /// cos of the inclination interval's ends (high end first): the band as bounds on z / ‖v‖.
    cos_band: (f64, f64),
    /// The arc's width, radians (TAU for a full turn).
    azimuth_width: f64,
    /// The arc's ends as unit (x, y) directions, start first: the arc test on cross products.
    arc_ends: [[f64; 2]; 2],
}

impl FieldOfView {
    /// The smallest FOV holding every (inclination, azimuth) given, widened by `margin` radians
    /// on each side. The azimuth arc is the complement of the largest gap between sorted
    /// azimuths, so forward-looking and full-turn scanners are both handled. Panics on empty input.
    pub fn covering(angles: &[(f64, f64)], margin: f64) -> Self {
        assert!(!angles.is_empty(), "a field of view needs at least one ray");
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        let mut az: Vec<f64> = Vec::with_capacity(angles.len());
        for &(t, p) in angles {
            lo = lo.min(t);
            hi = hi.max(t);
            az.push(p.rem_euclid(TAU));
        }
        az.sort_by(f64::total_cmp);
        let mut gap = az[0] + TAU - az[az.len() - 1];
        let mut start = az[0];
        for w in az.windows(2) {
            if w[1] - w[0] > gap {
                gap = w[1] - w[0];
                start = w[1];
            }
        }
        let width = TAU - gap;
        let (azimuth_start, azimuth_width) = if width + 2.0 * margin >= TAU - 1e-9 {
            (0.0, TAU)
        } else {
            (start - margin, width + 2.0 * margin)
        };
        let inclination = ((lo - margin).max(0.0), (hi + margin).min(PI));
        let end = azimuth_start + azimuth_width;
        Self {
            inclination,
            cos_band: (inclination.1.cos(), inclination.0.cos()),
            azimuth_width,
            arc_ends: [[azimuth_start.cos(), azimuth_start.sin()], [end.cos(), end.sin()]],
        }
    }

    /// The inclination interval (low, high), radians.
    pub fn inclination(&self) -> (f64, f64) {
        self.inclination
    }

    /// True when the sensor-frame vector `v` of length `norm` (> 0) points inside, with no
    /// inverse trigonometry (the membership test of every search along a line): the band on
    /// z / ‖v‖, the arc on the signs of v's cross products with its ends. v lies counter-
    /// clockwise of the start by at most π when the first is non-negative, and clockwise of the
    /// end by at most π when the second is: an arc up to π wide holds v when both hold, a wider
    /// one unless both fail (v is then in the complement, narrower than π).
    pub fn contains_vector(&self, v: &[f64; 3], norm: f64) -> bool {
        let c = v[2] / norm;
        if c < self.cos_band.0 || c > self.cos_band.1 {
            return false;
        }
        if self.azimuth_width >= TAU {
            return true;
        }
        let [s, e] = self.arc_ends;
        let after_start = s[0] * v[1] - s[1] * v[0] >= 0.0;
        let before_end = v[0] * e[1] - v[1] * e[0] >= 0.0;
        if self.azimuth_width <= PI {
            after_start && before_end
        } else {
            after_start || before_end
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition on angles, for reference.
    fn contains(fov: &FieldOfView, inclination: f64, azimuth: f64) -> bool {
        let start = fov.arc_ends[0][1].atan2(fov.arc_ends[0][0]);
        inclination >= fov.inclination.0
            && inclination <= fov.inclination.1
            && (azimuth - start).rem_euclid(TAU) <= fov.azimuth_width
    }

    fn sees(fov: &FieldOfView, inclination: f64, azimuth: f64) -> bool {
        fov.contains_vector(&crate::gp::sphere::to_sphere(inclination, azimuth, 2.0), 2.0)
    }

    #[test]
    fn forward_arc_and_wrapping_arc() {
        let fwd = FieldOfView::covering(&[(1.6, -1.5), (1.8, 1.5), (1.7, 0.0)], 0.01);
        assert!(sees(&fwd, 1.7, 1.0) && !sees(&fwd, 1.7, 3.0) && !sees(&fwd, 1.5, 0.0));
        let back = FieldOfView::covering(&[(1.6, 3.0), (1.6, -3.0)], 0.0);
        assert!(sees(&back, 1.6, 3.1) && sees(&back, 1.6, -3.1) && !sees(&back, 1.6, 0.0));
        let full: Vec<(f64, f64)> = (0..360).map(|i| (1.6, (i as f64).to_radians() - PI)).collect();
        let full = FieldOfView::covering(&full, 0.01);
        assert!(sees(&full, 1.6, 0.123) && !sees(&full, 1.3, 0.123));
        assert!((full.inclination().1 - full.inclination().0 - 0.02).abs() < 1e-12);
    }

    #[test]
    fn vector_test_agrees_with_the_angle_test() {
        use crate::gp::sphere::{angles_of, to_sphere};
        let fovs = [
            FieldOfView::covering(&[(1.6, -1.5), (1.8, 1.5), (1.7, 0.0)], 0.01),
            FieldOfView::covering(&[(1.6, 3.0), (1.6, -3.0)], 0.0),
            FieldOfView::covering(&[(1.2, -PI), (1.9, 0.0), (1.5, 2.0), (1.5, -2.0)], 0.05),
        ];
        let mut disagreements = 0;
        for fov in &fovs {
            for i in 0..=90 {
                for j in 0..180 {
                    let (t, p) = (PI * i as f64 / 90.0, -PI + TAU * j as f64 / 180.0);
                    let v = to_sphere(t, p, 3.7);
                    let (t2, p2) = angles_of(v);
                    disagreements += usize::from(contains(fov, t2, p2) != fov.contains_vector(&v, 3.7));
                }
            }
        }
        assert_eq!(disagreements, 0);
    }
}
