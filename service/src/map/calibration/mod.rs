//! Prequential σ calibration: each new scan tests the maps as they stood before it arrived.
//!
//! A stratified sample of the scan's returns, each taken as the mean of the returns within 5 cm of
//! it on its surface (a k-th of one return's noise, the same map error), is answered by
//! [`query::raw_elevation`] over the snapshot from before the scan. Each return is a fresh,
//! independent measurement of ground the maps already claim to know, so its residual against the
//! answer, with the returns' own noise taken out, tells how wide the answer's σ should have been.
//! Residuals are weighted by the ground area their return stands for and kept per (source, level
//! class, grazing class, range bin from the answering sensor; for the aggregate, from the sensors
//! that fused the cells there, and its grazing class from how squarely their rays met them) over
//! the last scans. The aggregate is also tested, at half weight, on every return a window map
//! answers; within a cell, each fifth of them by the answer's own σ gets the factor on σ whose 68 %
//! and 95 % intervals cover that share. The level class
//! ([`HeightEstimate::rise`](super::local::HeightEstimate::rise)) tells ground off the robot's
//! level from level ground, which err differently at the same range. Before the factors, each range
//! bin learns how much an answer's departure from its map's nearest data
//! ([`HeightEstimate::departure`](super::local::HeightEstimate::departure)) counts in its own
//! variance (`factors::departure_weights_of`). Nothing here knows the terrain or the sensor: it
//! adapts to whatever the robot drives on, and follows it when the terrain changes (the oldest
//! residuals drop out). Figures: docs/EVALUATION.md "Calibration". Every [`PAIR_EVERY_SCANS`]
//! scans, pairs of returns a footprint apart also measure how the maps' errors correlate
//! ([`super::correlation`]), and the held residuals give the errors' tail shape ([`TailShape`]):
//! what planner layers turn height σ into slope σ and risks with.

use super::correlation::{CorrelationLearner, PairResidual, PAIR_SEPARATION_M};
use super::query::{self, Answerer};
use super::relief::ReliefLearner;
use super::scales::{
    bin_of, class_of, level_of, split_by_level, ScaleTable, SigmaScales, TailShape, BINS, CLASSES, LEVEL,
    LEVELS,
};
use super::window::MapSnapshot;
use super::LocalRangeMap;
use crate::scan::ScanInput;
use nalgebra::Vector3;
use rangegp_proto::msg::Source;
use std::collections::{HashMap, VecDeque};

mod factors;
mod prior;
mod sample;

pub use prior::{check, under_settings};

use factors::{departure_weights_of, table_of, with_departure};
use sample::{map_return, stratified_sample, Sampled};

/// Default weight of the other window maps' disagreement in a window answer's variance far from
/// its data (`gp.view_disagreement`; chosen on the full calibration matrix among 0.3 and 0.5,
/// docs/EVALUATION.md "Calibration", step 9).
pub const DEFAULT_VIEW_DISAGREEMENT: f64 = 0.3;

/// Returns sampled per range bin from each scan.
pub const PER_BIN_PER_SCAN: usize = 48;
/// Residuals a bin remembers (about 30 scans at the full quota).
pub const BIN_MEMORY: usize = 1500;
/// A bin's scale stays 1 (the map's own, leave-one-out-calibrated σ) until it holds this many.
pub const MIN_RESIDUALS: usize = 40;
/// A cell's scales narrow σ (a factor under 1) only on residuals from at least this many scans;
/// until then a factor is at least 1. One scan's residuals share the errors of the few maps it
/// tested, so in a daemon's first scans a cell can look far surer than it is; widening needs no
/// such wait, as a σ too narrow is the planner's danger and one too wide only its cost.
pub const MIN_SCANS_TO_NARROW: usize = 5;
/// Bounds of a scale: σ is never shrunk below a tenth nor widened past a hundredfold.
pub const SCALE_BOUNDS: (f64, f64) = (0.1, 100.0);

/// One tested answer: squared residual, the answer's variance and the return's own noise
/// variance along z, m².
#[derive(Debug, Clone, Copy, Default)]
struct Residual {
    r2: f64,
    var: f64,
    noise_var: f64,
    /// Ground area the return stands for, relative ([`area_weight`]).
    weight: f64,
    /// The answer's distance to its map's nearest datum, metres.
    data_m: f64,
    /// The relief variance unseen at that distance (window answers with the relief in heights;
    /// else 0), m²: added to the scaled variance, as the snapshot adds it.
    relief_var: f64,
    /// The answer's squared departure from its map's nearest data
    /// ([`HeightEstimate::departure`](super::local::HeightEstimate::departure)), m².
    dep2: f64,
    /// Which observed scan it came from (the calibrator's count): how many scans a cell's
    /// residuals stand for ([`MIN_SCANS_TO_NARROW`]).
    scan: u64,
}

impl Residual {
    /// The residual with `weight` times its squared departure in its answer's own variance.
    fn with_departure(&self, weight: f64) -> Self {
        Self {
            var: self.var + weight * self.dep2,
            dep2: 0.0,
            ..*self
        }
    }
}

/// Recent residuals of one source, by level class, grazing class and range bin.
type Residuals = [[[VecDeque<Residual>; BINS]; CLASSES]; LEVELS];

/// The fitter's calibration state: recent residuals per cell and the scales they give.
#[derive(Debug, Clone, Default)]
pub struct Calibrator {
    window: Residuals,
    aggregate: Residuals,
    correlation: CorrelationLearner,
    relief: ReliefLearner,
    scales: SigmaScales,
    // Scales learnt before a restart: each part stands until it is relearnt
    // ([`Self::with_prior`]).
    prior: Option<SigmaScales>,
    // Scans observed so far (each residual says which it came from).
    observed: u64,
}

impl Calibrator {
    /// A calibrator with nothing learnt. It learns the relief unseen between data
    /// ([`super::relief`]) from maps that index their data, for planner layers; with
    /// `relief_in_heights` it also adds it to window answers' σ (`gp.unseen_relief`). Window
    /// answers far from their data count the other maps' disagreement with the default weight
    /// ([`Self::with_view_disagreement`]).
    pub fn new(relief_in_heights: bool) -> Self {
        let mut calibrator = Self::default();
        calibrator.scales.relief_in_heights = relief_in_heights;
        calibrator.scales.view_disagreement = DEFAULT_VIEW_DISAGREEMENT;
        calibrator
    }

    /// The same calibrator with another weight on the maps' disagreement (`gp.view_disagreement`).
    pub fn with_view_disagreement(mut self, weight: f64) -> Self {
        self.scales.view_disagreement = weight;
        self
    }

    /// Starts from `prior`, the scales learnt before a restart (a checkpoint's), as this
    /// calibrator's settings take them ([`under_settings`]): they are the scales at once, and
    /// each part the prior learnt counts as learnt until the calibrator has relearnt it from its
    /// own residuals: a table cell until it holds [`MIN_RESIDUALS`], a range bin's departure
    /// weight until its bin has enough to choose one, a relief bin, the tail shape and the
    /// correlation until each has its minimum. Parts the prior had filled from a neighbour are
    /// filled again from what is learnt now. A window cell's prior stands only while its range
    /// bin's departure weight is the prior's (its factor was fitted on variances that weight
    /// made). So a restarted daemon answers as calibrated as before it stopped, and no part
    /// returns to the map's raw σ on the first scans' few residuals.
    pub fn with_prior(mut self, prior: SigmaScales) -> Self {
        let prior = under_settings(
            prior,
            self.scales.relief_in_heights,
            self.scales.view_disagreement,
        );
        self.scales = prior;
        self.prior = Some(prior);
        self
    }

    /// The current scales.
    pub fn scales(&self) -> SigmaScales {
        self.scales
    }

    /// Residuals held, window then aggregate, by range bin (all grazing classes).
    #[cfg(test)]
    pub fn counts(&self) -> ([usize; BINS], [usize; BINS]) {
        let count = |r: &Residuals| std::array::from_fn(|b| r.iter().flatten().map(|c| c[b].len()).sum());
        (count(&self.window), count(&self.aggregate))
    }

    /// Tests `snapshot` (the maps before `scan`) against a stratified sample of `scan`'s returns
    /// and updates the scales; `map` is the scan's own fitted map, which gives each return's
    /// surface normal (the ground area it stands for). Returns how many returns were answered.
    /// Does nothing before the first map.
    pub fn observe(&mut self, snapshot: &MapSnapshot, scan: &ScanInput, map: &LocalRangeMap) -> usize {
        let Some(newest) = snapshot.maps().first() else {
            return 0;
        };
        self.observed += 1;
        let relief_before = self.scales.relief;
        self.relief.observe(scan, map);
        let prior = self.prior;
        (self.scales.relief, self.scales.learnt.relief) = self
            .relief
            .relief_with(prior.as_ref().map(|p| (&p.relief, &p.learnt.relief)));
        let in_heights = self.scales.relief_in_heights;
        let reference = newest.sensor_position();
        let sample = stratified_sample(scan, map, &reference);
        let sensor = map.sensor_position();
        let farther = farther_maps(snapshot, &sensor);
        let answers = query::par_map(
            &sample,
            rayon::current_num_threads(),
            |&(p, noise_var, weight)| {
                let a = primary_answer(snapshot, &sensor, p.x, p.y)?;
                let mut all = vec![(p, noise_var, weight, a, true)];
                // The aggregate is tested wherever it knows the ground, not only where no
                // window map answers: its factors are keyed on where the fusing scans stood,
                // which a return the window answers shares with ground only the aggregate
                // answers (step 22).
                if a.by != Answerer::Aggregate {
                    if let Some(b) = query::raw_aggregate_elevation(snapshot, p.x, p.y) {
                        all.push((p, noise_var, 0.5 * weight, b, false));
                    }
                }
                for &i in &farther {
                    if a.by != Answerer::Window(i) {
                        if let Some(b) = query::raw_elevation_of(snapshot, i, p.x, p.y) {
                            all.push((p, noise_var, 0.5 * weight, b, false));
                        }
                    }
                }
                Some(all)
            },
        );
        let mut touched = [false; 2];
        let mut answered = 0;
        for (p, noise_var, weight, a, primary) in answers.into_iter().flatten().flatten() {
            let r2 = (p.z - a.estimate.z).powi(2);
            if !(r2.is_finite() && a.estimate.var.is_finite()) {
                continue;
            }
            let (bins, which) = match a.by {
                Answerer::Aggregate => (&mut self.aggregate, 1),
                Answerer::Window(_) => (&mut self.window, 0),
            };
            let class = class_of(a.estimate.grazing);
            let level = if split_by_level(class) {
                level_of(a.estimate.rise)
            } else {
                LEVEL
            };
            let q = &mut bins[level][class][bin_of(a.rho_m)];
            if q.len() == BIN_MEMORY {
                q.pop_front();
            }
            q.push_back(Residual {
                r2,
                var: a.estimate.var.max(1e-14),
                noise_var,
                weight,
                data_m: a.estimate.data_m,
                relief_var: 0.0,
                dep2: a.estimate.departure.powi(2),
                scan: self.observed,
            });
            touched[which] = true;
            answered += usize::from(primary);
        }
        // The relief learnt from this scan applies to every held window residual (the new ones
        // included), and the window's scales are refitted under it.
        let relief = self.scales.relief;
        if in_heights {
            for r in self.window.iter_mut().flatten().flatten().flatten() {
                r.relief_var = relief.var_at(r.data_m);
            }
        }
        // Each range bin's weight on the departure is chosen first; the scales are fitted to
        // the variances it gives.
        let refit_window = touched[0] || (in_heights && relief != relief_before);
        if refit_window {
            (self.scales.departure, self.scales.learnt.departure) = departure_weights_of(
                &self.window,
                prior.as_ref().map(|p| (&p.departure, &p.learnt.departure)),
            );
        }
        let window = with_departure(&self.window, &self.scales.departure);
        if refit_window {
            let departure = self.scales.departure;
            let window_prior = prior.map(|p| {
                let mut flags = p.learnt.window;
                for (b, &weight) in departure.iter().enumerate() {
                    if weight != p.departure[b] {
                        flags.iter_mut().flatten().for_each(|row| row[b] = false);
                    }
                }
                (p.window, flags)
            });
            (self.scales.window, self.scales.learnt.window) =
                table_of(&window, window_prior.as_ref().map(|(t, f)| (t, f)));
        }
        if touched[1] {
            (self.scales.aggregate, self.scales.learnt.aggregate) = table_of(
                &self.aggregate,
                prior.as_ref().map(|p| (&p.aggregate, &p.learnt.aggregate)),
            );
        }
        if touched[0] || touched[1] {
            (self.scales.tails, self.scales.learnt.tails) = self.tails(&window);
        }
        if scan.sequence.is_multiple_of(PAIR_EVERY_SCANS) {
            let pairs = self.pairs(snapshot, scan, &sample);
            self.correlation.observe(&pairs);
            let prior = prior.filter(|p| p.learnt.correlation).map(|p| p.correlation);
            let learnt = self.correlation.learnt().or(prior);
            self.scales.correlation = learnt.unwrap_or_default();
            self.scales.learnt.correlation = learnt.is_some();
        }
        answered
    }

    /// Pairs of `scan`'s returns a footprint apart ([`PAIR_SEPARATION_M`]), each sampled return
    /// with the nearest other return in that band, both answered by `snapshot` (the maps before
    /// the scan) with σ calibrated by the current scales.
    fn pairs(&self, snapshot: &MapSnapshot, scan: &ScanInput, sample: &[Sampled]) -> Vec<PairResidual> {
        let cell = PAIR_SEPARATION_M.1;
        let key = |p: &Vector3<f64>| ((p.x / cell).floor() as i64, (p.y / cell).floor() as i64);
        let mut cells: HashMap<(i64, i64), Vec<Return>> = HashMap::new();
        for ray in &scan.rays {
            let (p, noise_var) = map_return(scan, ray);
            cells.entry(key(&p)).or_default().push((p, noise_var));
        }
        let partner = |p: &Vector3<f64>| -> Option<Return> {
            let (i, j) = key(p);
            let mut best: Option<(f64, Vector3<f64>, f64)> = None;
            for di in -1..=1 {
                for dj in -1..=1 {
                    for &(q, noise) in cells.get(&(i + di, j + dj)).into_iter().flatten() {
                        let d = (q.x - p.x).hypot(q.y - p.y);
                        let inside = (PAIR_SEPARATION_M.0..=PAIR_SEPARATION_M.1).contains(&d);
                        if inside && best.is_none_or(|(b, _, _)| d < b) {
                            best = Some((d, q, noise));
                        }
                    }
                }
            }
            best.map(|(_, q, noise)| (q, noise))
        };
        let answer = |p: &Vector3<f64>| -> Option<(f64, f64)> {
            let a = query::raw_elevation(snapshot, p.x, p.y)?;
            let source = match a.by {
                Answerer::Aggregate => Source::Aggregate,
                Answerer::Window(_) => Source::Window,
            };
            let var = self.scales.calibrate(source, a.rho_m, &a.estimate).var_m2;
            Some((p.z - a.estimate.z, var.sqrt()))
        };
        query::par_map(sample, rayon::current_num_threads(), |&(p, noise_p, _)| {
            let (q, noise_q) = partner(&p)?;
            let (ep, sp) = answer(&p)?;
            let (eq, sq) = answer(&q)?;
            Some(PairResidual {
                residual_m: [ep, eq],
                sd_m: [sp, sq],
                noise_var_m2: [noise_p, noise_q],
                separation_m: (q.x - p.x).hypot(q.y - p.y),
            })
        })
        .into_iter()
        .flatten()
        .collect()
    }

    /// The shape of the calibrated errors: the shares of every held residual (both sources,
    /// weighted by area; `window` with the departure in its variances) within ±1 and ±1.96
    /// calibrated σ, fitted by [`TailShape::fit`]; until [`MIN_TAIL_RESIDUALS`] count, the prior's
    /// shape where the prior had learnt it ([`Self::with_prior`]), else a Gaussian; and whether
    /// it is learnt.
    /// Only residuals whose return noise variance is at most [`LATENT_SHARE`] of the calibrated
    /// latent variance count.
    fn tails(&self, window: &Residuals) -> (TailShape, bool) {
        fn scaled<'a>(
            residuals: &'a Residuals,
            table: &'a ScaleTable,
        ) -> impl Iterator<Item = (&'a Residual, f64)> {
            let cells = residuals.iter().flatten().flatten();
            cells
                .zip(table.iter().flatten().flatten())
                .flat_map(|(q, scale)| q.iter().map(move |r| (r, scale.factor(r.var.sqrt()))))
        }
        let mut inside = [0.0; 2];
        let mut total = 0.0;
        let mut count = 0;
        let all = scaled(window, &self.scales.window).chain(scaled(&self.aggregate, &self.scales.aggregate));
        for (r, f) in all {
            let latent = f * f * r.var + r.relief_var;
            if r.noise_var > LATENT_SHARE * latent {
                continue;
            }
            let v = latent + r.noise_var;
            let w = r.weight.max(1e-9);
            total += w;
            count += 1;
            for (share, k) in inside.iter_mut().zip([1.0, 1.96]) {
                if r.r2 <= k * k * v {
                    *share += w;
                }
            }
        }
        if count < MIN_TAIL_RESIDUALS {
            return match self.prior.filter(|p| p.learnt.tails) {
                Some(p) => (p.tails, true),
                None => (TailShape::default(), false),
            };
        }
        (TailShape::fit(inside[0] / total, inside[1] / total), true)
    }
}

/// A return in map coordinates with its noise variance along z, m².
type Return = (Vector3<f64>, f64);

/// Bands of a window map's sensor displacement from the new scan's, metres: besides the map a
/// query would pick, each new return also tests the newest map of each band, if any. What the
/// nearest map's error looks like depends on how far the robot moved between the two scans
/// (its rings may land on the old ones or between them); maps that looked from farther make
/// the residuals of each range bin less dependent on the robot's speed.
pub const FARTHER_BANDS_M: [(f64, f64); 2] = [(1.5, 3.0), (3.0, 6.0)];

/// A window map whose sensor lies nearer than this to the new scan's is tested only where no
/// map from farther answers (metres): the scan's returns land on its rings, where a map errs
/// least, so a creeping robot would learn σ too narrow for the ground between the rings that
/// queries ask about (docs/EVALUATION.md "Slow robots").
pub const MIN_TEST_DISPLACEMENT_M: f64 = 0.5;

/// The answer a return at (x, y), scanned from `sensor`, tests: a query's own, unless that is a
/// window map whose sensor lay within [`MIN_TEST_DISPLACEMENT_M`] of `sensor` and a map from
/// farther answers, whose answer it then tests.
fn primary_answer(snapshot: &MapSnapshot, sensor: &Vector3<f64>, x: f64, y: f64) -> Option<query::RawAnswer> {
    let displaced = |i: usize| {
        snapshot
            .reach()
            .get(i)
            .is_some_and(|&[sx, sy, _]| (sx - sensor.x).hypot(sy - sensor.y) >= MIN_TEST_DISPLACEMENT_M)
    };
    let own = query::raw_elevation(snapshot, x, y)?;
    match own.by {
        Answerer::Window(i) if !displaced(i) => {
            Some(query::raw_window_elevation_where(snapshot, x, y, displaced).unwrap_or(own))
        }
        _ => Some(own),
    }
}

/// The newest window map of `snapshot` in each of [`FARTHER_BANDS_M`] from `sensor`.
fn farther_maps(snapshot: &MapSnapshot, sensor: &Vector3<f64>) -> Vec<usize> {
    FARTHER_BANDS_M
        .iter()
        .filter_map(|&(lo, hi)| {
            snapshot.reach().iter().position(|&[x, y, _]| {
                let d = (x - sensor.x).hypot(y - sensor.y);
                (lo..hi).contains(&d)
            })
        })
        .collect()
}

/// Every this many scans (by sequence) pairs of returns test how the maps' errors correlate (the
/// pairs need every return in a spatial hash: a few milliseconds for an OS1-64 scan).
pub const PAIR_EVERY_SCANS: u64 = 2;

/// Only residuals whose return noise variance is at most this share of the answer's calibrated
/// variance show the shape: the rest are mostly the return's own (Gaussian) noise, which would
/// hide the heavy tails of the map's errors that planner risks are about.
pub const LATENT_SHARE: f64 = 0.25;

/// Residuals held before the tail shape is fitted (a Gaussian until then).
pub const MIN_TAIL_RESIDUALS: usize = 400;

#[cfg(test)]
mod tests;
