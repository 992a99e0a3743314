//! Number parsers the lab's command lines share.

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
}
