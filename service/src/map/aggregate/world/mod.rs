//! The project's aggregate: a world-frame grid of cells, each holding the height of the ground
//! at its centre as predicted by the scans' range GPs (root-finding down the vertical line,
//! delta-method variance), fused across scans by inverse variance — the per-cell elevation
//! filter (seed 001 keeps the highest point per cell, a filter against vegetation that this
//! terrain does not have; a variance-weighted mean also shrinks the noise). Cells are grouped
//! into square tiles; each tile is an exact elevation GP (Matérn + the cells' fused variances as
//! known heteroscedastic noise, seed 003's two-stage idea) on the cells of the tile grown by a
//! margin, so a tile holds a bounded number of points. A new scan refits only the tiles whose
//! cells it changed. Predictions blend the covering tiles with a partition of unity (no seams).

mod answers;
mod change;
mod pages;
mod seen_from;
pub use seen_from::{record_in_domain, Seen, SeenRecord, SQUARE};

pub use super::ledger::Cell;
use super::ledger::{CellEdit, CellEdits, FusedCell, ScanRaster};
use super::returns::Measured;
use super::{Aggregate, AggregateError};
use crate::gp::{CholeskyError, JitterPolicy, Kernel};
use crate::map::elevation_gp::ElevationGp;
use crate::map::local::{HeightEstimate, LocalRangeMap};
use crate::map::scales::{departed_var, SigmaScales, BINS};
use crate::scan::ScanInput;
use change::Replaced;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::Arc;

/// A tile's own cells by (column, row) index: what a site map takes in per tile.
pub type TileCells = Vec<((i32, i32), Cell)>;

/// Settings of the world aggregate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WorldParams {
    /// Cell side, metres.
    pub cell_m: f64,
    /// Tile side, cells.
    pub tile_cells: i32,
    /// Margin each tile's experts train on beyond its side, cells.
    pub margin_cells: i32,
    /// Kernel variance of the elevation experts, m².
    pub kernel_variance: f64,
    /// Kernel length scale of the elevation experts, metres.
    pub length_scale: f64,
    /// Variance added to every cell's, m².
    pub nugget_m2: f64,
    /// Scan predictions whose map's own σ (before their departure from its data) exceeds this
    /// are not fused, metres.
    pub max_cell_sd_m: f64,
    /// A query farther than this from every fused cell is unobserved, metres: half the experts'
    /// length scale by default. Farther out a tile's expert continues its surface across ground
    /// no scan's prediction was fused into (the far side of a boulder, between far rings), and
    /// its calibrated σ there covered 0.80 of the errors at 95 %, against 0.96 on fused cells
    /// (docs/EVALUATION.md "Calibration", step 25). An answer-time setting: the cells do not
    /// depend on it, so a checkpoint or page written under another value is still this map's
    /// ([`Self::same_cells_as`]).
    pub max_gap_m: f64,
    /// Cells farther than this from the sensor are not fused, metres: beyond it a long-range
    /// sensor sees the ground at grazing angles (and the cells to visit grow as its square).
    /// The daemon may fuse a shorter reach to keep up with the sensor's rate.
    pub max_reach_m: f64,
    /// Detect changes (moving objects): returns that disagree with what earlier returns measured
    /// replace cells, and disagreeing predictions are left out instead of being averaged in
    /// (off: every prediction is fused, as before issue 17). Off by default: under
    /// odometry drift the map disagrees with itself where the robot returns, which looks like
    /// change, and cells replaced then are not restored by a later pose correction
    /// (docs/EVALUATION.md "World").
    pub change_detection: bool,
    /// A scan's height disagrees with a cell's when they differ by more than this many σ of
    /// their difference (3.29: χ² with one degree of freedom at 99.9 %).
    pub change_gate_sigmas: f64,
    /// σ added (in quadrature) to every disagreement test, metres: the smoothing a range map
    /// makes of edges and steps, which no single scan's σ includes; changes smaller than a few
    /// times this are fused, not reported.
    pub change_floor_m: f64,
    /// Scans whose returns must agree with each other, and not with what earlier returns
    /// measured in the cell, before the cell is replaced by them (one scan's stray returns are
    /// not a change).
    pub change_confirm_scans: u32,
}

impl Default for WorldParams {
    fn default() -> Self {
        Self {
            cell_m: 0.25,
            tile_cells: 10,
            margin_cells: 2,
            kernel_variance: 4e-4,
            length_scale: 0.6,
            nugget_m2: 1e-6,
            max_cell_sd_m: 0.1,
            max_gap_m: 0.3,
            max_reach_m: 10.0,
            change_detection: false,
            change_gate_sigmas: 3.29,
            change_floor_m: 0.03,
            change_confirm_scans: 2,
        }
    }
}

impl WorldParams {
    /// Whether cells fused under `other` are cells of these settings: every setting equal but
    /// the answer-time [`Self::max_gap_m`] and the change detection's, which act on later scans
    /// only (what a detector holds, returns and challengers, is not checkpointed).
    pub fn same_cells_as(&self, other: &WorldParams) -> bool {
        *self
            == WorldParams {
                max_gap_m: self.max_gap_m,
                change_detection: self.change_detection,
                change_gate_sigmas: self.change_gate_sigmas,
                change_floor_m: self.change_floor_m,
                change_confirm_scans: self.change_confirm_scans,
                ..*other
            }
    }
}

/// A cell replaced because its new evidence disagreed with the old (a moved object, a change).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Change {
    /// Cell index (column, row).
    pub cell: (i32, i32),
    /// The cell's centre, metres.
    pub x_m: f64,
    /// The cell's centre y, metres.
    pub y_m: f64,
    /// Height and variance before.
    pub old: Cell,
    /// Height and variance after.
    pub new: Cell,
}

/// One scan folded into the aggregate: who sent it and when it was taken.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScanRef {
    /// Publisher id.
    pub publisher_id: u64,
    /// Its sequence number.
    pub sequence: u64,
    /// Acquisition time, nanoseconds since the Unix epoch.
    pub stamp_ns: u64,
    /// The insert it was fused in (scans of one insert share it; counted from the first).
    pub insert: u64,
    /// How far from its sensor it was fused, metres.
    pub reach_m: f64,
    /// The weights its window answers' squared departures from their data took in the variance
    /// they were fused with, per range bin ([`SigmaScales::departure`], learnt by the window
    /// when it was fused): with the reach, what a replay needs to fuse it again.
    pub departure_weights: [f64; BINS],
}

/// A tile that left the area around the robot: its own cells and the points its expert was
/// fitted to, so that it comes back exactly as it left (the site map's unit on disk).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilePage {
    /// Tile index (column, row).
    pub key: (i32, i32),
    /// The cells the tile owns.
    pub cells: Vec<((i32, i32), Cell)>,
    /// The (x, y, z) points its expert was fitted to (its cells and its margin's).
    pub points: Vec<[f64; 3]>,
    /// Their noise variances, m².
    pub noise_var: Vec<f64>,
    /// How its cells were seen, sorted by index ([`WorldState::seen`]; none once a correction
    /// edited any of its cells while it was on disk).
    pub seen: Vec<SeenRecord>,
}

/// What an insert did: the tiles it evicted, each scan's fused cells (for the ledger) and the
/// cells it replaced.
#[derive(Debug, Clone, Default)]
pub struct Inserted {
    /// Tiles that left the radius (to be paged out).
    pub evicted: Vec<TilePage>,
    /// Each scan's fused cells, in the batch's order.
    pub fused: Vec<ScanRaster>,
    /// Per scan of the batch (in order), the cells its evidence replaced.
    pub changes: Vec<Vec<Change>>,
}

/// What [`WorldAggregate::apply_edits`] did, and the edits left for pages on disk.
#[derive(Debug, Clone, Default)]
pub struct Applied {
    /// Cells whose evidence changed.
    pub cells_changed: u64,
    /// Tiles refitted in memory.
    pub tiles_refitted: usize,
    /// Edits for tiles on disk, by tile.
    pub page_edits: BTreeMap<(i32, i32), CellEdits>,
}

impl TilePage {
    /// Applies cell edits to the page's own cells and to the points its expert is fitted to
    /// (its cells and its margin's; a margin point keeps no count of scans, so its precision
    /// alone says when nothing is left of it).
    pub fn apply_edits(&mut self, edits: &[((i32, i32), CellEdit)], params: &WorldParams) {
        let (cell_m, n) = (params.cell_m, params.tile_cells);
        let index = |x: f64, y: f64| ((x / cell_m).floor() as i32, (y / cell_m).floor() as i32);
        let mut points: BTreeMap<(i32, i32), Cell> = self
            .points
            .iter()
            .zip(&self.noise_var)
            .map(|(p, v)| {
                let var = (v - params.nugget_m2).max(f64::MIN_POSITIVE);
                (
                    index(p[0], p[1]),
                    Cell {
                        z: p[2],
                        var,
                        scans: u32::MAX / 2,
                    },
                )
            })
            .collect();
        let mut cells: BTreeMap<(i32, i32), Cell> = self.cells.iter().copied().collect();
        for &(c, edit) in edits {
            let after = if tile_of(c, n) == self.key {
                let after = edit.apply(cells.get(&c).copied());
                match after {
                    Some(cell) => cells.insert(c, cell),
                    None => cells.remove(&c),
                };
                after
            } else {
                edit.apply(points.get(&c).copied())
            };
            match after {
                Some(cell) => points.insert(c, cell),
                None => points.remove(&c),
            };
        }
        // As in memory, a cell a correction edited forgets how it was seen.
        let edited: BTreeSet<(i32, i32)> = edits.iter().map(|&(c, _)| c).collect();
        self.seen.retain(|(c, _)| !edited.contains(c));
        self.cells = cells.into_iter().collect();
        self.points = points
            .iter()
            .map(|(&(i, j), c)| [(i as f64 + 0.5) * cell_m, (j as f64 + 0.5) * cell_m, c.z])
            .collect();
        self.noise_var = points.values().map(|c| c.var + params.nugget_m2).collect();
    }
}

/// Scans the aggregate remembers having folded in, newest last (provenance for operators and for
/// replaying a checkpoint; older entries are forgotten, the count is kept).
pub const HISTORY_LEN: usize = 4096;

/// What a checkpoint of the aggregate holds (tiles are refitted from the cells on restore).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldState {
    /// Settings.
    pub params: WorldParams,
    /// Cells by (column, row) index, sorted.
    pub cells: Vec<((i32, i32), Cell)>,
    /// Scans folded in since the aggregate was created.
    pub inserts: u64,
    /// The newest of them (at most [`HISTORY_LEN`]), oldest first.
    pub history: Vec<ScanRef>,
    /// Where the last scans' sensors stood, (x, y) in metres, oldest first (at most
    /// [`VIEWS_KEPT`]): how new the next scan's view is ([`INDEPENDENT_VIEW_M`]).
    pub views: Vec<[f64; 2]>,
    /// How each cell that has a record was seen, sorted by index: the fusing sensors' distance
    /// (metres) and their rays' grazing ([`WorldAggregate::seen_at`]), which key the aggregate's
    /// σ factors.
    pub seen: Vec<SeenRecord>,
}

/// The world-frame tiled elevation aggregate.
#[derive(Debug, Clone)]
pub struct WorldAggregate {
    params: WorldParams,
    cells: HashMap<(i32, i32), Cell>,
    // Disagreeing evidence per cell (the scans fused together), until confirmed (then it replaces
    // the cell) or contradicted.
    challengers: HashMap<(i32, i32), Cell>,
    // The insert at which each replaced cell was replaced: older scans' evidence is gone from it.
    replaced_at: HashMap<(i32, i32), u64>,
    // Each cell's height as the scans' returns measured it (each scan's plane through its
    // returns in the cell, fused): what a change is tested against. Not checkpointed: after a
    // restart the cells themselves are the reference until returns come again.
    returns: HashMap<(i32, i32), Measured>,
    // Shared so that a published copy costs the cells and one pointer per tile.
    tiles: HashMap<(i32, i32), Arc<ElevationGp>>,
    refits: u64,
    inserts: u64,
    history: VecDeque<ScanRef>,
    // The sensors (x, y) of the last scans fused as views (share at least [`MIN_VIEW_SHARE`]),
    // newest last: how new a scan's view is ([`view_share`]). Cleared by a correction that
    // moves cells: the first scan after one counts in full.
    views: VecDeque<[f64; 2]>,
    // The window's departure weights as last learnt: how much a window answer's departure from
    // its data weighs, per range bin, in the variance it is fused with (none until learnt). Not
    // checkpointed: relearnt.
    departure_weights: [f64; BINS],
    // How each fused cell was seen: its sensors' distance and their rays' grazing, fused by
    // inverse variance as its height (`seen_from`): what the aggregate's σ factors are keyed on.
    // Checkpointed and paged: a cell corrected or replaced has none until a scan fuses it again
    // (answers there fall back to the distance from the newest sensor, seen squarely).
    seen_from: HashMap<(i32, i32), seen_from::SeenFrom>,
}

impl WorldAggregate {
    /// An empty aggregate (panics on non-positive sizes: caller's misuse).
    pub fn new(params: WorldParams) -> Self {
        assert!(
            params.cell_m > 0.0 && params.tile_cells > 0 && params.margin_cells >= 0,
            "bad world-aggregate sizes"
        );
        Self {
            params,
            cells: HashMap::new(),
            challengers: HashMap::new(),
            replaced_at: HashMap::new(),
            returns: HashMap::new(),
            tiles: HashMap::new(),
            refits: 0,
            inserts: 0,
            history: VecDeque::new(),
            views: VecDeque::new(),
            departure_weights: [0.0; BINS],
            seen_from: HashMap::new(),
        }
    }

    /// Takes the departure weights of the window's σ scales as last learnt: from the next insert
    /// on, a window answer is fused with the variance they give it before scaling
    /// ([`SigmaScales::own_var`]).
    pub fn set_window_scales(&mut self, window_scales: &SigmaScales) {
        self.departure_weights = window_scales.departure;
    }

    /// Rebuilds an aggregate from a checkpointed state, refitting every tile.
    pub fn from_state(state: WorldState) -> Result<Self, AggregateError> {
        let mut agg = Self::new(state.params);
        agg.cells = state.cells.into_iter().collect();
        agg.inserts = state.inserts;
        agg.history = state.history.into_iter().collect();
        agg.views = state.views.into_iter().collect();
        agg.restore_seen_from(&state.seen);
        let all: BTreeSet<(i32, i32)> = agg.cells.keys().flat_map(|&c| agg.tiles_covering(c)).collect();
        agg.refit(all)?;
        Ok(agg)
    }

    /// The state to checkpoint (cells sorted by index, so equal maps give equal bytes).
    pub fn state(&self) -> WorldState {
        let mut cells: Vec<((i32, i32), Cell)> = self.cells.iter().map(|(&k, &v)| (k, v)).collect();
        cells.sort_by_key(|&(k, _)| k);
        WorldState {
            params: self.params,
            cells,
            inserts: self.inserts,
            history: self.history.iter().copied().collect(),
            views: self.views.iter().copied().collect(),
            seen: self.seen_records(),
        }
    }

    /// Its settings.
    pub fn params(&self) -> &WorldParams {
        &self.params
    }

    /// The scans it remembers having folded in (at most [`HISTORY_LEN`]), oldest first.
    pub fn history(&self) -> impl Iterator<Item = &ScanRef> {
        self.history.iter()
    }

    /// Scans folded in since creation (restored with a checkpoint).
    pub fn inserts(&self) -> u64 {
        self.inserts
    }

    /// The newest scan folded in.
    pub fn newest_scan(&self) -> Option<ScanRef> {
        self.history.back().copied()
    }

    /// Fitted tiles.
    pub fn tiles(&self) -> usize {
        self.tiles.len()
    }

    /// Tile fits since creation (a scan refits only the tiles it touched).
    pub fn refits(&self) -> u64 {
        self.refits
    }

    /// Folds a scan in, then evicts the tiles beyond `radius_m` of its sensor: see
    /// [`Self::insert_all_and_evict`].
    pub fn insert_and_evict(
        &mut self,
        scan: &ScanInput,
        local: &LocalRangeMap,
        radius_m: f64,
    ) -> Result<usize, AggregateError> {
        self.insert_all_and_evict(&[(scan, local)], radius_m, self.params.max_reach_m)
            .map(|inserted| inserted.evicted.len())
    }

    /// Folds every scan of `batch` in, each out to `reach_m` of its sensor (at most
    /// `max_reach_m`; in order; each tile they touch is refitted once), then
    /// evicts the tiles beyond `radius_m` of the last scan's sensor, but only when the map held
    /// a tile within that radius before the insert. A scan far from everything mapped (a pose
    /// glitch, or the first scan of a relocalised robot) adds its tiles and evicts nothing, so no
    /// single scan can empty the map. Returns the evicted tiles; an empty batch does nothing.
    pub fn insert_all_and_evict(
        &mut self,
        batch: &[(&ScanInput, &LocalRangeMap)],
        radius_m: f64,
        reach_m: f64,
    ) -> Result<Inserted, AggregateError> {
        let Some((_, newest)) = batch.last() else {
            return Ok(Inserted::default());
        };
        let s = newest.sensor_position();
        let connected = self.tiles.is_empty()
            || self
                .tiles
                .keys()
                .any(|&t| self.tile_distance(t, s.x, s.y) <= radius_m);
        let (fused, changes) = self.insert_all_within(batch, reach_m)?;
        let evicted = if connected {
            self.evict_beyond(s.x, s.y, radius_m)
        } else {
            Vec::new()
        };
        Ok(Inserted {
            evicted,
            fused,
            changes,
        })
    }

    /// Folds every scan of `batch` in, in order, each out to `reach_m` of its sensor (at most
    /// `max_reach_m`; a scan's cost grows as the square of its reach): each scan's predicted cell
    /// heights are fused by inverse variance, then every tile any of them touched is refitted
    /// once (a batch costs the cells of each scan but the refits of one). On a failed refit the
    /// aggregate keeps the fused cells and the tiles it had; the caller publishes a copy only on
    /// success.
    pub fn insert_all_within(
        &mut self,
        batch: &[(&ScanInput, &LocalRangeMap)],
        reach_m: f64,
    ) -> Result<(Vec<ScanRaster>, Vec<Vec<Change>>), AggregateError> {
        let mut dirty = BTreeSet::new();
        let mut changes = Vec::with_capacity(batch.len());
        let insert = self.history.back().map_or(0, |r| r.insert + 1);
        let reach_m = reach_m.min(self.params.max_reach_m);
        let mut fused = Vec::with_capacity(batch.len());
        for (scan, local) in batch {
            let sensor = local.sensor_position();
            let share = view_share(&self.views, sensor.x, sensor.y);
            let cells = self.predicted_cells(local, reach_m);
            let this = self.inserts;
            let mut kept = Vec::with_capacity(cells.len());
            let mut replaced = Vec::new();
            // Rays that pass below the returns' plane of a cell: what stood there has left.
            let watch = self.params.change_detection;
            let carved = if watch {
                self.carved(scan, local, reach_m)
            } else {
                BTreeSet::new()
            };
            let returns = if watch {
                self.returns_by_cell(scan, local, reach_m)
            } else {
                Vec::new()
            };
            // Announced: what the world did (a correction of the map's own guess is not news).
            let mut moved = Vec::new();
            for c in carved {
                if let Some(change) = self.clear(c, local, this) {
                    replaced.push(change);
                    moved.push(change);
                    dirty.extend(self.tiles_covering(c));
                }
            }
            // A cell is replaced once per scan (the ledger keeps one height of it per scan).
            let cleared: BTreeSet<(i32, i32)> = moved.iter().map(|c| c.cell).collect();
            // The scan's own returns: where they disagree with what earlier returns measured
            // there, something moved.
            for (c, plane) in returns {
                match self.challenge(c, plane, this, cleared.contains(&c)) {
                    Some(Replaced::Moved(change)) => {
                        replaced.push(change);
                        moved.push(change);
                    }
                    Some(Replaced::Corrected(change)) => replaced.push(change),
                    None => continue,
                }
                dirty.extend(self.tiles_covering(c));
            }
            // A replaced cell's whole evidence is this scan's (for the ledger); its prediction
            // there is not fused again.
            for change in &replaced {
                if change.new.z.is_finite() {
                    kept.push((change.cell, change.new.z as f32, change.new.var as f32));
                }
            }
            let now_replaced: BTreeSet<(i32, i32)> = replaced.iter().map(|c| c.cell).collect();
            for &((c, z, var), grazing) in &cells {
                if now_replaced.contains(&c) {
                    continue;
                }
                // Where the cell holds earlier views, this one counts as its share of an
                // independent view: its variance is divided by the share (nothing under
                // [`MIN_VIEW_SHARE`]). A cell seen for the first time takes it in full.
                let var = match self.cells.contains_key(&c) {
                    false => var,
                    true if share >= MIN_VIEW_SHARE => var / share as f32,
                    true => continue,
                };
                let seen = Cell {
                    z: z as f64,
                    var: var as f64,
                    scans: 1,
                };
                let (x, y) = self.centre(c);
                if !self.fuse(c, seen, (x - sensor.x).hypot(y - sensor.y), grazing) {
                    continue;
                }
                kept.push((c, z, var));
                dirty.extend(self.tiles_covering(c));
            }
            let mut raster = ScanRaster::new(
                (scan.publisher_id, scan.sequence, scan.stamp_ns),
                *local.pose(),
                &kept,
            );
            raster.insert = this;
            fused.push(raster);
            changes.push(moved);
            self.inserts += 1;
            // Only a view that counted is remembered: a robot creeping by less than the least
            // share a scan still builds up distance from the last view that did.
            if share >= MIN_VIEW_SHARE {
                if self.views.len() == VIEWS_KEPT {
                    self.views.pop_front();
                }
                self.views.push_back([sensor.x, sensor.y]);
            }
            if self.history.len() == HISTORY_LEN {
                self.history.pop_front();
            }
            self.history.push_back(ScanRef {
                publisher_id: scan.publisher_id,
                sequence: scan.sequence,
                stamp_ns: scan.stamp_ns,
                insert,
                reach_m,
                departure_weights: self.departure_weights,
            });
        }
        self.refit(dirty)?;
        Ok((fused, changes))
    }

    /// Folds one scan's predicted height `seen` at cell `c` in, by inverse variance, and says
    /// whether it did: with change detection on, a prediction that disagrees with the cell is
    /// left out instead. Predictions never replace a cell: a range map's height between its
    /// rings, behind an edge or at a rim depends on where it was seen from, so two views of an
    /// unchanged world disagree there (on rough relief that was most of the false changes);
    /// only returns measure a change ([`Self::challenge`]). The view's sensor stood
    /// `distance_m` from the cell and its rays met it at `grazing` ([`Self::fold_seen_from`]).
    fn fuse(&mut self, c: (i32, i32), seen: Cell, distance_m: f64, grazing: f64) -> bool {
        let before = self.cells.get(&c).copied();
        if let Some(cell) = before {
            if self.params.change_detection && !self.agree(&cell, &seen) {
                return false;
            }
        }
        self.cells
            .insert(c, before.map_or(seen, |cell| fused(cell, seen)));
        self.fold_seen_from(c, before, seen, distance_m, grazing);
        true
    }

    /// The cells within `reach_m` (at most `max_reach_m` and the scan's range) of `local`'s
    /// sensor whose height it predicts surely enough to fuse, with their answers and the
    /// grazing of its rays there ([`Self::window_answer`]), in parallel on the current rayon
    /// pool.
    fn predicted_cells(&self, local: &LocalRangeMap, reach_m: f64) -> Vec<(FusedCell, f64)> {
        let s = local.sensor_position();
        let reach = local.max_range().min(self.params.max_reach_m).min(reach_m);
        let (lo, hi) = (
            self.cell_of(s.x - reach, s.y - reach),
            self.cell_of(s.x + reach, s.y + reach),
        );
        let candidates: Vec<(i32, i32)> = (lo.0..=hi.0)
            .flat_map(|i| (lo.1..=hi.1).map(move |j| (i, j)))
            .collect();
        candidates
            .par_iter()
            .filter_map(|&c| {
                let (x, y) = self.centre(c);
                if (x - s.x).hypot(y - s.y) >= reach {
                    return None;
                }
                self.window_answer(local, c)
                    .map(|(z, var, grazing)| ((c, z, var), grazing))
            })
            .collect()
    }

    /// `local`'s answer at the centre of cell `c` as the aggregate fuses it: its height and the
    /// variance the window owns there ([`departed_var`]: the map's, plus its squared
    /// departure from the map's nearest data as weighted for that range), rounded as the ledger
    /// keeps them (f32), so that a correction takes out exactly what went in; and its rays'
    /// grazing there. `None` where the map's own σ exceeds `max_cell_sd_m`.
    fn window_answer(&self, local: &LocalRangeMap, c: (i32, i32)) -> Option<(f32, f32, f64)> {
        let (x, y) = self.centre(c);
        let max_var = self.params.max_cell_sd_m.powi(2);
        let e = local
            .elevation(x, y)
            .filter(|e| e.var <= max_var && e.var > 0.0)?;
        let s = local.sensor_position();
        let var = departed_var(&self.departure_weights, (x - s.x).hypot(y - s.y), &e) as f32;
        (var > 0.0 && var.is_finite()).then_some((e.z as f32, var, e.grazing))
    }

    /// The centre of cell `c`, metres.
    fn centre(&self, (i, j): (i32, i32)) -> (f64, f64) {
        (
            (i as f64 + 0.5) * self.params.cell_m,
            (j as f64 + 0.5) * self.params.cell_m,
        )
    }

    /// The index (column, row) of the cell holding map (x, y).
    pub fn cell_of(&self, x: f64, y: f64) -> (i32, i32) {
        (
            (x / self.params.cell_m).floor() as i32,
            (y / self.params.cell_m).floor() as i32,
        )
    }

    fn tile_of(&self, c: (i32, i32)) -> (i32, i32) {
        tile_of(c, self.params.tile_cells)
    }

    /// Tiles whose grown box contains cell `c`.
    fn tiles_covering(&self, c: (i32, i32)) -> impl Iterator<Item = (i32, i32)> + '_ {
        let (ti, tj) = self.tile_of(c);
        let (n, m) = (self.params.tile_cells, self.params.margin_cells);
        let inside = move |v: i32, t: i32| v >= t * n - m && v < (t + 1) * n + m;
        (-1..=1)
            .flat_map(move |di| (-1..=1).map(move |dj| (ti + di, tj + dj)))
            .filter(move |&(a, b)| inside(c.0, a) && inside(c.1, b))
    }

    /// Refits the experts of `tiles` in parallel from their cells.
    fn refit(&mut self, tiles: BTreeSet<(i32, i32)>) -> Result<(), AggregateError> {
        let (n, m) = (self.params.tile_cells, self.params.margin_cells);
        let kernel = Kernel::matern32(self.params.kernel_variance, self.params.length_scale);
        let fitted: Vec<((i32, i32), Option<ElevationGp>)> = tiles
            .into_par_iter()
            .map(|(ti, tj)| {
                let mut points = Vec::new();
                let mut noise = Vec::new();
                for i in ti * n - m..(ti + 1) * n + m {
                    for j in tj * n - m..(tj + 1) * n + m {
                        if let Some(c) = self.cells.get(&(i, j)) {
                            let (x, y) = self.centre((i, j));
                            points.push([x, y, c.z]);
                            noise.push(c.var + self.params.nugget_m2);
                        }
                    }
                }
                if points.is_empty() {
                    return Ok(((ti, tj), None));
                }
                Ok(((ti, tj), Some(fit_tile(&points, &noise, kernel)?)))
            })
            .collect::<Result<_, AggregateError>>()?;
        self.refits += fitted.len() as u64;
        for (key, gp) in fitted {
            match gp {
                Some(gp) => self.tiles.insert(key, Arc::new(gp)),
                None => self.tiles.remove(&key),
            };
        }
        Ok(())
    }
}

/// The tile (column, row) of tiles `tile_cells` cells on a side that holds cell `c`.
fn tile_of((i, j): (i32, i32), tile_cells: i32) -> (i32, i32) {
    (i.div_euclid(tile_cells), j.div_euclid(tile_cells))
}

/// A cell as the ledger keeps heights (f32), so that a correction takes out exactly this.
fn f32_cell(c: Cell) -> Cell {
    Cell {
        z: c.z as f32 as f64,
        var: c.var as f32 as f64,
        scans: c.scans,
    }
}

/// Scans whose sensors lie closer than this view the ground from nearly the same place, metres:
/// their rings fall on the same ground, so their heights between the rings err alike, and
/// fusing them as independent would shrink σ with every scan of a robot creeping or standing
/// still (measured: docs/EVALUATION.md "Slow robots").
pub const INDEPENDENT_VIEW_M: f64 = 0.5;

/// A view sharing less than this of an independent one adds nothing to cells already fused.
pub const MIN_VIEW_SHARE: f64 = 0.05;

/// The recent sensors a new scan's view is compared with.
pub const VIEWS_KEPT: usize = 64;

/// The share of an independent view a scan from (x, y) brings: its distance to the nearest of
/// the `views` fused before, over [`INDEPENDENT_VIEW_M`], at most 1 (1 with none).
fn view_share(views: &VecDeque<[f64; 2]>, x: f64, y: f64) -> f64 {
    views
        .iter()
        .map(|[vx, vy]| (x - vx).hypot(y - vy) / INDEPENDENT_VIEW_M)
        .fold(1.0, f64::min)
}

/// Two heights fused by inverse variance.
fn fused(a: Cell, b: Cell) -> Cell {
    let var = 1.0 / (1.0 / a.var + 1.0 / b.var);
    Cell {
        z: var * (a.z / a.var + b.z / b.var),
        var,
        scans: a.scans + b.scans,
    }
}

/// One tile's expert: fitted to its cells, then its variance scaled locally by its own
/// leave-one-out residuals (fused cells whose neighbours disagree with them more than their
/// variances allow widen σ around themselves: rough ground, steps, and scans whose errors were
/// fused as if independent).
fn fit_tile(points: &[[f64; 3]], noise_var: &[f64], kernel: Kernel) -> Result<ElevationGp, CholeskyError> {
    let mut gp = ElevationGp::fit(points, noise_var, kernel, JitterPolicy::default())?;
    gp.widen_locally();
    Ok(gp)
}

impl Aggregate for WorldAggregate {
    fn name(&self) -> &'static str {
        "world tiled elevation experts"
    }

    fn insert(&mut self, scan: &ScanInput, local: &LocalRangeMap) -> Result<(), AggregateError> {
        self.insert_all_within(&[(scan, local)], self.params.max_reach_m)
            .map(|_| ())
    }

    fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        self.estimate(x, y)
    }

    fn len(&self) -> usize {
        self.cells.len()
    }
}

#[cfg(test)]
mod tests;
