//! First crossing of a signed gap function along a line (negative in free space, non-negative
//! at or behind the surface): coarse sampling or a trace, then a safeguarded secant (the
//! Illinois variant of regula falsi where the secant strays).
//! Shared by every map that answers "where does this line meet the surface".

/// A refinement stops when a trace's estimate of the distance to the crossing (else the gap, to
/// a tenth of this) or its bracket is below this, metres.
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
            return prev.and_then(|p| refine(&gap, p, (t, g), None::<&fn(f64, f64) -> f64>));
        }
        prev = Some((t, g));
    }
    None
}

/// How far past the estimated crossing a traced step goes (the estimate assumes a flat surface
/// and falls short on rising ground; the refinement takes the bracket an overshoot makes).
const TRACE_OVERSHOOT: f64 = 1.5;

/// The first t in [t0, t1] where `gap` turns non-negative, stepping from t0 by what the gap
/// itself says of the distance left: `ahead(t, gap(t))` is the estimated signed distance to the
/// crossing (positive in free space), stepped `TRACE_OVERSHOOT` times over and clamped to
/// [`min_step`, `max_step`] (`max_step` after an unobserved point), then refined as
/// [`first_crossing`] does, on the estimates. Where the gap measures the distance to a surface
/// the step lands near it at once, so a long stretch of free space costs a few evaluations
/// instead of a fixed sampling's many; `max_step` bounds what can be stepped over as a fixed
/// sampling's spacing does.
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
            Some(g) if g >= 0.0 => return prev.and_then(|p| refine(&gap, p, (t, g), Some(&ahead))),
            Some(g) => {
                prev = Some((t, g));
                (TRACE_OVERSHOOT * ahead(t, g)).clamp(min_step, max_step)
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

/// Refinement of a bracket (ga < 0 ≤ gb). Each step takes the secant through the last two
/// iterates when it falls inside the bracket and the last step at least halved the residual,
/// else the Illinois variant of regula falsi (which keeps the convergence when the secant
/// wanders). With a trace's `ahead`, the secant runs on its distance estimates rather than on
/// the gap, and the first step is the estimate from the bracket's near end: a trace's bracket
/// has one end far out in free space, where the gap is far from linear, while the estimate of
/// the distance left is linear in t on flat ground and nearly so on any smooth surface. The
/// secant of the gap through the last two iterates is the slope at the root when they are close.
fn refine(
    gap: &impl Fn(f64) -> Option<f64>,
    (mut ta, mut ga): (f64, f64),
    (mut tb, mut gb): (f64, f64),
    ahead: Option<&impl Fn(f64, f64) -> f64>,
) -> Option<Root> {
    // The residual the secant runs on: the signed distance behind the surface the estimate
    // gives (where it gives one), else the gap itself.
    let estimate = |t: f64, g: f64| ahead.map(|ahead| -ahead(t, g)).filter(|h| h.is_finite());
    let residual = |t: f64, g: f64| estimate(t, g).unwrap_or(g);
    let mut side = 0i8;
    // The last two iterates as (t, gap, residual); the bracket's ends start the sequence.
    let mut older = (ta, ga, residual(ta, ga));
    let mut last = (tb, gb, residual(tb, gb));
    for k in 0..60 {
        let falsi = (ta * gb - tb * ga) / (gb - ga);
        let guess = match (k, ahead) {
            (0, Some(_)) => Some(last.0 - last.2),
            _ => secant((older.0, older.2), (last.0, last.2)),
        };
        let converging = k == 0 || last.2.abs() <= 0.5 * older.2.abs();
        let t = match guess {
            Some(t) if t > ta && t < tb && converging => t,
            _ => falsi,
        };
        let g = gap(t)?;
        let h = estimate(t, g);
        let converged = match h {
            Some(h) => h.abs() < ROOT_TOLERANCE_M,
            None => g.abs() < 0.1 * ROOT_TOLERANCE_M,
        };
        if converged || (tb - ta).abs() < ROOT_TOLERANCE_M {
            let (tp, gp, hp) = last;
            let slope = if (t - tp).abs() <= SECANT_SPAN_M && t != tp {
                Some((g - gp) / (t - tp))
            } else {
                // The estimate's secant over the last step (nearly linear: see above) times the
                // gap's change per unit of estimate at the root (a unit gap's estimate inverted).
                h.zip(estimate(t, 1.0))
                    .filter(|_| t != tp)
                    .map(|(h, unit)| (h - hp) / (t - tp) / unit)
            };
            return Some(Root {
                t,
                slope: slope.filter(|s| s.is_finite()),
                value: Some(g),
            });
        }
        older = last;
        last = (t, g, h.unwrap_or(g));
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

/// Where the line through two points (t, value) meets zero (`None` when it is flat).
fn secant((t0, g0): (f64, f64), (t1, g1): (f64, f64)) -> Option<f64> {
    (g1 != g0).then(|| t1 - g1 * (t1 - t0) / (g1 - g0))
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
    fn a_flat_ground_trace_lands_on_the_crossing_with_its_slope_from_the_estimates() {
        // A vertical line 5 m from a sensor 1 m above flat ground, t the depth below the
        // sensor: the gap along each ray is far from linear in t (tens of metres near the
        // horizon), the estimate of the distance left exact.
        let (rho, ground) = (5.0f64, 1.0);
        let calls = std::cell::Cell::new(0);
        let gap = |t: f64| {
            calls.set(calls.get() + 1);
            let dist = rho.hypot(t);
            Some(dist * (1.0 - ground / t))
        };
        let ahead = |t: f64, g: f64| -g * t / rho.hypot(t);
        let root = first_crossing_traced(gap, (0.05, 2.0), (0.02, 0.5), ahead).expect("crossing");
        assert!((root.t - ground).abs() < 1e-9, "{root:?}");
        assert!(calls.get() <= 4, "{} evaluations", calls.get());
        // ∂gap/∂t at the ground is the distance over the depth there.
        let v = root_variance(gap, root, 1.0).expect("slope");
        let slope = rho.hypot(ground) / ground;
        assert!((v - 1.0 / (slope * slope)).abs() < 1e-9, "{v}");
    }

    #[test]
    fn traced_steps_take_the_first_crossing_in_few_evaluations() {
        // An estimate of the distance left far too generous is held to the largest step: the
        // first of the two crossings of sin(t) − 0.5 is still the one found.
        let gap = |t: f64| Some(t.sin() - 0.5);
        let root = first_crossing_traced(gap, (-1.0, 3.0), (0.05, 0.2), |_, g| -10.0 * g).expect("crossing");
        assert!((root.t - std::f64::consts::FRAC_PI_6).abs() < 1e-6, "{root:?}");
        assert!(root.gap().is_some_and(|g| g.abs() < 1e-5));
        // A surface 3 away and an exact estimate: the overshot step brackets it at once and the
        // estimate from behind lands on it (three evaluations, where even sampling at the
        // smallest step would take 300).
        let calls = std::cell::Cell::new(0);
        let line = |t: f64| {
            calls.set(calls.get() + 1);
            Some(t - 3.0)
        };
        let root = first_crossing_traced(line, (0.0, 10.0), (0.01, 5.0), |_, g| -g).expect("crossing");
        assert!(
            (root.t - 3.0).abs() < 1e-9 && calls.get() <= 3,
            "{root:?} after {} calls",
            calls.get()
        );
        // No crossing, or an unobserved stretch between free space and the surface: none.
        assert!(first_crossing_traced(|t| Some(t - 10.0), (0.0, 5.0), (0.1, 1.0), |_, g| -g).is_none());
        let gappy = |t: f64| (!(1.0..2.0).contains(&t)).then_some(t - 1.5);
        assert!(first_crossing_traced(gappy, (0.0, 5.0), (0.4, 0.4), |_, g| -g).is_none());
    }
}
