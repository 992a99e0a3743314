//! The angular field of view a scan actually observed, so maps never answer outside it.

use std::f64::consts::{PI, TAU};
use std::sync::Arc;

/// Azimuth sectors of [`FieldOfView`]'s ceiling, even in the diamond angle ([`diamond`]):
/// 0.32°–0.64° wide.
const CEILING_SECTORS: usize = 720;

/// How far above the highest return in an azimuth the view reaches, in ring spacings: half way
/// to the next ring, whose ray came back empty. Between the two the ground may lie within range
/// unseen; 0.9 kept more of those answers and erred more: window RMSE on the OS1-64 and the
/// VLP-16 up to 30 % higher than at 0.5 on rough relief (docs/EVALUATION.md "Calibration",
/// step 29).
const CEILING_RINGS: f64 = 0.5;

/// Slack of the ceiling test on z / ‖v‖, above the ceiling's f32 rounding.
const CEILING_TOLERANCE: f64 = 1e-6;

/// Inclination interval × azimuth arc (the arc may wrap through ±π), optionally under a
/// ceiling: in each azimuth no higher than half way to the ring above the scan's highest return
/// there (`gp.view_ceiling`).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldOfView {
    inclination: (f64, f64),
    /// cos of the inclination interval's ends (high end first): the band as bounds on z / ‖v‖.
    cos_band: (f64, f64),
    /// The arc's width, radians (TAU for a full turn).
    azimuth_width: f64,
    /// The arc's ends as unit (x, y) directions, start first: the arc test on cross products.
    arc_ends: [[f64; 2]; 2],
    /// Per azimuth sector ([`CEILING_SECTORS`] even in the diamond angle), the largest z / ‖v‖
    /// in view ([`Self::covering`]); interpolated between sector centres. `None`: no ceiling.
    ceiling: Option<Arc<[f32]>>,
}

impl FieldOfView {
    /// The smallest FOV holding every (inclination, azimuth) given, widened by `margin` radians
    /// on each side. The azimuth arc is the complement of the largest gap between sorted
    /// azimuths, so forward-looking and full-turn scanners are both handled.
    ///
    /// The angles are a scan's returns, so above the highest of them in an azimuth the rays
    /// came back empty: nothing lies there within range, and a map that continued its surface
    /// into that sky (from a hill's returns beside it, say) would put ground where there is
    /// none. With `ceiling` the view also ends, in each azimuth, half a ring spacing above the
    /// highest return there (the spacing is the median gap between the distinct inclinations;
    /// at least `margin`); between the sectors that hold returns the ceiling is interpolated.
    /// Without it the view is the band and the arc alone. Panics on empty input.
    pub fn covering(angles: &[(f64, f64)], margin: f64, ceiling: bool) -> Self {
        assert!(!angles.is_empty(), "a field of view needs at least one ray");
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        // (azimuth in [0, 2π), inclination) by azimuth.
        let mut rays: Vec<(f64, f64)> = Vec::with_capacity(angles.len());
        for &(t, p) in angles {
            lo = lo.min(t);
            hi = hi.max(t);
            rays.push((p.rem_euclid(TAU), t));
        }
        rays.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let mut gap = rays[0].0 + TAU - rays[rays.len() - 1].0;
        let mut start = rays[0].0;
        for w in rays.windows(2) {
            if w[1].0 - w[0].0 > gap {
                gap = w[1].0 - w[0].0;
                start = w[1].0;
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
            ceiling: ceiling.then(|| {
                // Each column's highest return: (its inclination, the azimuth).
                let columns: Vec<(f64, f64)> = rays
                    .chunk_by(|a, b| a.0 == b.0)
                    .map(|run| (run.iter().map(|r| r.1).fold(f64::INFINITY, f64::min), run[0].0))
                    .collect();
                ceiling_of(&columns, (CEILING_RINGS * ring_spacing(angles)).max(margin))
            }),
        }
    }

    /// The inclination interval (low, high), radians.
    pub fn inclination(&self) -> (f64, f64) {
        self.inclination
    }

    /// True when the sensor-frame vector `v` of length `norm` (> 0) lies under the ceiling (or
    /// the view has none): the test of a crossing a search found in the band.
    pub fn under_ceiling(&self, v: &[f64; 3], norm: f64) -> bool {
        self.ceiling
            .as_ref()
            .is_none_or(|top| v[2] / norm <= ceiling_at(top, v[0], v[1]) + CEILING_TOLERANCE)
    }

    /// True when the sensor-frame vector `v` of length `norm` (> 0) lies in the band and the
    /// arc, the ceiling aside, with no inverse trigonometry (the membership test of every
    /// search along a line, so that a crossing the map carried into the sky above the scan's
    /// returns is found, and refused, rather than stepped over to whatever the map puts below
    /// it): the band on z / ‖v‖, the arc on the signs of v's cross products with its ends. v
    /// lies counter-clockwise of the start by at most π when the first is non-negative, and
    /// clockwise of the end by at most π when the second is: an arc up to π wide holds v when
    /// both hold, a wider one unless both fail (v is then in the complement, narrower than π).
    pub fn band_holds(&self, v: &[f64; 3], norm: f64) -> bool {
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

/// The largest z / ‖v‖ under the sectors' ceiling `top` in the azimuth of (x, y): linear
/// between sector centres.
fn ceiling_at(top: &[f32], x: f64, y: f64) -> f64 {
    let n = top.len();
    let f = (diamond(x, y) * n as f64 / 4.0 - 0.5).rem_euclid(n as f64);
    let i = (f.floor() as usize).min(n - 1);
    let w = f - i as f64;
    f64::from(top[i]) * (1.0 - w) + f64::from(top[(i + 1) % n]) * w
}

/// The diamond angle of (x, y), in [0, 4): increasing with the azimuth from +x as the angle
/// does, with no inverse trigonometry (the ceiling is looked up at every answer, and at every
/// step of a ray's closest-approach scan); 0 at the origin.
fn diamond(x: f64, y: f64) -> f64 {
    if x == 0.0 && y == 0.0 {
        0.0
    } else if y >= 0.0 {
        if x >= 0.0 {
            y / (x + y)
        } else {
            1.0 - x / (y - x)
        }
    } else if x < 0.0 {
        2.0 - y / (-x - y)
    } else {
        3.0 + x / (x - y)
    }
}

/// The median gap between the distinct inclinations of `angles` (to 0.001 rad): a spinning
/// scanner's ring spacing, radians (0 with one ring).
fn ring_spacing(angles: &[(f64, f64)]) -> f64 {
    let last = (PI * 1e3) as usize + 1;
    let mut seen = vec![false; last + 1];
    for &(t, _) in angles {
        seen[((t * 1e3).round().max(0.0) as usize).min(last)] = true;
    }
    let rings: Vec<usize> = (0..seen.len()).filter(|&i| seen[i]).collect();
    let mut gaps: Vec<usize> = rings.windows(2).map(|w| w[1] - w[0]).collect();
    if gaps.is_empty() {
        return 0.0;
    }
    let mid = gaps.len() / 2;
    1e-3 * *gaps.select_nth_unstable(mid).1 as f64
}

/// Per azimuth sector, cos of (the smallest inclination among the `columns` (inclination,
/// azimuth) there less `lift`): the largest z / ‖v‖ in view; sectors without returns take the
/// linear interpolation between the nearest sectors with returns on either side (around the
/// circle).
fn ceiling_of(columns: &[(f64, f64)], lift: f64) -> Arc<[f32]> {
    let n = CEILING_SECTORS;
    let mut top = vec![f64::NAN; n];
    for &(t, p) in columns {
        let i = ((diamond(p.cos(), p.sin()) * n as f64 / 4.0) as usize).min(n - 1);
        let c = (t - lift).max(0.0).cos();
        if top[i].is_nan() || c > top[i] {
            top[i] = c;
        }
    }
    let filled: Vec<usize> = (0..n).filter(|&i| !top[i].is_nan()).collect();
    let mut out = top.clone();
    for (k, &a) in filled.iter().enumerate() {
        let b = filled[(k + 1) % filled.len()];
        let span = (b + n - a) % n;
        let span = if span == 0 { n } else { span };
        for step in 1..span {
            let w = step as f64 / span as f64;
            out[(a + step) % n] = top[a] * (1.0 - w) + top[b] * w;
        }
    }
    out.into_iter().map(|c| c as f32).collect()
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
            && fov.ceiling.as_deref().is_none_or(|top| {
                inclination.cos() <= ceiling_at(top, azimuth.cos(), azimuth.sin()) + CEILING_TOLERANCE
            })
    }

    /// The vector test: in the band and the arc, and under the ceiling.
    fn inside(fov: &FieldOfView, v: &[f64; 3], norm: f64) -> bool {
        fov.band_holds(v, norm) && fov.under_ceiling(v, norm)
    }

    fn sees(fov: &FieldOfView, inclination: f64, azimuth: f64) -> bool {
        inside(fov, &crate::gp::sphere::to_sphere(inclination, azimuth, 2.0), 2.0)
    }

    #[test]
    fn forward_arc_and_wrapping_arc() {
        let fwd = FieldOfView::covering(&[(1.6, -1.5), (1.8, 1.5), (1.7, 0.0)], 0.01, true);
        assert!(sees(&fwd, 1.75, 1.0) && !sees(&fwd, 1.75, 3.0) && !sees(&fwd, 1.5, 0.0));
        let back = FieldOfView::covering(&[(1.6, 3.0), (1.6, -3.0)], 0.0, true);
        assert!(sees(&back, 1.6, 3.1) && sees(&back, 1.6, -3.1) && !sees(&back, 1.6, 0.0));
        let full: Vec<(f64, f64)> = (0..360).map(|i| (1.6, (i as f64).to_radians() - PI)).collect();
        let full = FieldOfView::covering(&full, 0.01, true);
        assert!(sees(&full, 1.6, 0.123) && !sees(&full, 1.3, 0.123));
        assert!((full.inclination().1 - full.inclination().0 - 0.02).abs() < 1e-12);
    }

    #[test]
    fn the_diamond_angle_rises_with_the_azimuth_around_the_circle() {
        let d: Vec<f64> = (0..720)
            .map(|k| {
                let a = TAU * k as f64 / 720.0;
                diamond(a.cos(), a.sin())
            })
            .collect();
        assert!(d.windows(2).all(|w| w[1] > w[0]), "monotone");
        assert!(d[0].abs() < 1e-12 && (d[180] - 1.0).abs() < 1e-12 && (d[360] - 2.0).abs() < 1e-12);
        assert!((d[540] - 3.0).abs() < 1e-12 && d[719] < 4.0);
    }

    #[test]
    fn above_the_highest_return_in_an_azimuth_nothing_is_in_view() {
        // Five rings 0.1 rad apart, a column a degree; between azimuths 0 and 0.5 rad only the
        // lowest two rings returned (the rays above went past a crest into the sky): the view
        // there ends half a ring above 1.9 rad, at 1.85.
        let mut angles = Vec::new();
        for column in 0..360 {
            let azimuth = (column as f64).to_radians() - PI;
            let rings = if (0.0..=0.5).contains(&azimuth) {
                3..5
            } else {
                0..5
            };
            angles.extend(rings.map(|ring| (1.6 + 0.1 * ring as f64, azimuth)));
        }
        let fov = FieldOfView::covering(&angles, 0.01, true);
        assert!(fov.azimuth_width >= TAU, "a full turn");
        assert!(
            sees(&fov, 1.62, -1.0) && sees(&fov, 1.62, 1.0),
            "the top ring where it returned"
        );
        assert!(sees(&fov, 1.86, 0.25), "within half a ring of the highest return");
        assert!(!sees(&fov, 1.84, 0.25) && !sees(&fov, 1.62, 0.25), "above it");
        // Between a column that returned from every ring and one that did not, the ceiling
        // falls linearly: no step for a query's line to flicker across.
        let before = -1f64.to_radians();
        assert!(sees(&fov, 1.6, before) && !sees(&fov, 1.6, 0.1));
        let at = |azimuth: f64| {
            ceiling_at(
                fov.ceiling.as_deref().expect("a ceiling"),
                azimuth.cos(),
                azimuth.sin(),
            )
        };
        let mid = at(-0.5f64.to_radians());
        assert!(mid < at(before) && mid > at(0.1));
    }

    #[test]
    fn vector_test_agrees_with_the_angle_test() {
        use crate::gp::sphere::{angles_of, to_sphere};
        let fovs = [
            FieldOfView::covering(&[(1.6, -1.5), (1.8, 1.5), (1.7, 0.0)], 0.01, true),
            FieldOfView::covering(&[(1.6, 3.0), (1.6, -3.0)], 0.0, true),
            FieldOfView::covering(&[(1.2, -PI), (1.9, 0.0), (1.5, 2.0), (1.5, -2.0)], 0.05, true),
        ];
        let mut disagreements = 0;
        for fov in &fovs {
            for i in 0..=90 {
                for j in 0..180 {
                    let (t, p) = (PI * i as f64 / 90.0, -PI + TAU * j as f64 / 180.0);
                    let v = to_sphere(t, p, 3.7);
                    let (t2, p2) = angles_of(v);
                    disagreements += usize::from(contains(fov, t2, p2) != inside(fov, &v, 3.7));
                }
            }
        }
        assert_eq!(disagreements, 0);
    }
}
