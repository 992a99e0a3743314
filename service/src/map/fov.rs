//! The angular field of view a scan actually observed, so maps never answer outside it.

use std::f64::consts::{PI, TAU};

/// Inclination interval × azimuth arc (the arc may wrap through ±π).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldOfView {
    inclination: (f64, f64),
    azimuth_start: f64,
    azimuth_width: f64,
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
        Self {
            inclination: ((lo - margin).max(0.0), (hi + margin).min(PI)),
            azimuth_start,
            azimuth_width,
        }
    }

    /// True when the direction (inclination, azimuth) lies inside.
    pub fn contains(&self, inclination: f64, azimuth: f64) -> bool {
        inclination >= self.inclination.0
            && inclination <= self.inclination.1
            && (azimuth - self.azimuth_start).rem_euclid(TAU) <= self.azimuth_width
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forward_arc_and_wrapping_arc() {
        let fwd = FieldOfView::covering(&[(1.6, -1.5), (1.8, 1.5), (1.7, 0.0)], 0.01);
        assert!(fwd.contains(1.7, 1.0) && !fwd.contains(1.7, 3.0) && !fwd.contains(1.5, 0.0));
        let back = FieldOfView::covering(&[(1.6, 3.0), (1.6, -3.0)], 0.0);
        assert!(back.contains(1.6, 3.1) && back.contains(1.6, -3.1) && !back.contains(1.6, 0.0));
        let full: Vec<(f64, f64)> = (0..360).map(|i| (1.6, (i as f64).to_radians() - PI)).collect();
        assert!(FieldOfView::covering(&full, 0.01).contains(1.6, 0.123));
    }
}
