//! σ scales restored from a checkpoint: checked before use, and fitted to this daemon's
//! settings before its calibrator starts from them ([`super::Calibrator::with_prior`]).

use super::SCALE_BOUNDS;
use crate::map::correlation::LENGTH_BOUNDS_M;
use crate::map::scales::{BinScale, CellFlags, SigmaScales, DEPARTURE_WEIGHTS};

/// Whether every value of `scales` is one the calibrator could have learnt; else what is not.
/// A checkpoint whose scales fail this keeps its map and drops them.
pub fn check(scales: &SigmaScales) -> Result<(), &'static str> {
    let tables = [&scales.window, &scales.aggregate];
    if !tables
        .iter()
        .flat_map(|t| t.iter().flatten().flatten())
        .all(learnable)
    {
        return Err("a σ scale is out of its bounds, or its σ medians are mixed or not ascending");
    }
    if !scales.departure.iter().all(|w| DEPARTURE_WEIGHTS.contains(w)) {
        return Err("a departure weight is none of the weights chosen among");
    }
    let non_negative = |v: f64| v.is_finite() && v >= 0.0;
    if !(scales.relief.var_m2.iter().all(|&v| non_negative(v)) && non_negative(scales.view_disagreement)) {
        return Err("a relief variance or the disagreement weight is negative or not finite");
    }
    if !scales.tails.in_domain() {
        return Err("the tail shape is not one the fit chooses among");
    }
    let (lo, hi) = LENGTH_BOUNDS_M;
    if !(lo..=hi).contains(&scales.correlation.length_m) {
        return Err("the error correlation length is out of its bounds");
    }
    Ok(())
}

/// Whether a calibrator could have learnt `bin`: every scale within [`SCALE_BOUNDS`], the σ
/// medians all −∞ (one group) or all finite, ascending.
fn learnable(bin: &BinScale) -> bool {
    let (lo, hi) = SCALE_BOUNDS;
    let l = &bin.log_sd;
    bin.scale.iter().all(|&s| (lo..=hi).contains(&s))
        && (l.iter().all(|&v| v == f64::NEG_INFINITY) || l.iter().all(|v| v.is_finite()))
        && l.windows(2).all(|w| w[0] <= w[1])
}

/// The scales `prior` (a checkpoint's) as a daemon whose window answers count the relief
/// (`relief_in_heights`) and the other views' disagreement (`view_disagreement`) as given
/// starts from. The window's scales, departure weights and the tail shape were learnt on
/// variances that the stored settings made; under other settings they are forgotten (relearnt
/// from the next scans).
pub fn under_settings(prior: SigmaScales, relief_in_heights: bool, view_disagreement: f64) -> SigmaScales {
    let same = prior.relief_in_heights == relief_in_heights && prior.view_disagreement == view_disagreement;
    let mut scales = SigmaScales {
        relief_in_heights,
        view_disagreement,
        ..prior
    };
    if !same {
        let fresh = SigmaScales::default();
        scales.window = fresh.window;
        scales.departure = fresh.departure;
        scales.tails = fresh.tails;
        scales.learnt.window = CellFlags::default();
        scales.learnt.departure = fresh.learnt.departure;
        scales.learnt.tails = false;
    }
    scales
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn under_other_settings_the_windows_scales_are_forgotten_and_the_rest_kept() {
        let mut prior = SigmaScales {
            view_disagreement: 0.3,
            departure: [0.25; crate::map::scales::BINS],
            ..SigmaScales::default()
        };
        prior.learnt.window[1][2][3] = true;
        prior.learnt.aggregate[1][2][3] = true;
        prior.learnt.departure[4] = true;
        prior.learnt.tails = true;
        prior.tails.dof = 3.0;
        prior.correlation.length_m = 0.3;
        assert_eq!(under_settings(prior, false, 0.3), prior);
        let other = under_settings(prior, false, 0.5);
        assert_eq!(other.view_disagreement, 0.5);
        assert!(!other.learnt.window[1][2][3] && !other.learnt.departure[4] && !other.learnt.tails);
        assert_eq!(other.tails, crate::map::scales::TailShape::default());
        assert_eq!(other.departure, [0.0; crate::map::scales::BINS]);
        assert!(other.learnt.aggregate[1][2][3]);
        assert_eq!(other.correlation, prior.correlation);
        assert!(!under_settings(prior, true, 0.3).learnt.window[1][2][3]);
    }

    #[test]
    fn values_the_calibrator_cannot_learn_are_caught() {
        assert_eq!(check(&SigmaScales::default()), Ok(()));
        let damaged: [&dyn Fn(&mut SigmaScales); 8] = [
            &|s| s.window[0][0][0].scale[2] = 1e3,
            &|s| s.aggregate[1][2][3].log_sd = [f64::NEG_INFINITY, 0.0, 0.0, 0.0, 0.0],
            &|s| s.aggregate[1][2][3].log_sd = [0.0, -1.0, 0.0, 0.0, 0.0],
            &|s| s.departure[3] = 0.3,
            &|s| s.relief.var_m2[0] = f64::INFINITY,
            &|s| s.tails.dof = 2.5,
            &|s| s.tails.scale = f64::NAN,
            &|s| s.correlation.length_m = f64::MIN_POSITIVE,
        ];
        for (k, damage) in damaged.iter().enumerate() {
            let mut s = SigmaScales::default();
            damage(&mut s);
            assert!(check(&s).is_err(), "damage {k}");
        }
    }
}
