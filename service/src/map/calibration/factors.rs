//! The σ factors of held residuals: per source, level class, grazing class, range bin and fifth
//! by σ.

use super::{Residual, Residuals, MIN_RESIDUALS, MIN_SCANS_TO_NARROW, SCALE_BOUNDS};
use crate::map::scales::{
    split_by_level, BinScale, CellFlags, ScaleTable, BINS, CLASSES, DEPARTURE_WEIGHTS, LEVEL, LEVELS,
    SIGMA_GROUPS,
};
use std::collections::VecDeque;

/// The scales of one source, and which cells were learnt. A cell with [`MIN_RESIDUALS`] is
/// learnt from them; one with fewer that `prior` learnt (the scales restored from before a
/// restart, with their flags) keeps the prior's, as learnt. Any other cell takes the scales of
/// the nearest learnt range bin of its grazing class and level class (the wider, between two
/// as near); a class with none at all takes the nearest class's of its level, and a level with
/// none at all the nearest level's. So an empty cell neither pulls its neighbours'
/// interpolation toward 1 nor answers with the map's raw σ. Where the level is not told apart
/// ([`split_by_level`]) every level holds level ground's scales.
pub(super) fn table_of(
    residuals: &Residuals,
    prior: Option<(&ScaleTable, &CellFlags)>,
) -> (ScaleTable, CellFlags) {
    // A class not split by level learns at level ground only, and its other levels' cells
    // are copies: the prior counts there alone too.
    let counts = |l: usize, c: usize| split_by_level(c) || l == LEVEL;
    let mut learnt: CellFlags = std::array::from_fn(|l| {
        std::array::from_fn(|c| {
            std::array::from_fn(|b| {
                residuals[l][c][b].len() >= MIN_RESIDUALS
                    || (counts(l, c) && prior.is_some_and(|(_, flags)| flags[l][c][b]))
            })
        })
    });
    let cell = |l: usize, c: usize, b: usize| {
        let own = &residuals[l][c][b];
        if own.len() >= MIN_RESIDUALS {
            Some(bin_scale_of(own))
        } else {
            prior.filter(|_| learnt[l][c][b]).map(|(table, _)| table[l][c][b])
        }
    };
    let levels: Vec<Option<LevelScales>> = (0..LEVELS)
        .map(|l| {
            let rows: Vec<Option<[BinScale; BINS]>> = (0..CLASSES)
                .map(|c| row_of(&(0..BINS).map(|b| cell(l, c, b)).collect::<Vec<_>>()))
                .collect();
            filled_classes(&rows)
        })
        .collect();
    let width = |level: &LevelScales| level.iter().flatten().map(BinScale::width).sum::<f64>();
    let mut table: ScaleTable =
        std::array::from_fn(|l| nearest_filled(&levels, l, width).unwrap_or_default());
    let (level, level_learnt) = (table[LEVEL], learnt[LEVEL]);
    for (scales, flags) in table.iter_mut().zip(learnt.iter_mut()) {
        for c in 0..CLASSES {
            if !split_by_level(c) {
                scales[c] = level[c];
                flags[c] = level_learnt[c];
            }
        }
    }
    (table, learnt)
}

/// Residuals of one range bin (all level and grazing classes) weighed for its departure weight,
/// at most this many (an even stride through them): the choice fits scales five times over.
pub const DEPARTURE_SAMPLE: usize = 2500;

/// Each range bin's weight on an answer's squared departure from its nearest data in its own
/// variance: of [`DEPARTURE_WEIGHTS`], the one under which the bin's held residuals (all level
/// and grazing classes), with the scales they then get, fall within 1 σ most nearly as often
/// as a Gaussian's do, 68 % (their 95 % is what the scales aim at); of two as near, the
/// smaller. The departure tells large errors from small ones near the sensor, and counts for
/// less far out, where the data thin and every answer departs from them. A bin with too few
/// residuals keeps `prior`'s weight where the prior learnt one (restored from before a restart,
/// with its flags); else it takes its nearest learnt neighbour's; with none anywhere, 0. Also
/// returns which bins are learnt.
pub(super) fn departure_weights_of(
    residuals: &Residuals,
    prior: Option<(&[f64; BINS], &[bool; BINS])>,
) -> ([f64; BINS], [bool; BINS]) {
    let learnt: Vec<Option<f64>> = (0..BINS)
        .map(|b| {
            let pooled: Vec<Residual> = residuals
                .iter()
                .flatten()
                .flat_map(|c| c[b].iter().copied())
                .collect();
            let stride = pooled.len().div_ceil(DEPARTURE_SAMPLE).max(1);
            let pooled: Vec<Residual> = pooled.into_iter().step_by(stride).collect();
            (pooled.len() >= SIGMA_GROUPS * MIN_RESIDUALS).then(|| {
                let area = weight_in(&pooled);
                let total: f64 = pooled.iter().map(&area).sum();
                let miss = |weight: f64| {
                    let own: VecDeque<Residual> = pooled.iter().map(|r| r.with_departure(weight)).collect();
                    // The scales as the residuals would have them, however few scans: a weight
                    // chosen under the rule for few scans would narrow σ by the back door.
                    let scale = bin_scales(&own);
                    let inside: f64 = own
                        .iter()
                        .filter(|r| {
                            let f = scale.factor(r.var.sqrt());
                            r.r2 <= f * f * r.var + r.relief_var + r.noise_var
                        })
                        .map(&area)
                        .sum();
                    (inside / total - GAUSSIAN_1SD).abs()
                };
                let mut best = (0.0, f64::INFINITY);
                for weight in DEPARTURE_WEIGHTS {
                    let m = miss(weight);
                    if m < best.1 {
                        best = (weight, m);
                    }
                }
                best.0
            })
        })
        .collect();
    let learnt: Vec<Option<f64>> = learnt
        .into_iter()
        .enumerate()
        .map(|(b, own)| own.or(prior.filter(|(_, flags)| flags[b]).map(|(weights, _)| weights[b])))
        .collect();
    (
        std::array::from_fn(|b| nearest_filled(&learnt, b, |w| *w).unwrap_or(0.0)),
        std::array::from_fn(|b| learnt[b].is_some()),
    )
}

/// The share of a Gaussian within 1 σ of its mean.
const GAUSSIAN_1SD: f64 = 0.6827;

/// `residuals` with each range bin's `weights` times their squared departure in their own
/// variances.
pub(super) fn with_departure(residuals: &Residuals, weights: &[f64; BINS]) -> Residuals {
    let mut out = residuals.clone();
    for class in out.iter_mut().flatten() {
        for (q, &weight) in class.iter_mut().zip(weights) {
            for r in q {
                *r = r.with_departure(weight);
            }
        }
    }
    out
}

/// Scales by grazing class and range bin.
type LevelScales = [[BinScale; BINS]; CLASSES];

/// One level's rows by grazing class, gaps filled from the nearest grazing class; `None` when
/// no row has a learnt cell.
fn filled_classes(rows: &[Option<[BinScale; BINS]>]) -> Option<LevelScales> {
    let width = |row: &[BinScale; BINS]| row.iter().map(BinScale::width).sum::<f64>();
    rows.iter()
        .any(Option::is_some)
        .then(|| std::array::from_fn(|c| nearest_filled(rows, c, width).unwrap_or_default()))
}

/// One grazing class's scales by range bin from its learnt cells, gaps filled from the nearest
/// bin; `None` when no bin is learnt.
fn row_of(learnt: &[Option<BinScale>]) -> Option<[BinScale; BINS]> {
    learnt
        .iter()
        .any(Option::is_some)
        .then(|| std::array::from_fn(|k| nearest_filled(learnt, k, BinScale::width).unwrap_or_default()))
}

/// `items[k]` if present, else the nearest present one (of two as near, the one `width` calls
/// wider).
fn nearest_filled<T: Copy>(items: &[Option<T>], k: usize, width: impl Fn(&T) -> f64) -> Option<T> {
    (0..items.len()).find_map(|d| {
        let below = k.checked_sub(d).and_then(|i| items[i]);
        let above = items.get(k + d).copied().flatten();
        match (below, above) {
            (Some(a), Some(b)) => Some(if width(&a) >= width(&b) { a } else { b }),
            (a, b) => a.or(b),
        }
    })
}

/// The scales of one bin: its residuals sorted by the answer's σ, cut into [`SIGMA_GROUPS`]
/// groups of equal count when each can hold [`MIN_RESIDUALS`] (else one group for all); none
/// under 1 while they come from fewer than [`MIN_SCANS_TO_NARROW`] scans.
fn bin_scale_of(residuals: &VecDeque<Residual>) -> BinScale {
    let mut out = bin_scales(residuals);
    if !from_enough_scans(residuals) {
        out.scale = out.scale.map(|s| s.max(1.0));
    }
    out
}

/// Whether a cell's `residuals` (held in the order they were observed, so one scan's lie
/// together) come from at least [`MIN_SCANS_TO_NARROW`] scans.
fn from_enough_scans(residuals: &VecDeque<Residual>) -> bool {
    let needed = MIN_SCANS_TO_NARROW - 1;
    let next_scans = residuals
        .iter()
        .zip(residuals.iter().skip(1))
        .filter(|(a, b)| a.scan != b.scan);
    !residuals.is_empty() && next_scans.take(needed).count() == needed
}

/// [`bin_scale_of`] before its rule for few scans (what a departure weight is chosen under).
fn bin_scales(residuals: &VecDeque<Residual>) -> BinScale {
    let mut sorted: Vec<Residual> = residuals.iter().copied().collect();
    sorted.sort_by(|a, b| a.var.total_cmp(&b.var));
    let mut out = BinScale::default();
    if sorted.is_empty() {
        return out;
    }
    let group = |g: &[Residual]| (0.5 * g[g.len() / 2].var.ln(), scale_of(g));
    if sorted.len() < SIGMA_GROUPS * MIN_RESIDUALS {
        // One group: every slot holds the whole bin's scale.
        let (log_sd, scale) = group(&sorted);
        out.log_sd = [log_sd; SIGMA_GROUPS];
        out.scale = [scale; SIGMA_GROUPS];
        return out;
    }
    let n = sorted.len();
    for k in 0..SIGMA_GROUPS {
        (out.log_sd[k], out.scale[k]) = group(&sorted[k * n / SIGMA_GROUPS..(k + 1) * n / SIGMA_GROUPS]);
    }
    out
}

/// The σ scale of one group: within the band where 93–97 % of residuals fall inside 1.96 σ and
/// 62–74 % inside 1 σ, the one nearest to 95 % coverage; where heavy tails leave no such band, the
/// geometric middle of the two demands. 1 until [`MIN_RESIDUALS`] are held. Never below 1 where
/// most of the group's weight lies in residuals whose return noise exceeds the map's own
/// variance ([`noise_dominated`]): those residuals cannot show a map too unsure, only one too
/// sure.
pub(super) fn scale_of(residuals: &[Residual]) -> f64 {
    if residuals.len() < MIN_RESIDUALS {
        return 1.0;
    }
    let least = if noise_dominated(residuals) {
        1.0
    } else {
        SCALE_BOUNDS.0
    };
    let at = |k: f64, share: f64| scale_for_coverage(residuals, k, share);
    let target = at(1.96, 0.95);
    let lo = at(1.96, 0.93).max(at(1.0, 0.62));
    let hi = at(1.96, 0.97).min(at(1.0, 0.74));
    let s = if lo <= hi {
        target.clamp(lo, hi)
    } else {
        (lo * hi).sqrt()
    };
    s.clamp(least, SCALE_BOUNDS.1)
}

/// Whether most of the residuals' weight ([`weight_in`]) lies where the return's own noise
/// variance exceeds the map's variance. A return 3 cm noisy tests a map of 5 mm σ hardly at all:
/// any scale of σ down to the smallest covers it, so the bisection would shrink σ to its bound
/// (seen near a VLP-16, whose 3 cm floor the daemon measures). The unseen relief does not count
/// here: it is part of the answer's σ, so a scale it makes small still leaves σ covering.
fn noise_dominated(residuals: &[Residual]) -> bool {
    let weight = weight_in(residuals);
    let all: f64 = residuals.iter().map(&weight).sum();
    let noisy: f64 = residuals
        .iter()
        .filter(|r| r.noise_var > r.var)
        .map(&weight)
        .sum();
    noisy > 0.5 * all
}

/// Each residual's weight among `residuals`: the ground area it stands for, or 1 each where the
/// weights sum to nothing (every return on a vertical face).
fn weight_in(residuals: &[Residual]) -> impl Fn(&Residual) -> f64 {
    let by_area = residuals.iter().map(|r| r.weight).sum::<f64>() > 0.0;
    move |r: &Residual| if by_area { r.weight } else { 1.0 }
}

/// The smallest scale s (bisection in log s over [`SCALE_BOUNDS`]) at which a `share` of the
/// residuals lies within k·sqrt(s²·var + relief_var + noise_var).
fn scale_for_coverage(residuals: &[Residual], k: f64, share: f64) -> f64 {
    let weight = weight_in(residuals);
    let need = share * residuals.iter().map(&weight).sum::<f64>();
    let covered = |s: f64| {
        let s2 = s * s;
        residuals
            .iter()
            .filter(|r| r.r2 <= k * k * (s2 * r.var + r.relief_var + r.noise_var))
            .map(&weight)
            .sum::<f64>()
    };
    let (mut lo, mut hi) = (SCALE_BOUNDS.0.ln(), SCALE_BOUNDS.1.ln());
    for _ in 0..30 {
        let mid = 0.5 * (lo + hi);
        if covered(mid.exp()) >= need {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi.exp()
}
