//! First crossing of a signed gap function along a line (negative in free space, non-negative
//! at or behind the surface): coarse sampling, then the Illinois variant of regula falsi.
//! Shared by every map that answers "where does this line meet the surface".

/// Residuals of this size (metres) and below count as "on the surface".
pub const ROOT_TOLERANCE_M: f64 = 1e-5;

/// Last two iterates closer than this (metres) give the slope at the root as a secant.
const SECANT_SPAN_M: f64 = 1e-3;

/// A crossing: where, and the gap's slope there when the refinement already measured it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Root {
    /// Position along the line.
    pub t: f64,
    slope: Option<f64>,
    value: Option<f64>,
}

impl Root {
    /// The gap at `t` when the refinement evaluated it there (the surface's own value, which a
    /// caller need not compute again).
    pub fn gap(&self) -> Option<f64> {
        self.value
    }
}

/// The first t in [t0, t1] where `gap` turns non-negative after being negative, sampled at
/// `samples` points (a gap of `None` is "not observed" and breaks the bracket), or `None`.
pub fn first_crossing(gap: impl Fn(f64) -> Option<f64>, t0: f64, t1: f64, samples: usize) -> Option<Root> {
    let mut prev: Option<(f64, f64)> = None;
    for k in 0..=samples {
        let t = t0 + (t1 - t0) * k as f64 / samples as f64;
        let Some(g) = gap(t) else {
            prev = None;
            continue;
        };
        if g >= 0.0 {
            return prev.and_then(|p| refine(&gap, p, (t, g)));
        }
        prev = Some((t, g));
    }
    None
}

/// The first t in [t0, t1] where `gap` turns non-negative, stepping from t0 by what the gap
/// itself says of the distance left: `ahead(t, gap(t))` (clamped to [`min_step`, `max_step`];
/// `max_step` after an unobserved point), then refined as [`first_crossing`] does. Where the
/// gap measures the distance to a surface the step lands near it at once, so a long stretch of
/// free space costs a few evaluations instead of a fixed sampling's many; `max_step` bounds what
/// can be stepped over as a fixed sampling's spacing does.
pub fn first_crossing_traced(
    gap: impl Fn(f64) -> Option<f64>,
    (t0, t1): (f64, f64),
    (min_step, max_step): (f64, f64),
    ahead: impl Fn(f64, f64) -> f64,
) -> Option<Root> {
    let mut prev: Option<(f64, f64)> = None;
    let mut t = t0;
    loop {
        let step = match gap(t) {
            Some(g) if g >= 0.0 => return prev.and_then(|p| refine(&gap, p, (t, g))),
            Some(g) => {
                prev = Some((t, g));
                ahead(t, g).clamp(min_step, max_step)
            }
            None => {
                prev = None;
                max_step
            }
        };
        if t >= t1 {
            return None;
        }
        t = (t + step).min(t1);
    }
}

/// Illinois refinement of a bracket (ga < 0 ≤ gb). The secant through the last two iterates
/// is the slope at the root when they are close (superlinear convergence makes them so).
fn refine(
    gap: &impl Fn(f64) -> Option<f64>,
    (mut ta, mut ga): (f64, f64),
    (mut tb, mut gb): (f64, f64),
) -> Option<Root> {
    let mut side = 0i8;
    let mut previous = (tb, gb);
    for _ in 0..60 {
        let t = (ta * gb - tb * ga) / (gb - ga);
        let g = gap(t)?;
        if g.abs() < ROOT_TOLERANCE_M * 0.1 || (tb - ta).abs() < ROOT_TOLERANCE_M {
            let (tp, gp) = previous;
            let close = (t - tp).abs() <= SECANT_SPAN_M && t != tp;
            return Some(Root {
                t,
                slope: close.then(|| (g - gp) / (t - tp)),
                value: Some(g),
            });
        }
        previous = (t, g);
        if g < 0.0 {
            ta = t;
            ga = g;
            if side == -1 {
                gb *= 0.5;
            }
            side = -1;
        } else {
            tb = t;
            gb = g;
            if side == 1 {
                ga *= 0.5;
            }
            side = 1;
        }
    }
    Some(Root {
        t: 0.5 * (ta + tb),
        slope: None,
        value: None,
    })
}

/// Variance of a root of `gap` by the delta method, `var_at_root / (∂gap/∂t)²` (the
/// refinement's secant, else a central difference); `None` where the slope vanishes or the
/// gap is unobserved.
pub fn root_variance(gap: impl Fn(f64) -> Option<f64>, root: Root, var_at_root: f64) -> Option<f64> {
    let h = 1e-4;
    let slope = match root.slope {
        Some(s) => s,
        None => (gap(root.t + h)? - gap(root.t - h)?) / (2.0 * h),
    };
    (slope.abs() > 1e-6).then(|| var_at_root / (slope * slope))
}

/// The variance of a ray's crossing from the stretch of the ray that lies within ±2 σ of the
/// surface around `root` (σ the gap's standard deviation there): a ray grazing the surface runs
/// inside that band for long, and its hit could be anywhere along it, which the delta method's
/// local slope does not see. Walks out from the root in `step`s within [t0, t1]; the band's
/// length is read as a ±2 σ interval: ((t_hi − t_lo) / 4)².
pub fn band_variance(
    gap: impl Fn(f64) -> Option<f64>,
    root: Root,
    sd_gap: f64,
    step: f64,
    t0: f64,
    t1: f64,
) -> f64 {
    let within = |t: f64| gap(t).is_some_and(|g| g.abs() <= 2.0 * sd_gap);
    let walk = |dir: f64| {
        let mut t = root.t;
        for _ in 0..BAND_STEPS {
            let next = (t + dir * step).clamp(t0, t1);
            if next == t || !within(next) {
                break;
            }
            t = next;
        }
        t
    };
    let (lo, hi) = (walk(-1.0), walk(1.0));
    ((hi - lo) / 4.0).powi(2)
}

/// Most steps [`band_variance`] walks each way.
const BAND_STEPS: usize = 400;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_first_of_two_crossings_with_its_delta_variance() {
        // gap(t) = sin(t) − 0.5 meets zero first at π/6.
        let gap = |t: f64| Some(t.sin() - 0.5);
        let root = first_crossing(gap, -1.0, 3.0, 40).expect("crossing");
        assert!((root.t - std::f64::consts::FRAC_PI_6).abs() < 1e-6, "{root:?}");
        assert!(root.slope.is_some(), "the refinement measured the slope");
        let slope = std::f64::consts::FRAC_PI_6.cos();
        let expected = 0.01 / (slope * slope);
        let v = root_variance(gap, root, 0.01).expect("slope");
        assert!((v - expected).abs() < 1e-7, "{v} vs {expected}");
        let unmeasured = Root { slope: None, ..root };
        let v = root_variance(gap, unmeasured, 0.01).expect("slope");
        assert!((v - expected).abs() < 1e-7, "{v} vs {expected}");
        assert!(first_crossing(|t: f64| Some(t - 10.0), 0.0, 5.0, 10).is_none());
        // A steep crossing's band is short; a grazing one's long.
        let steep = band_variance(
            |t: f64| Some(t - 1.0),
            Root {
                t: 1.0,
                slope: Some(1.0),
                value: Some(0.0),
            },
            0.01,
            0.005,
            0.0,
            5.0,
        );
        let grazing = band_variance(
            |t: f64| Some(0.01 * (t - 1.0)),
            Root {
                t: 1.0,
                slope: Some(0.01),
                value: Some(0.0),
            },
            0.01,
            0.005,
            0.0,
            5.0,
        );
        assert!(steep.sqrt() < 0.02 && grazing.sqrt() > 0.5, "{steep} {grazing}");
        assert!(first_crossing(|t: f64| (t < 1.0).then_some(t - 2.0), 0.0, 5.0, 10).is_none());
    }

    #[test]
    fn traced_steps_take_the_first_crossing_in_few_evaluations() {
        // An estimate of the distance left far too generous is held to the largest step: the
        // first of the two crossings of sin(t) − 0.5 is still the one found.
        let gap = |t: f64| Some(t.sin() - 0.5);
        let root = first_crossing_traced(gap, (-1.0, 3.0), (0.05, 0.2), |_, g| -10.0 * g).expect("crossing");
        assert!((root.t - std::f64::consts::FRAC_PI_6).abs() < 1e-6, "{root:?}");
        assert!(root.gap().is_some_and(|g| g.abs() < 1e-5));
        // A surface 3 away and an estimate that overshoots by half: bracketed at once, the
        // secant lands on it (three evaluations, where even sampling at the smallest step
        // would take 300).
        let calls = std::cell::Cell::new(0);
        let line = |t: f64| {
            calls.set(calls.get() + 1);
            Some(t - 3.0)
        };
        let root = first_crossing_traced(line, (0.0, 10.0), (0.01, 5.0), |_, g| -1.5 * g).expect("crossing");
        assert!(
            (root.t - 3.0).abs() < 1e-9 && calls.get() <= 4,
            "{root:?} after {} calls",
            calls.get()
        );
        // No crossing, or an unobserved stretch between free space and the surface: none.
        assert!(first_crossing_traced(|t| Some(t - 10.0), (0.0, 5.0), (0.1, 1.0), |_, g| -g).is_none());
        let gappy = |t: f64| (!(1.0..2.0).contains(&t)).then_some(t - 1.5);
        assert!(first_crossing_traced(gappy, (0.0, 5.0), (0.4, 0.4), |_, g| -g).is_none());
    }
}
