//! The bars a run must meet (docs/EVALUATION.md). Full mode checks the bars of the issue and of
//! the seed-000 evaluation design (docs/EVALUATION.md "Bars"); quick mode (CI) checks thresholds set about 25 % above what
//! the quick sizes measured when the full run met its bars, so a regression in map quality fails CI
//! while the run stays deterministic (every scan, split and optimiser start is seeded).

use super::Summary;

/// An upper or lower limit on one headline number.
struct Bar {
    /// The summary.json key.
    key: &'static str,
    /// The measured value.
    value: f64,
    /// Inclusive limits.
    limits: (f64, f64),
}

impl Bar {
    fn at_most(key: &'static str, value: f64, max: f64) -> Self {
        Self {
            key,
            value,
            limits: (f64::NEG_INFINITY, max),
        }
    }
    fn within(key: &'static str, value: f64, min: f64, max: f64) -> Self {
        Self {
            key,
            value,
            limits: (min, max),
        }
    }
    /// A line saying how the bar was missed, or `None` when it holds (NaN never holds).
    fn missed(&self) -> Option<String> {
        let (lo, hi) = self.limits;
        (!(self.value >= lo && self.value <= hi))
            .then(|| format!("{} = {:.4} outside [{lo}, {hi}]", self.key, self.value))
    }
}

/// The limits of one mode.
struct Limits {
    local_range_rmse_z: f64,
    local_coverage95: (f64, f64),
    aggregate_rmse_z: f64,
    overhang_ray_rmse: f64,
}

/// Full mode: the bars.
const FULL: Limits = Limits {
    local_range_rmse_z: 0.0121,
    local_coverage95: (0.90, 0.99),
    aggregate_rmse_z: 0.02,
    overhang_ray_rmse: 0.02,
};

/// Quick mode: about 1.25 × the quick sizes' measurements (docs/EVALUATION.md lists both).
const QUICK: Limits = Limits {
    local_range_rmse_z: 0.0158,
    local_coverage95: (0.88, 0.99),
    aggregate_rmse_z: 0.0135,
    overhang_ray_rmse: 0.021,
};

/// Every bar `summary` misses, one line each.
pub fn failures(summary: &Summary) -> Vec<String> {
    let l = if summary.quick { &QUICK } else { &FULL };
    let mut bars = Vec::new();
    let mut extra = Vec::new();
    if let Some(s) = &summary.local {
        bars.push(Bar::at_most(
            "local.range_rmse_z",
            s.range_rmse_z,
            l.local_range_rmse_z,
        ));
        let (lo, hi) = l.local_coverage95;
        bars.push(Bar::within("local.coverage95", s.coverage95, lo, hi));
        let (range_cv, elev_cv) = (s.report.range.length_scale_cv, s.report.elevation.length_scale_cv);
        if range_cv.partial_cmp(&elev_cv) != Some(std::cmp::Ordering::Less) {
            extra.push(format!(
                "range-GP length-scale CV {range_cv:.3} is not below the elevation GP's {elev_cv:.3}"
            ));
        }
    }
    if let Some(s) = &summary.aggregate {
        bars.push(Bar::at_most("aggregate.rmse_z", s.rmse_z, l.aggregate_rmse_z));
        for (key, v) in [
            ("aggregate.seed000_rmse_z", s.seed000_rmse_z),
            ("aggregate.batch_elev_rmse_z", s.batch_elev_rmse_z),
        ] {
            bars.push(Bar::within(key, v, 0.0, f64::MAX));
        }
    }
    if let Some(s) = &summary.overhang {
        bars.push(Bar::at_most("overhang.ray_rmse", s.ray_rmse, l.overhang_ray_rmse));
    }
    bars.iter().filter_map(Bar::missed).chain(extra).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bar_holds_inside_and_is_missed_outside_or_on_nan() {
        assert!(Bar::at_most("k", 0.01, 0.02).missed().is_none());
        assert!(Bar::at_most("k", 0.03, 0.02).missed().is_some());
        assert!(Bar::at_most("k", f64::NAN, 0.02).missed().is_some());
        assert!(Bar::within("k", 0.95, 0.9, 0.99).missed().is_none());
        assert!(Bar::within("k", 0.85, 0.9, 0.99).missed().is_some());
        assert!(Bar::within("k", 1.0, 0.9, 0.99).missed().is_some());
    }
}
