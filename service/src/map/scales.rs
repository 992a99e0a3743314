//! The learnt σ factors a snapshot applies to its answers, and their lookup: per (source, level
//! class, grazing class, range bin), each a function of the answer's own σ, interpolated so that
//! σ never jumps. [`super::calibration`] learns them; queries and the snapshot only read them.

use super::local::HeightEstimate;
use rangegp_proto::msg::Source;
use serde::{Deserialize, Serialize};

/// Upper edges of the range bins, metres of horizontal distance from the answering sensor (the
/// last bin is open-ended). Doubling widths: the error of a range map grows with range.
pub const RANGE_EDGES_M: [f64; 6] = [2.5, 5.0, 10.0, 20.0, 40.0, 80.0];
/// Number of range bins.
pub const BINS: usize = RANGE_EDGES_M.len() + 1;

/// How many groups of a bin's residuals, by the answer's own σ, get a scale each.
pub const SIGMA_GROUPS: usize = 5;

/// The σ scale of one range bin as a function of the answer's own σ: each group of residuals
/// (equal counts, by σ) has a scale at its median log σ; between medians the scale is linear in
/// log σ (see [`BinScale::factor`] beyond them). Answers the map itself is surer of can be more or less
/// overconfident than the rest, and one factor per bin cannot right both.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BinScale {
    /// Median ln σ of each group, ascending (equal when the bin has few residuals).
    pub(super) log_sd: [f64; SIGMA_GROUPS],
    /// Factor on σ of each group.
    pub(super) scale: [f64; SIGMA_GROUPS],
}

impl Default for BinScale {
    fn default() -> Self {
        Self {
            // Below every σ: the factor is 1 everywhere.
            log_sd: [f64::NEG_INFINITY; SIGMA_GROUPS],
            scale: [1.0; SIGMA_GROUPS],
        }
    }
}

impl BinScale {
    /// How wide these scales make σ (the factor at σ = 1 mm), to choose between two equally
    /// near fills of an empty cell.
    pub(super) fn width(&self) -> f64 {
        self.factor(1e-3)
    }

    /// The factor on an answer of standard deviation `sd`, interpolated in ln σ between the
    /// groups' medians; below the surest group's median that group's factor holds, above the
    /// widest group's that group's (a floor on σ itself was measured and not kept:
    /// docs/EVALUATION.md "Calibration").
    pub fn factor(&self, sd: f64) -> f64 {
        let x = sd.max(1e-12).ln();
        let (l, s) = (&self.log_sd, &self.scale);
        if x <= l[0] {
            return s[0];
        }
        for k in 1..SIGMA_GROUPS {
            if x <= l[k] {
                let w = if l[k] > l[k - 1] {
                    (x - l[k - 1]) / (l[k] - l[k - 1])
                } else {
                    1.0
                };
                return (s[k - 1].ln() * (1.0 - w) + s[k].ln() * w).exp();
            }
        }
        s[SIGMA_GROUPS - 1]
    }
}

/// Upper edges of the grazing classes (an answer's [`HeightEstimate::grazing`]; the last class
/// is open-ended and holds every answer that is not near a shadow; an aggregate answer's
/// grazing is its fusing views', fused as its height).
pub const GRAZING_EDGES: [f64; 2] = [0.5, 0.75];
/// Number of grazing classes.
pub const CLASSES: usize = GRAZING_EDGES.len() + 1;
/// Where each grazing class's scale holds exactly; between them it is interpolated in ln g.
const GRAZING_CENTRES: [f64; CLASSES] = [0.354, 0.612, 1.0];

/// Upper edges of the level classes of an answer's rise ([`HeightEstimate::rise`]), from ground
/// well below the robot's level to well above (a grade of 1 %: 0.3 m at 30 m). Ground off the
/// robot's level errs more than level ground at the same range, the more the farther off it
/// lies (docs/EVALUATION.md "Calibration", step 15).
pub const RISE_EDGES: [f64; 2] = [-0.01, 0.01];
/// Number of level classes.
pub const LEVELS: usize = RISE_EDGES.len() + 1;
/// The level class of level ground.
pub const LEVEL: usize = LEVELS / 2;
/// Where each level class's scale holds exactly (level ground at 0, the others at twice their
/// edge); between them it is interpolated linearly.
const RISE_CENTRES: [f64; LEVELS] = [-0.02, 0.0, 0.02];

/// The weights a window answer's squared departure from its nearest data
/// ([`HeightEstimate::departure`]) may take in its own variance, one learnt per range bin
/// (docs/EVALUATION.md "Calibration", step 16).
pub const DEPARTURE_WEIGHTS: [f64; 5] = [0.0, 1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0];

/// σ scales of one source, by level class, grazing class and range bin.
pub type ScaleTable = [[[BinScale; BINS]; CLASSES]; LEVELS];

/// Upper edges of the bins of an answer's distance to the nearest datum
/// ([`HeightEstimate::data_m`]), metres; the last bin is open-ended.
pub const DATA_EDGES_M: [f64; 7] = [0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 6.4];
/// Number of data-distance bins.
pub const DATA_BINS: usize = DATA_EDGES_M.len() + 1;

/// The variance of the relief an answer has not seen, by its distance to the nearest datum of
/// its map ([`HeightEstimate::data_m`]), learnt from the scans' own returns
/// ([`super::relief`]): the terrain's semivariogram for planner layers, and with `gp.unseen_relief`
/// added to window answers' calibrated variance. Linear in ln d between
/// the bins' centres, as d² below the first (no relief at a datum), the last bin's beyond.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Relief {
    /// Variance at each bin's centre, m².
    pub var_m2: [f64; DATA_BINS],
}

impl Relief {
    /// The terrain's semivariogram at distances up to `reach_m`, or `None` unless every bin up
    /// to the one holding `reach_m` is learnt ([`Semivariogram`]).
    pub fn semivariogram(&self, reach_m: f64) -> Option<Semivariogram> {
        let last = data_bin_of(reach_m.max(0.0)).min(DATA_BINS - 1);
        self.var_m2[..=last]
            .iter()
            .all(|&v| v > 0.0 && v.is_finite())
            .then_some(Semivariogram { relief: *self })
    }

    /// The relief variance at distance `data_m` from the nearest datum, m².
    pub fn var_at(&self, data_m: f64) -> f64 {
        let first = data_centre_m(0);
        if data_m.is_nan() || data_m <= 0.0 {
            return 0.0;
        }
        if data_m < first {
            return self.var_m2[0] * (data_m / first).powi(2);
        }
        let centres: [f64; DATA_BINS] = std::array::from_fn(data_centre_m);
        let (b0, b1, w) = bracket(data_m, &centres, log);
        self.var_m2[b0] * (1.0 - w) + self.var_m2[b1] * w
    }
}

/// Half the mean square of the terrain's increments over a distance s, γ(s), taken as the learnt
/// departure R(s). For a terrain whose increments grow as s^H (Hurst exponent H) the departure at
/// the midpoint of two points s either side is R(s) = 2γ(s)(1 − 4^(H−1)): γ = R for a random walk
/// (H = ½), γ ≈ 2R at H = 0.8. Reading H from how R grows was measured and not kept
/// (docs/EVALUATION.md "Planner layers").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Semivariogram {
    relief: Relief,
}

impl Semivariogram {
    /// γ at distance `s_m`, m².
    pub fn at(&self, s_m: f64) -> f64 {
        self.relief.var_at(s_m)
    }
}

/// The centre of data-distance bin `bin`, metres.
pub fn data_centre_m(bin: usize) -> f64 {
    centre_of(&DATA_EDGES_M, bin)
}

/// The data-distance bin of `data_m`.
pub fn data_bin_of(data_m: f64) -> usize {
    DATA_EDGES_M.iter().take_while(|&&e| data_m >= e).count()
}

/// Per (source, grazing class, range bin) σ scales, and for window answers the relief unseen
/// between their data; what a snapshot applies to its answers.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct SigmaScales {
    /// Window answers.
    pub window: ScaleTable,
    /// The unseen relief, by distance to the nearest datum: the terrain's own roughness, which
    /// bounds planner layers' σ ([`super::layers`]).
    pub relief: Relief,
    /// Whether window answers' variance includes the relief (`gp.unseen_relief`).
    pub relief_in_heights: bool,
    /// Weight of the other window maps' disagreement in a window answer's variance far from
    /// its data (`gp.view_disagreement`; 0: not counted).
    pub view_disagreement: f64,
    /// Weight of a window answer's squared departure from its nearest data in its own
    /// variance, by range bin (one of [`DEPARTURE_WEIGHTS`]).
    pub departure: [f64; BINS],
    /// Aggregate answers (range bin and grazing class from how the fusing scans saw the cells:
    /// `WorldAggregate::seen_at`; all level).
    pub aggregate: ScaleTable,
    /// The shape of the calibrated errors, for probabilities beyond a limit (planner risks).
    pub tails: TailShape,
    /// How the height errors of nearby answers correlate (slope σ from height σ).
    pub correlation: ErrorCorrelation,
    /// Which of these the calibrator learnt from residuals (what a restarted daemon keeps).
    pub learnt: Learnt,
}

/// Table cells' flags, by level class, grazing class and range bin.
pub type CellFlags = [[[bool; BINS]; CLASSES]; LEVELS];

/// Which parts of [`SigmaScales`] the calibrator learnt from residuals, as against filled from a
/// neighbour or left at the default: what a restarted calibrator keeps of a checkpoint's scales
/// (`calibration::Calibrator::with_prior`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Learnt {
    /// Window table cells.
    pub window: CellFlags,
    /// Aggregate table cells.
    pub aggregate: CellFlags,
    /// Departure weights, by range bin.
    pub departure: [bool; BINS],
    /// Relief variances, by data-distance bin.
    pub relief: [bool; DATA_BINS],
    /// The tail shape.
    pub tails: bool,
    /// The error correlation.
    pub correlation: bool,
}

/// Correlation length of height errors before any is learnt, metres.
pub const DEFAULT_ERROR_LENGTH_M: f64 = 0.5;

/// The correlation of the maps' height errors between two answers a distance d apart: Matérn-3/2
/// of length `length_m`, learnt by the calibrator (`map::correlation`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ErrorCorrelation {
    /// Correlation length, metres.
    pub length_m: f64,
}

impl Default for ErrorCorrelation {
    fn default() -> Self {
        Self {
            length_m: DEFAULT_ERROR_LENGTH_M,
        }
    }
}

impl ErrorCorrelation {
    /// The correlation at horizontal distance `d_m`.
    pub fn at(&self, d_m: f64) -> f64 {
        let a = 3f64.sqrt() * d_m / self.length_m;
        (1.0 + a) * (-a).exp()
    }
}

/// Degrees of freedom [`TailShape::fit`] chooses among (Gaussian besides).
const TAIL_DOFS: [f64; 9] = [1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0];

/// The shape of calibrated errors: error = `scale` · σ · T with T Student's t of `dof` degrees of
/// freedom, Gaussian when `dof` is infinite. Heavy tails make a calibrated σ too wide near the
/// mean and too narrow far out: a Gaussian then overstates the probability of a limit a little
/// beyond the mean and understates it far beyond (docs/ARCHITECTURE.md "Planner layers").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TailShape {
    /// Degrees of freedom (infinite: Gaussian).
    pub dof: f64,
    /// Factor on σ of the t's unit scale.
    pub scale: f64,
}

impl Default for TailShape {
    fn default() -> Self {
        Self {
            dof: f64::INFINITY,
            scale: 1.0,
        }
    }
}

impl TailShape {
    /// Whether [`Self::fit`] could have given it (a checkpoint's, before it is restored).
    pub fn in_domain(&self) -> bool {
        let dof_ok = self.dof == f64::INFINITY || TAIL_DOFS.contains(&self.dof);
        dof_ok && self.scale.is_finite() && self.scale > 0.0
    }

    /// The shape whose central intervals of ±1 σ and ±1.96 σ hold `cov68` and `cov95` of the
    /// errors (as measured): for each candidate degree of freedom the scale that gives `cov68`,
    /// then the candidate whose ±1.96 σ share is nearest `cov95`. Gaussian when the shares are not
    /// in (0, 1) or not increasing.
    pub fn fit(cov68: f64, cov95: f64) -> Self {
        if !(cov68 > 0.0 && cov68 < cov95 && cov95 < 1.0) {
            return Self::default();
        }
        let q = 0.5 * (1.0 + cov68);
        let gaussian = {
            let scale = 1.0 / distrs::Normal::ppf(q, 0.0, 1.0);
            let err = (2.0 * distrs::Normal::cdf(1.96 / scale, 0.0, 1.0) - 1.0 - cov95).abs();
            (
                err,
                Self {
                    dof: f64::INFINITY,
                    scale,
                },
            )
        };
        TAIL_DOFS
            .iter()
            .map(|&dof| {
                let scale = 1.0 / distrs::StudentsT::ppf(q, dof);
                let err = (2.0 * distrs::StudentsT::cdf(1.96 / scale, dof) - 1.0 - cov95).abs();
                (err, Self { dof, scale })
            })
            .chain([gaussian])
            .filter(|(err, t)| err.is_finite() && t.scale.is_finite() && t.scale > 0.0)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or_else(Self::default, |(_, t)| t)
    }

    /// P(X > limit) for X of mean `mean` and calibrated σ `sd` with this shape; a step at the
    /// limit when `sd` is 0.
    pub fn exceedance(&self, mean: f64, sd: f64, limit: f64) -> f64 {
        if sd.is_nan() || sd <= 0.0 {
            return if mean > limit { 1.0 } else { 0.0 };
        }
        let x = (limit - mean) / (self.scale * sd);
        let below = if self.dof.is_finite() {
            distrs::StudentsT::cdf(x, self.dof)
        } else {
            distrs::Normal::cdf(x, 0.0, 1.0)
        };
        (1.0 - below).clamp(0.0, 1.0)
    }

    /// P(|X| > limit) for X as in [`Self::exceedance`] (`limit` ≥ 0): both tails.
    pub fn outside(&self, mean: f64, sd: f64, limit: f64) -> f64 {
        (self.exceedance(mean, sd, limit) + self.exceedance(-mean, sd, limit)).min(1.0)
    }
}

impl SigmaScales {
    /// The variance an answer `estimate` of `source` at horizontal distance `rho_m` owns before
    /// scaling: the map's, plus for a window answer its squared departure from its nearest data
    /// weighted as learnt for that range (interpolated in ln ρ between bin centres).
    pub fn own_var(&self, source: Source, rho_m: f64, estimate: &HeightEstimate) -> f64 {
        match source {
            Source::Aggregate => estimate.var.max(0.0),
            _ => departed_var(&self.departure, rho_m, estimate),
        }
    }

    /// The factor on σ (not σ²) over [`Self::own_var`] for an answer `estimate` of `source` at
    /// horizontal distance `rho_m`. Between the centres of neighbouring range bins, grazing
    /// classes and level classes the factor is interpolated in (ln ρ, ln g, rise), so that σ
    /// never jumps at an edge.
    pub fn factor(&self, source: Source, rho_m: f64, estimate: &HeightEstimate) -> f64 {
        self.factor_over(source, rho_m, estimate, self.own_var(source, rho_m, estimate))
    }

    /// [`Self::factor`] for an answer whose own variance is `own_var`.
    fn factor_over(&self, source: Source, rho_m: f64, estimate: &HeightEstimate, own_var: f64) -> f64 {
        let table = match source {
            Source::Aggregate => &self.aggregate,
            _ => &self.window,
        };
        table_factor(table, rho_m, estimate, own_var.sqrt())
    }

    /// `estimate` (of `source`, at horizontal distance `rho_m`) calibrated: its own variance
    /// ([`Self::own_var`]) scaled by [`Self::factor`] squared, plus for a window answer the relief
    /// unseen at its distance from data; and the factor that takes its σ to the calibrated one, at least the scale alone
    /// and at most [`MAX_SD_FACTOR`] (or the scale, if larger), which a point's and a ray's σ,
    /// given along the sensor's ray, take so that they stay calibrated like the height's.
    pub fn calibrate(&self, source: Source, rho_m: f64, estimate: &HeightEstimate) -> Calibrated {
        let own_var = self.own_var(source, rho_m, estimate);
        let factor = self.factor_over(source, rho_m, estimate, own_var);
        let relief = match source {
            Source::Window if self.relief_in_heights => self.relief.var_at(estimate.data_m),
            _ => 0.0,
        };
        let raw = estimate.var.max(0.0);
        let var_m2 = own_var * factor * factor + relief;
        let sd_factor = if raw > 0.0 {
            (var_m2 / raw).sqrt().min(MAX_SD_FACTOR).max(factor)
        } else {
            factor
        };
        Calibrated {
            var_m2,
            relief_m2: relief,
            sd_factor,
        }
    }
}

/// Largest factor the unseen relief may put on an answer's σ along its ray (a map sure to a
/// micrometre at a point far from its data would otherwise scale a ray's variance without bound).
pub const MAX_SD_FACTOR: f64 = 100.0;

/// An answer calibrated ([`SigmaScales::calibrate`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibrated {
    /// Calibrated height variance, m².
    pub var_m2: f64,
    /// The unseen relief's share of `var_m2`, m² (its errors correlate differently: planner
    /// layers take it apart, [`super::layers`]).
    pub relief_m2: f64,
    /// Factor from the map's own σ to the calibrated one.
    pub sd_factor: f64,
}

/// The factor of `table` for answer `estimate` of own σ `sd` at horizontal distance `rho_m`:
/// trilinear in (ln ρ, ln g, rise) between the centres of neighbouring range bins, grazing
/// classes and level classes.
fn table_factor(table: &ScaleTable, rho_m: f64, estimate: &HeightEstimate, sd: f64) -> f64 {
    let rho_centres: [f64; BINS] = std::array::from_fn(bin_centre_m);
    let (b0, b1, wb) = bracket(rho_m, &rho_centres, log);
    let (c0, c1, wc) = bracket(estimate.grazing, &GRAZING_CENTRES, log);
    let (l0, l1, wl) = bracket(estimate.rise, &RISE_CENTRES, |x| x);
    let ln = |l: usize, c: usize, b: usize| table[l][c][b].factor(sd).ln();
    let at_level = |l: usize| {
        let lower = ln(l, c0, b0) * (1.0 - wb) + ln(l, c0, b1) * wb;
        let upper = ln(l, c1, b0) * (1.0 - wb) + ln(l, c1, b1) * wb;
        lower * (1.0 - wc) + upper * wc
    };
    (at_level(l0) * (1.0 - wl) + at_level(l1) * wl).exp()
}

/// ln x, with x floored at 1e-12.
fn log(x: f64) -> f64 {
    x.max(1e-12).ln()
}

/// The neighbouring `centres` (ascending) around `x` and the weight of the upper, linear in
/// `axis(x)`; beyond the ends (or for a NaN `x`), the end alone.
fn bracket(x: f64, centres: &[f64], axis: impl Fn(f64) -> f64) -> (usize, usize, f64) {
    let last = centres.len() - 1;
    let Some(upper) = centres.iter().position(|&c| x <= c) else {
        return (last, last, 0.0);
    };
    if upper == 0 {
        return (0, 0, 0.0);
    }
    let (lo, hi) = (axis(centres[upper - 1]), axis(centres[upper]));
    (upper - 1, upper, (axis(x) - lo) / (hi - lo))
}

/// A window answer's variance before scaling ([`SigmaScales::own_var`]): the map's, plus its
/// squared departure from its nearest data times `departure`'s weight for horizontal distance
/// `rho_m` (interpolated in ln ρ between bin centres). What the aggregate fuses a window answer
/// with, given the weights alone.
pub fn departed_var(departure: &[f64; BINS], rho_m: f64, estimate: &HeightEstimate) -> f64 {
    let rho_centres: [f64; BINS] = std::array::from_fn(bin_centre_m);
    let (b0, b1, w) = bracket(rho_m, &rho_centres, log);
    let weight = departure[b0] * (1.0 - w) + departure[b1] * w;
    estimate.var.max(0.0) + weight * estimate.departure * estimate.departure
}

/// A range bin's centre ([`centre_of`] the range edges).
fn bin_centre_m(bin: usize) -> f64 {
    centre_of(&RANGE_EDGES_M, bin)
}

/// The centre of bin `bin` of the bins `edges` bound: the geometric middle of its edges (the
/// first bin's: half its edge; the open last bin's: √2 × its lower edge).
fn centre_of(edges: &[f64], bin: usize) -> f64 {
    match bin {
        0 => 0.5 * edges[0],
        k if k == edges.len() => edges[k - 1] * std::f64::consts::SQRT_2,
        k => (edges[k - 1] * edges[k]).sqrt(),
    }
}

/// The range bin of horizontal distance `rho_m`.
pub fn bin_of(rho_m: f64) -> usize {
    RANGE_EDGES_M.iter().take_while(|&&e| rho_m >= e).count()
}

/// Whether answers of grazing class `class` are told apart by level: only far from shadows (the
/// last class). Near a shadow an answer is the map's smoothing of a jump, and its height says
/// little of the ground's level.
pub fn split_by_level(class: usize) -> bool {
    class == CLASSES - 1
}

/// The level class of an answer's rise.
pub fn level_of(rise: f64) -> usize {
    RISE_EDGES.iter().take_while(|&&e| rise >= e).count()
}

/// The grazing class of an answer's grazing fraction.
pub fn class_of(grazing: f64) -> usize {
    GRAZING_EDGES.iter().take_while(|&&e| grazing >= e).count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_semivariogram_is_the_relief_where_every_near_bin_is_learnt() {
        let walk = Relief {
            var_m2: std::array::from_fn(|b| 1e-3 * data_centre_m(b)),
        };
        let v = walk.semivariogram(0.6).expect("learnt");
        assert_eq!(v.at(0.3), walk.var_at(0.3));
        let mut unlearnt = walk;
        unlearnt.var_m2[1] = 0.0;
        assert_eq!(unlearnt.semivariogram(0.6), None);
        assert!(
            unlearnt.semivariogram(0.09).is_some(),
            "only the first bin reaches 9 cm"
        );
    }

    #[test]
    fn gaussian_shares_give_a_gaussian_and_heavy_tails_a_student_t_that_holds_them() {
        let g = TailShape::fit(0.6827, 0.95);
        assert!(g.dof >= 20.0 && (g.scale - 1.0).abs() < 0.02, "{g:?}");
        let t = TailShape::fit(0.80, 0.93);
        assert!(t.dof <= 4.0 && t.scale < 0.8, "{t:?}");
        let share = |k: f64| 1.0 - 2.0 * t.exceedance(0.0, 1.0, k);
        assert!((share(1.0) - 0.80).abs() < 1e-6);
        assert!((share(1.96) - 0.93).abs() < 0.02);
        assert_eq!(TailShape::fit(0.9, 0.8), TailShape::default());
        assert_eq!(TailShape::default().exceedance(0.3, 0.0, 0.2), 1.0);
    }

    #[test]
    fn the_factor_is_continuous_across_range_bins_grazing_and_level_classes_and_sigma_groups() {
        let mut scales = SigmaScales::default();
        for (l, level) in scales.window.iter_mut().enumerate() {
            for (c, row) in level.iter_mut().enumerate() {
                for (k, b) in row.iter_mut().enumerate() {
                    b.log_sd = [-6.0, -5.0, -4.0, -3.0, -2.0];
                    b.scale = std::array::from_fn(|g| {
                        1.0 + k as f64 + 0.5 * g as f64 + 2.0 * c as f64 + 3.0 * l as f64
                    });
                }
            }
        }
        let at_rise = |rho: f64, grazing: f64, sd: f64, rise: f64| {
            let e = HeightEstimate {
                z: 0.0,
                var: sd * sd,
                grazing,
                point_sd: [0.0, 0.0, sd],
                data_m: 0.0,
                rise,
                departure: 0.0,
            };
            scales.factor(Source::Window, rho, &e)
        };
        let at = |rho: f64, grazing: f64, sd: f64| at_rise(rho, grazing, sd, 0.0);
        let rhos = RANGE_EDGES_M.iter().copied().chain((0..BINS).map(bin_centre_m));
        let grazings = GRAZING_EDGES.iter().chain(GRAZING_CENTRES.iter()).copied();
        for rho in rhos {
            for sd in [1e-3, (-4.5f64).exp(), 0.05, 1.0] {
                let jump = (at(rho - 1e-9, 0.8, sd) - at(rho + 1e-9, 0.8, sd)).abs();
                assert!(jump < 1e-6, "jump at ρ {rho}, σ {sd}");
                let jump = (at(rho, 0.8, sd * (1.0 - 1e-9)) - at(rho, 0.8, sd)).abs();
                assert!(jump < 1e-6, "jump at σ {sd}");
            }
        }
        for g in grazings {
            let jump = (at(7.0, g - 1e-9, 0.01) - at(7.0, g + 1e-9, 0.01)).abs();
            assert!(jump < 1e-6, "jump at grazing {g}");
        }
        // The departure's weight, learnt per range bin, is interpolated like the factors.
        let mut departed = scales;
        departed.departure = std::array::from_fn(|b| DEPARTURE_WEIGHTS[b % DEPARTURE_WEIGHTS.len()]);
        let e = HeightEstimate {
            z: 0.0,
            var: 1e-4,
            grazing: 0.8,
            point_sd: [0.0, 0.0, 0.01],
            data_m: 0.0,
            rise: 0.0,
            departure: 0.2,
        };
        for rho in RANGE_EDGES_M.iter().copied().chain((0..BINS).map(bin_centre_m)) {
            let var = |r: f64| departed.calibrate(Source::Window, r, &e).var_m2;
            assert!(
                (var(rho - 1e-9) - var(rho + 1e-9)).abs() < 1e-9,
                "jump at ρ {rho}"
            );
        }
        let own = departed.own_var(Source::Window, bin_centre_m(BINS - 1), &e);
        assert!(
            (own - (1e-4 + DEPARTURE_WEIGHTS[(BINS - 1) % DEPARTURE_WEIGHTS.len()] * 0.04)).abs() < 1e-12
        );
        assert_eq!(departed.own_var(Source::Aggregate, 7.0, &e), 1e-4);
        for rise in RISE_EDGES.iter().chain(RISE_CENTRES.iter()).copied() {
            let jump = (at_rise(7.0, 0.8, 0.01, rise - 1e-9) - at_rise(7.0, 0.8, 0.01, rise + 1e-9)).abs();
            assert!(jump < 1e-6, "jump at rise {rise}");
        }
        // At a cell's centres its own factor holds; far from any shadow, the last class's; far
        // off level, the end level's.
        let (l, c, b) = (LEVELS / 2, 1, 3);
        let f = at(bin_centre_m(b), GRAZING_CENTRES[c], 0.05);
        assert!((f - scales.window[l][c][b].factor(0.05)).abs() < 1e-9);
        let f = at(bin_centre_m(b), f64::INFINITY, 0.05);
        assert!((f - scales.window[l][CLASSES - 1][b].factor(0.05)).abs() < 1e-9);
        let f = at_rise(bin_centre_m(b), f64::INFINITY, 0.05, -0.5);
        assert!((f - scales.window[0][CLASSES - 1][b].factor(0.05)).abs() < 1e-9);
        assert!(
            f < at(bin_centre_m(b), f64::INFINITY, 0.05),
            "the levels' factors differ"
        );
    }
}
