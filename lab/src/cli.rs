//! Number parsers and options the lab's command lines share.

use rangegp_sim::ScannerPreset;

/// A finite number that `ok` accepts, else `why` (the lab's CLIs parse their numbers with it).
pub(crate) fn within(s: &str, ok: impl Fn(f64) -> bool, why: &str) -> std::result::Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{s}: {e}"))?;
    if v.is_finite() && ok(v) {
        Ok(v)
    } else {
        Err(format!("{s}: {why}"))
    }
}

/// Parses `--chassis-m`, the side of the square chassis a simulated sensor tilts with: a
/// finite side in [0.2, 5] m.
pub fn chassis_side(s: &str) -> std::result::Result<f64, String> {
    within(
        s,
        |v| (0.2..=5.0).contains(&v),
        "the chassis side must lie in [0.2, 5] m",
    )
}

/// Parses `--weak-returns-m`, the range at which a simulated sensor just detects a surface met
/// squarely: a finite range in [1, 1000] m.
pub fn weak_return_range(s: &str) -> std::result::Result<f64, String> {
    within(
        s,
        |v| (1.0..=1000.0).contains(&v),
        "the weak-return range must lie in [1, 1000] m",
    )
}

/// How a simulated sensor rides and what it fails to return: the options `scangen`,
/// `record-sim` and `rangegp-eval` (its calibration and layers drives) share.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct SimSensorArgs {
    /// Side of a square chassis whose wheels rest on the ground, metres: the sensor tilts
    /// with the slopes it drives (default: level on any slope).
    #[arg(long, value_parser = chassis_side)]
    pub chassis_m: Option<f64>,
    /// Range at which the sensor just detects a surface met squarely, metres: grazed ground
    /// farther out than this × √cos(incidence) returns nothing, as on a real device (default:
    /// every ray within the maximum range returns).
    #[arg(long, value_parser = weak_return_range)]
    pub weak_returns_m: Option<f64>,
}

impl SimSensorArgs {
    /// `preset` losing weak returns beyond `--weak-returns-m`, when given.
    pub fn preset(&self, preset: ScannerPreset) -> ScannerPreset {
        match self.weak_returns_m {
            Some(range_m) => preset.with_weak_returns(range_m),
            None => preset,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chassis_side_outside_its_range_or_not_a_number_is_refused() {
        assert_eq!(chassis_side("1.0"), Ok(1.0));
        for bad in ["0.1", "6", "NaN", "inf", "one"] {
            assert!(chassis_side(bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn a_weak_return_range_outside_its_range_or_not_a_number_is_refused() {
        assert_eq!(weak_return_range("80"), Ok(80.0));
        for bad in ["0.5", "2000", "NaN", "-inf", "far"] {
            assert!(weak_return_range(bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn the_sensor_options_set_the_weak_return_range_only_when_given() {
        let vlp16 = ScannerPreset::vlp16();
        let none = SimSensorArgs::default().preset(vlp16.clone());
        assert_eq!(none.weak_return_range_m, vlp16.weak_return_range_m);
        let weak = SimSensorArgs {
            weak_returns_m: Some(60.0),
            ..SimSensorArgs::default()
        };
        assert_eq!(weak.preset(vlp16).weak_return_range_m, Some(60.0));
    }
}
