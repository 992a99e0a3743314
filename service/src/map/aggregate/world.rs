//! The project's aggregate: a world-frame grid of cells, each holding the height of the ground
//! at its centre as predicted by the scans' range GPs (root-finding down the vertical line,
//! delta-method variance), fused across scans by inverse variance — the per-cell elevation
//! filter (seed 001 keeps the highest point per cell, a filter against vegetation that this
//! terrain does not have; a variance-weighted mean also shrinks the noise). Cells are grouped
//! into square tiles; each tile is an exact elevation GP (Matérn + the cells' fused variances as
//! known heteroscedastic noise, seed 003's two-stage idea) on the cells of the tile grown by a
//! margin, so a tile holds a bounded number of points. A new scan refits only the tiles whose
//! cells it changed. Predictions blend the covering tiles with a partition of unity (no seams).

pub use super::ledger::Cell;
use super::ledger::{CellEdit, CellEdits, FusedCell, ScanRaster};
use super::returns::{CellReturns, Measured, Plane};
use super::{Aggregate, AggregateError};
use crate::gp::{CholeskyError, JitterPolicy, Kernel};
use crate::map::elevation_gp::ElevationGp;
use crate::map::local::{normal_cdf, provenance_of, HeightEstimate, LocalRangeMap, RayEstimate};
use crate::map::root;
use crate::scan::ScanInput;
use nalgebra::Vector3;
use rangegp_proto::msg::Provenance;
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
    /// Scan predictions less certain than this (σ, metres) are not fused.
    pub max_cell_sd_m: f64,
    /// A query farther than this from every fused cell is unobserved, metres.
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
            max_gap_m: 0.75,
            max_reach_m: 10.0,
            change_detection: false,
            change_gate_sigmas: 3.29,
            change_floor_m: 0.03,
            change_confirm_scans: 2,
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
        }
    }

    /// Rebuilds an aggregate from a checkpointed state, refitting every tile.
    pub fn from_state(state: WorldState) -> Result<Self, AggregateError> {
        let mut agg = Self::new(state.params);
        agg.cells = state.cells.into_iter().collect();
        agg.inserts = state.inserts;
        agg.history = state.history.into_iter().collect();
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
            let cells: Vec<FusedCell> = self
                .predicted_cells(local, reach_m)
                .into_iter()
                // As the ledger keeps them, so that a correction takes out exactly what went in.
                .map(|(c, e)| (c, e.z as f32, e.var as f32))
                .filter(|&(_, _, var)| var > 0.0)
                .collect();
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
            for &(c, z, var) in &cells {
                if now_replaced.contains(&c) {
                    continue;
                }
                let seen = Cell {
                    z: z as f64,
                    var: var as f64,
                    scans: 1,
                };
                if !self.fuse(c, seen) {
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
            if self.history.len() == HISTORY_LEN {
                self.history.pop_front();
            }
            self.history.push_back(ScanRef {
                publisher_id: scan.publisher_id,
                sequence: scan.sequence,
                stamp_ns: scan.stamp_ns,
                insert,
                reach_m,
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
    /// only returns measure a change ([`Self::challenge`]).
    fn fuse(&mut self, c: (i32, i32), seen: Cell) -> bool {
        let Some(cell) = self.cells.get(&c).copied() else {
            self.cells.insert(c, seen);
            return true;
        };
        if self.params.change_detection && !self.agree(&cell, &seen) {
            return false;
        }
        self.cells.insert(c, fused(cell, seen));
        true
    }

    /// Tests one scan's returns in cell `c` (`plane`, through them) against what earlier returns
    /// measured there (else against the cell): agreeing, they are fused into that reference and
    /// dismiss a challenger they disagree with; disagreeing, they are held as a challenger, and
    /// `change_confirm_scans` scans that reject the reference on the same side replace the cell
    /// (not when rays of this scan, `cleared`, just did).
    /// Returns the replacement when they do: a move of the world when earlier returns were
    /// contradicted (returns against returns compare like with like, neither smoothed by a range
    /// map), a correction of the map when only predictions were.
    fn challenge(&mut self, c: (i32, i32), plane: Plane, this: u64, cleared: bool) -> Option<Replaced> {
        let cell = self.cells.get(&c).copied()?;
        let seen = Cell {
            z: plane.z,
            var: plane.var,
            scans: 1,
        };
        let earlier = self.returns.get(&c).map(|r| r.cell);
        let reference = earlier.unwrap_or(cell);
        if self.agree(&reference, &seen) {
            let measured = earlier.map_or(seen, |r| fused(r, seen));
            self.returns.insert(
                c,
                Measured {
                    cell: measured,
                    slope: plane.slope,
                },
            );
            // Returns too uncertain to tell the two apart dismiss nothing.
            if self.challengers.get(&c).is_none_or(|ch| !self.agree(ch, &seen)) {
                self.challengers.remove(&c);
            }
            return None;
        }
        let challenger = match self.challengers.get(&c) {
            Some(ch) if (ch.z - reference.z).signum() == (seen.z - reference.z).signum() => fused(*ch, seen),
            _ => seen,
        };
        if challenger.scans < self.params.change_confirm_scans || cleared {
            self.challengers.insert(c, challenger);
            return None;
        }
        self.challengers.remove(&c);
        // The earlier challengers confirmed it; the cell takes the confirming scan's own evidence,
        // as its raster in the ledger keeps it (so that a pose correction moves it with that
        // scan alone: the challengers may have been sent from other, differently wrong poses).
        let challenger = f32_cell(seen);
        self.cells.insert(c, challenger);
        self.returns.insert(
            c,
            Measured {
                cell: seen,
                slope: plane.slope,
            },
        );
        self.replaced_at.insert(c, this);
        let (x_m, y_m) = self.centre(c);
        let change = Change {
            cell: c,
            x_m,
            y_m,
            old: cell,
            new: challenger,
        };
        Some(if earlier.is_some() {
            Replaced::Moved(change)
        } else {
            Replaced::Corrected(change)
        })
    }

    /// The cells whose returns' plane rays of the scan passed below, where they crossed them,
    /// by [`CLEAR_MARGIN_M`] and 2 σ of the plane: each ray walked from the sensor to its return,
    /// cell by cell (every other ray: neighbouring rays cross the same cells). A ray is free
    /// space: whatever the returns hit there is gone.
    fn carved(&self, scan: &ScanInput, local: &LocalRangeMap, reach_m: f64) -> BTreeSet<(i32, i32)> {
        let mut carved = BTreeSet::new();
        if self.returns.is_empty() {
            return carved;
        }
        let pose = local.pose();
        let s = pose.translation.vector;
        let reach = local.max_range().min(self.params.max_reach_m).min(reach_m);
        let step = 0.5 * self.params.cell_m;
        for r in scan.rays.iter().step_by(2) {
            let (si, ci) = r.inclination.sin_cos();
            let (sa, ca) = r.azimuth.sin_cos();
            let d = pose.rotation * Vector3::new(si * ca, si * sa, ci);
            let flat = d.xy().norm();
            if flat < 1e-6 {
                continue;
            }
            // Up to the cell before the return's (the return's own cell holds what it hit).
            let end = (r.range - self.params.cell_m / flat).min(reach / flat);
            let mut t = step / flat;
            while t < end {
                let p = s + d * t;
                let c = self.cell_of(p.x, p.y);
                if let Some(m) = self.returns.get(&c) {
                    let (cx, cy) = self.centre(c);
                    if p.z < m.at(p.x - cx, p.y - cy) - CLEAR_MARGIN_M - 2.0 * m.cell.var.sqrt() {
                        carved.insert(c);
                    }
                }
                t += step / flat;
            }
        }
        carved
    }

    /// A cell that a scan's rays passed below (one scan is enough: a ray went through where
    /// something stood) takes the scan's own height there, or leaves the map where the scan has
    /// none; unless that height agrees with what the returns measured there.
    fn clear(&mut self, c: (i32, i32), local: &LocalRangeMap, this: u64) -> Option<Change> {
        let cell = self.cells.get(&c).copied()?;
        let (x_m, y_m) = self.centre(c);
        let height = local
            .elevation(x_m, y_m)
            .filter(|e| e.var > 0.0 && e.var <= self.params.max_cell_sd_m.powi(2))
            .map(|e| {
                f32_cell(Cell {
                    z: e.z,
                    var: e.var,
                    scans: 1,
                })
            });
        // The scan's own height there must disagree too: a plane through a crater's rim, carried
        // across the cell, stands above ground the rays legitimately graze.
        let reference = self.returns.get(&c).map_or(cell, |m| m.cell);
        if height.is_some_and(|h| self.agree(&reference, &h)) {
            return None;
        }
        self.challengers.remove(&c);
        self.returns.remove(&c);
        self.replaced_at.insert(c, this);
        let new = match height {
            Some(h) => {
                self.cells.insert(c, h);
                h
            }
            None => {
                self.cells.remove(&c);
                Cell {
                    z: f64::NEG_INFINITY,
                    var: cell.var,
                    scans: 0,
                }
            }
        };
        Some(Change {
            cell: c,
            x_m,
            y_m,
            old: cell,
            new,
        })
    }

    /// The scan's returns within `reach_m` binned by cell, where a cell holds at least two: the
    /// height at the cell's centre of a plane through them, with its variance (their noise, or
    /// their scatter about the plane where larger, through the fit: [`CellReturns`]). The
    /// highest return, used before, read a sloping cell differently from every view, and the
    /// top of many noisy returns lies above the ground by a couple of σ.
    fn returns_by_cell(
        &self,
        scan: &ScanInput,
        local: &LocalRangeMap,
        reach_m: f64,
    ) -> Vec<((i32, i32), Plane)> {
        let pose = local.pose();
        let s = pose.translation.vector;
        let reach = local.max_range().min(self.params.max_reach_m).min(reach_m);
        let mut bins: HashMap<(i32, i32), CellReturns> = HashMap::new();
        for r in &scan.rays {
            let (si, ci) = r.inclination.sin_cos();
            let (sa, ca) = r.azimuth.sin_cos();
            let p = pose * nalgebra::Point3::new(si * ca * r.range, si * sa * r.range, ci * r.range);
            if (p.x - s.x).hypot(p.y - s.y) >= reach {
                continue;
            }
            let sd = scan.range_sd(r.range);
            let c = self.cell_of(p.x, p.y);
            let (cx, cy) = self.centre(c);
            bins.entry(c).or_default().add(p.x - cx, p.y - cy, p.z, sd * sd);
        }
        bins.into_iter()
            .filter(|(_, b)| b.count() >= 2)
            .filter_map(|(c, b)| Some((c, b.plane()?)))
            .collect()
    }

    /// Whether two heights agree within the change gate.
    fn agree(&self, a: &Cell, b: &Cell) -> bool {
        let p = &self.params;
        let var = a.var + b.var + p.change_floor_m * p.change_floor_m;
        (a.z - b.z).powi(2) <= p.change_gate_sigmas * p.change_gate_sigmas * var
    }

    /// The insert at which cell `c` was last replaced by a change (older scans' evidence is no
    /// longer in it).
    pub fn replaced_at(&self, c: (i32, i32)) -> Option<u64> {
        self.replaced_at.get(&c).copied()
    }

    /// Applies cell edits (a pose correction's): cells whose tile is in memory, or on no page
    /// (`paged` says which tiles are on disk), change here and their tiles are refitted; the
    /// rest are returned per tile on disk, for the caller to apply to the pages
    /// ([`TilePage::apply_edits`]; a page also holds its margin's cells, so a cell's edit goes
    /// to every paged tile whose grown box holds it).
    pub fn apply_edits(
        &mut self,
        edits: HashMap<(i32, i32), CellEdit>,
        paged: &dyn Fn((i32, i32)) -> bool,
    ) -> Result<Applied, AggregateError> {
        let mut dirty = BTreeSet::new();
        let mut applied = Applied::default();
        let mut edited_tiles = BTreeSet::new();
        let on_disk = |agg: &Self, t: (i32, i32)| !agg.tiles.contains_key(&t) && paged(t);
        for (c, edit) in edits {
            if edit == CellEdit::default() {
                continue;
            }
            applied.cells_changed += 1;
            let own = self.tile_of(c);
            edited_tiles.insert(own);
            let covering: Vec<(i32, i32)> = self.tiles_covering(c).collect();
            if !on_disk(self, own) {
                match edit.apply(self.cells.get(&c).copied()) {
                    Some(cell) => self.cells.insert(c, cell),
                    None => self.cells.remove(&c),
                };
            }
            for t in covering {
                if on_disk(self, t) {
                    applied.page_edits.entry(t).or_default().push((c, edit));
                } else if !on_disk(self, own) {
                    dirty.insert(t);
                }
            }
        }
        // What returns measured, and the challengers they hold, moved with their scans; a scan's
        // returns also fed cells its prediction was left out of (no edit names those), so every
        // reference in a tile the correction edited goes: the cells are the reference until
        // returns come again.
        let n = self.params.tile_cells;
        self.returns
            .retain(|&c, _| !edited_tiles.contains(&tile_of(c, n)));
        self.challengers
            .retain(|&c, _| !edited_tiles.contains(&tile_of(c, n)));
        applied.tiles_refitted = dirty.len();
        self.refit(dirty)?;
        Ok(applied)
    }

    /// The cells within `reach_m` (at most `max_reach_m` and the scan's range) of `local`'s
    /// sensor whose height it predicts surely enough to fuse (σ ≤ `max_cell_sd_m`), in parallel
    /// on the current rayon pool.
    fn predicted_cells(&self, local: &LocalRangeMap, reach_m: f64) -> Vec<((i32, i32), HeightEstimate)> {
        let s = local.sensor_position();
        let reach = local.max_range().min(self.params.max_reach_m).min(reach_m);
        let (lo, hi) = (
            self.cell_of(s.x - reach, s.y - reach),
            self.cell_of(s.x + reach, s.y + reach),
        );
        let candidates: Vec<(i32, i32)> = (lo.0..=hi.0)
            .flat_map(|i| (lo.1..=hi.1).map(move |j| (i, j)))
            .collect();
        let max_var = self.params.max_cell_sd_m.powi(2);
        candidates
            .par_iter()
            .filter_map(|&c| {
                let (x, y) = self.centre(c);
                if (x - s.x).hypot(y - s.y) >= reach {
                    return None;
                }
                let e = local
                    .elevation(x, y)
                    .filter(|e| e.var <= max_var && e.var > 0.0)?;
                Some((c, e))
            })
            .collect()
    }

    /// Distance from tile `t`'s centre to map (x, y), metres.
    pub fn tile_distance(&self, (ti, tj): (i32, i32), x: f64, y: f64) -> f64 {
        let side = self.params.tile_cells as f64 * self.params.cell_m;
        ((ti as f64 + 0.5) * side - x).hypot((tj as f64 + 0.5) * side - y)
    }

    /// Drops the tiles whose centre lies farther than `radius_m` from map (x, y), with the
    /// cells they own, and returns them as pages (for the site map on disk). Neighbours keep
    /// their fits (their margins may have trained on dropped cells) until a scan touches them.
    pub fn evict_beyond(&mut self, x: f64, y: f64, radius_m: f64) -> Vec<TilePage> {
        // Every cell's own tile is fitted (its grown box holds the cell), so the far tiles name
        // every cell to drop.
        let gone: BTreeSet<(i32, i32)> = self
            .tiles
            .keys()
            .copied()
            .filter(|&t| self.tile_distance(t, x, y) > radius_m)
            .collect();
        if gone.is_empty() {
            return Vec::new();
        }
        let n = self.params.tile_cells;
        let mut pages: HashMap<(i32, i32), TilePage> = gone
            .iter()
            .map(|&key| {
                let (points, noise_var) = self
                    .tiles
                    .get(&key)
                    .map(|gp| {
                        let (p, v) = gp.training();
                        (p.to_vec(), v.to_vec())
                    })
                    .unwrap_or_default();
                let page = TilePage {
                    key,
                    cells: Vec::new(),
                    points,
                    noise_var,
                };
                (key, page)
            })
            .collect();
        self.tiles.retain(|t, _| !gone.contains(t));
        self.cells
            .retain(|&(i, j), cell| match pages.get_mut(&tile_of((i, j), n)) {
                Some(page) => {
                    page.cells.push(((i, j), *cell));
                    false
                }
                None => true,
            });
        let cells = &self.cells;
        self.challengers.retain(|c, _| cells.contains_key(c));
        self.replaced_at.retain(|c, _| cells.contains_key(c));
        self.returns.retain(|c, _| cells.contains_key(c));
        let mut pages: Vec<TilePage> = pages.into_values().collect();
        for page in &mut pages {
            page.cells.sort_by_key(|&(k, _)| k);
        }
        pages.sort_by_key(|p| p.key);
        pages
    }

    /// Whether tile `key` is held in memory.
    pub fn has_tile(&self, key: (i32, i32)) -> bool {
        self.tiles.contains_key(&key)
    }

    /// Brings paged-out tiles back: each page's cells (where no cell is held now) and its
    /// expert, refitted from the page's own points, so a tile that left and came back with no
    /// new scan in between answers exactly as before. A page whose tile is held is skipped.
    pub fn restore_pages(&mut self, pages: Vec<TilePage>) -> Result<usize, AggregateError> {
        let kernel = Kernel::matern32(self.params.kernel_variance, self.params.length_scale);
        let fresh: Vec<TilePage> = pages.into_iter().filter(|p| !self.has_tile(p.key)).collect();
        let fitted: Vec<((i32, i32), Option<ElevationGp>)> = fresh
            .par_iter()
            .map(|p| {
                if p.points.is_empty() || p.points.len() != p.noise_var.len() {
                    return Ok((p.key, None));
                }
                Ok((p.key, Some(fit_tile(&p.points, &p.noise_var, kernel)?)))
            })
            .collect::<Result<_, AggregateError>>()?;
        for page in &fresh {
            for &(c, cell) in &page.cells {
                self.cells.entry(c).or_insert(cell);
            }
        }
        let restored = fitted.len();
        for (key, gp) in fitted {
            if let Some(gp) = gp {
                self.tiles.insert(key, Arc::new(gp));
            }
        }
        Ok(restored)
    }

    /// The fused cells, by index.
    pub fn cells(&self) -> &HashMap<(i32, i32), Cell> {
        &self.cells
    }

    /// The fitted tiles' keys (every cell's own tile is fitted).
    pub fn tile_keys(&self) -> impl Iterator<Item = (i32, i32)> + '_ {
        self.tiles.keys().copied()
    }

    /// The cells tile `key` owns, sorted by index.
    pub fn tile_cells(&self, key: (i32, i32)) -> TileCells {
        let n = self.params.tile_cells;
        let mut cells = Vec::new();
        for i in key.0 * n..(key.0 + 1) * n {
            for j in key.1 * n..(key.1 + 1) * n {
                if let Some(&c) = self.cells.get(&(i, j)) {
                    cells.push(((i, j), c));
                }
            }
        }
        cells
    }

    /// Replaces the cells of each named tile by the given ones (an empty list empties it) and
    /// refits every tile whose grown box they fall in: how a site map takes in tiles assembled
    /// from robots. A cell given for a tile other than its own is misuse (panics). On a failed
    /// refit the cells are replaced and the old fits kept, as for an insert.
    pub fn replace_tiles(&mut self, tiles: &BTreeMap<(i32, i32), TileCells>) -> Result<(), AggregateError> {
        let mut dirty = BTreeSet::new();
        for (&key, cells) in tiles {
            for (c, _) in self.tile_cells(key) {
                self.cells.remove(&c);
            }
            for &(c, cell) in cells {
                assert_eq!(self.tile_of(c), key, "cell {c:?} given for tile {key:?}");
                self.cells.insert(c, cell);
            }
            dirty.extend((-1..=1).flat_map(|di| (-1..=1).map(move |dj| (key.0 + di, key.1 + dj))));
        }
        self.inserts += 1;
        self.refit(dirty)
    }

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

    /// Partition-of-unity weight of tile `t` at (x, y): 1 inside the tile shrunk by the margin,
    /// falling linearly to 0 at the tile grown by the margin.
    fn weight(&self, (ti, tj): (i32, i32), x: f64, y: f64) -> f64 {
        let side = self.params.tile_cells as f64 * self.params.cell_m;
        let margin = (self.params.margin_cells as f64 * self.params.cell_m).max(1e-9);
        let ramp = |v: f64, t: i32| {
            let (lo, hi) = (t as f64 * side, (t + 1) as f64 * side);
            (((v - lo + margin) / (2.0 * margin)).min((hi + margin - v) / (2.0 * margin))).clamp(0.0, 1.0)
        };
        ramp(x, ti) * ramp(y, tj)
    }

    /// Distance from map (x, y) to the nearest fused cell's centre, if one lies within
    /// `max_gap_m`.
    fn nearest_cell(&self, x: f64, y: f64) -> Option<f64> {
        let (ci, cj) = self.cell_of(x, y);
        let cell = self.params.cell_m;
        let reach = (self.params.max_gap_m / cell).ceil() as i32;
        let mut nearest = f64::INFINITY;
        // Ring by ring outwards: every centre of ring r + 1 and beyond lies at least (r + ½)
        // cells away, so a nearer one found by ring r ends the search (the same minimum as
        // visiting the whole square, in a handful of lookups where cells are dense).
        for r in 0..=reach {
            for di in -r..=r {
                let edge = di.abs() == r;
                let step = if edge { 1 } else { (2 * r).max(1) as usize };
                for dj in (-r..=r).step_by(step) {
                    let key = (ci + di, cj + dj);
                    if self.cells.contains_key(&key) {
                        let (cx, cy) = self.centre(key);
                        nearest = nearest.min((cx - x).hypot(cy - y));
                    }
                }
            }
            if nearest < (r as f64 + 0.5) * cell * (1.0 - 1e-9) {
                break;
            }
        }
        (nearest <= self.params.max_gap_m).then_some(nearest)
    }

    /// Casts a map-frame ray (unit `dir`) over the aggregate's surface up to `max_range`: the
    /// first crossing of the ray below the fused heights (sampled every half cell, then
    /// refined), its variance by the delta method through the height's, and the probability of
    /// a hit before `max_range`. Only ground within a correlation length of fused cells counts
    /// (observed or interpolated). `None` when the aggregate knows the ground nowhere along the
    /// ray. Without a crossing, the hit probability is set by the ray's closest approach to the
    /// surface (in σ of the height there), as for a local map; a ray that first meets known
    /// ground already below it crossed the surface in ground the aggregate does not know: its
    /// hit probability is then near 1 and no range is given.
    pub fn cast(
        &self,
        origin: Vector3<f64>,
        dir: Vector3<f64>,
        max_range: f64,
        sd_factor: &dyn Fn(&Vector3<f64>) -> f64,
    ) -> Option<RayEstimate> {
        let point = |t: f64| origin + dir * t;
        // Positive below the surface, negative above it: a crossing from − to + is a hit. Only
        // ground within a correlation length of data counts: beyond it the surface is the
        // tiles' smooth continuation, and a ray must not stop on it.
        let known = |x: f64, y: f64| {
            self.graded(x, y)
                .filter(|(_, p)| *p != Provenance::Extrapolated)
                .map(|(e, _)| e)
        };
        let gap = |t: f64| {
            let p = point(t);
            known(p.x, p.y).map(|e| e.z - p.z)
        };
        let samples = ((max_range / (0.5 * self.params.cell_m)).ceil() as usize).clamp(8, 4000);
        if let Some(root) = root::first_crossing(gap, 0.0, max_range, samples) {
            let hit = point(root.t);
            let (e, provenance) = self.graded(hit.x, hit.y)?;
            let f = sd_factor(&hit);
            let step = 0.25 * self.params.cell_m;
            let band = root::band_variance(gap, root, f * e.var.sqrt(), step, 0.0, max_range);
            let var = (f * f * root::root_variance(gap, root, e.var)?).max(band);
            return Some(RayEstimate {
                range: Some(root.t),
                range_var: Some(var),
                hit_probability: normal_cdf((max_range - root.t) / var.sqrt().max(1e-12)),
                provenance,
            });
        }
        // The closest approach by the tiles' own σ; the calibration's factor is asked once, there.
        let (closest, at) = (0..=samples)
            .filter_map(|k| {
                let p = point(max_range * k as f64 / samples as f64);
                self.elevation(p.x, p.y)
                    .map(|e| ((e.z - p.z) / e.var.sqrt().max(1e-12), p))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(RayEstimate {
            range: None,
            range_var: None,
            hit_probability: normal_cdf(closest / sd_factor(&at)),
            provenance: Provenance::None,
        })
    }

    /// How much data stands behind the answer at (x, y): graded by the distance to the nearest
    /// fused cell against the experts' length scale (`None` where nothing is answered). Needs no
    /// prediction: only whether one would be made.
    pub fn provenance(&self, x: f64, y: f64) -> Provenance {
        let Some(datum_m) = self.nearest_cell(x, y) else {
            return Provenance::None;
        };
        if self.covering(x, y).next().is_none() {
            return Provenance::None;
        }
        provenance_of(datum_m, self.params.length_scale)
    }

    /// The tile experts whose weight at (x, y) is positive, with the weight.
    fn covering(&self, x: f64, y: f64) -> impl Iterator<Item = (&ElevationGp, f64)> + '_ {
        let (ti, tj) = self.tile_of(self.cell_of(x, y));
        (-1..=1)
            .flat_map(move |di| (-1..=1).map(move |dj| (ti + di, tj + dj)))
            .filter_map(move |t| {
                let gp = self.tiles.get(&t)?;
                let w = self.weight(t, x, y);
                (w > 0.0).then_some((gp.as_ref(), w))
            })
    }

    /// The height at (x, y) where a fused cell lies within `max_gap_m`.
    fn estimate(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        self.nearest_cell(x, y)?;
        self.blend(x, y)
    }

    /// [`Self::estimate`] with its provenance.
    fn graded(&self, x: f64, y: f64) -> Option<(HeightEstimate, Provenance)> {
        let datum_m = self.nearest_cell(x, y)?;
        let e = self.blend(x, y)?;
        Some((e, provenance_of(datum_m, self.params.length_scale)))
    }

    /// The tiles at (x, y) blended with a partition of unity (mean and variance of the mixture).
    fn blend(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        let (mut wsum, mut m1, mut m2) = (0.0, 0.0, 0.0);
        for (gp, w) in self.covering(x, y) {
            let (m, v) = gp.predict(x, y);
            wsum += w;
            m1 += w * m;
            m2 += w * (v + m * m);
        }
        (wsum > 0.0).then(|| {
            let z = m1 / wsum;
            let var = (m2 / wsum - z * z).max(0.0);
            HeightEstimate {
                z,
                var,
                grazing: f64::INFINITY,
                point_sd: [0.0, 0.0, var.sqrt()],
                data_m: 0.0,
            }
        })
    }
}

/// A cell the returns replaced.
#[derive(Debug, Clone, Copy)]
enum Replaced {
    /// They contradicted what earlier returns measured there: the world moved (announced).
    Moved(Change),
    /// They corrected a height only range maps had predicted: the map was wrong, not the
    /// world (not announced; on rough relief these were nearly all the false changes).
    Corrected(Change),
}

/// A ray clears a cell when it passes this far below its returns' plane where it
/// crosses the cell, plus 2 σ of the plane's height, metres (less than the change gate: a ray
/// is a line, not a guess; 0.1 m against the cell's centre height left the low edge of a
/// removed object standing for a whole pass, its grazing rays never that far below).
const CLEAR_MARGIN_M: f64 = 0.05;

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
mod tests {
    use super::*;
    use crate::map::test_support::{params, scan_of};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use rangegp_sim::Heightmap;

    fn fold(agg: &mut WorldAggregate, terrain: &Heightmap, x: f64, y: f64, heading: f64) {
        let pose = Isometry3::from_parts(
            Translation3::new(x, y, 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, heading),
        );
        let scan = scan_of(terrain, pose);
        let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
        agg.insert(&scan, &local).expect("insert");
    }

    /// An aggregate whose cells are exactly a flat 4 m × 4 m block at height 0.2 m, cells
    /// (0..16, 0..16) of 0.25 m.
    fn block() -> WorldAggregate {
        let cells = (0..16)
            .flat_map(|i| {
                (0..16).map(move |j| {
                    (
                        (i, j),
                        Cell {
                            z: 0.2,
                            var: 1e-4,
                            scans: 1,
                        },
                    )
                })
            })
            .collect();
        WorldAggregate::from_state(WorldState {
            params: WorldParams::default(),
            cells,
            inserts: 1,
            history: Vec::new(),
        })
        .expect("refit")
    }

    #[test]
    fn the_ring_search_finds_the_nearest_cell_of_the_whole_square() {
        let mut agg = block();
        // Holes and an outlier, so the nearest cell is not always the one underneath.
        agg.cells.retain(|&(i, j), _| (i + 2 * j) % 5 != 0);
        let reach = (agg.params.max_gap_m / agg.params.cell_m).ceil() as i32;
        let brute = |x: f64, y: f64| {
            let (ci, cj) = agg.cell_of(x, y);
            let mut nearest = f64::INFINITY;
            for di in -reach..=reach {
                for dj in -reach..=reach {
                    if agg.cells.contains_key(&(ci + di, cj + dj)) {
                        let (cx, cy) = agg.centre((ci + di, cj + dj));
                        nearest = nearest.min((cx - x).hypot(cy - y));
                    }
                }
            }
            (nearest <= agg.params.max_gap_m).then_some(nearest)
        };
        let mut rng = rand_pcg::Pcg64::new(11, 3);
        for _ in 0..2000 {
            use rand::Rng;
            let (x, y) = (rng.random_range(-1.5..5.5), rng.random_range(-1.5..5.5));
            assert_eq!(agg.nearest_cell(x, y), brute(x, y), "at ({x}, {y})");
        }
    }

    #[test]
    fn provenance_follows_the_distance_to_the_nearest_fused_cell() {
        let agg = block();
        let at = |x: f64, y: f64| agg.elevation(x, y).map(|_| agg.provenance(x, y));
        // On a cell centre, and at a cell corner (0.18 m from four centres, within 0.3 ℓ).
        assert_eq!(at(2.125, 2.125), Some(Provenance::Observed));
        assert_eq!(at(2.0, 2.0), Some(Provenance::Observed));
        // Beyond the block's edge (the last centres are at 3.875 m): 0.5 m, 0.7 m, 0.8 m out.
        assert_eq!(at(4.375, 2.125), Some(Provenance::Interpolated));
        assert_eq!(at(4.575, 2.125), Some(Provenance::Extrapolated));
        assert_eq!(at(4.675, 2.125), None);
        let e = agg.elevation(2.125, 2.125).expect("inside");
        assert!((e.z - 0.2).abs() < 1e-3 && e.point_sd == [0.0, 0.0, e.var.sqrt()]);
    }

    #[test]
    fn a_ray_meets_the_fused_surface_where_geometry_says() {
        let agg = block();
        // From 1 m above the block's middle, 45° down along +x: the surface at z = 0.2 is met
        // 0.8 m down, i.e. after 0.8·√2 m.
        let origin = Vector3::new(1.0, 2.0, 1.0);
        let dir = Vector3::new(1.0, 0.0, -1.0).normalize();
        let hit = agg.cast(origin, dir, 5.0, &|_| 1.0).expect("known ground");
        let t = hit.range.expect("a hit");
        assert!((t - 0.8 * 2f64.sqrt()).abs() < 5e-3, "range {t}");
        assert!(hit.hit_probability > 0.99 && hit.range_var.is_some_and(|v| v > 0.0));
        assert_eq!(hit.provenance, Provenance::Observed);
        // Level and above the surface: no crossing, a small hit probability, not none.
        let miss = agg
            .cast(Vector3::new(0.5, 2.0, 1.0), Vector3::x(), 3.0, &|_| 1.0)
            .expect("known ground");
        assert!(miss.range.is_none() && miss.hit_probability < 1e-6);
        // Over nothing the aggregate knows: no answer at all.
        assert!(agg
            .cast(Vector3::new(50.0, 50.0, 1.0), Vector3::x(), 5.0, &|_| 1.0)
            .is_none());
    }

    #[test]
    fn flat_ground_is_fused_level_and_unseen_places_are_none() {
        let terrain = Heightmap::flat(60.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        assert!(agg.is_empty() && agg.elevation(3.0, 0.0).is_none());
        fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
        fold(&mut agg, &terrain, 4.0, 0.0, 0.0);
        assert!(agg.cells().values().any(|c| c.scans == 2), "overlap fused");
        for (x, y) in [(3.0, 1.0), (6.0, -1.0), (8.0, 2.5), (11.0, 0.0)] {
            let e = agg.elevation(x, y).expect("observed");
            assert!(e.z.abs() < 3e-3, "z at ({x}, {y}) = {}", e.z);
            assert!(e.var > 0.0 && e.var.sqrt() < 0.02, "σ {}", e.var.sqrt());
        }
        assert!(agg.elevation(-15.0, -15.0).is_none(), "never seen");
    }

    #[test]
    fn a_scan_refits_only_the_tiles_it_touches() {
        let terrain = Heightmap::flat(60.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        fold(&mut agg, &terrain, -20.0, 0.0, 0.0);
        let (tiles, refits) = (agg.tiles(), agg.refits());
        assert_eq!(refits, tiles as u64, "first scan fits each of its tiles once");
        let before = agg.elevation(-15.0, 1.0).expect("observed");
        // Far from the first scan: its tiles are new, the old ones untouched.
        fold(&mut agg, &terrain, 10.0, 0.0, 0.0);
        assert_eq!(agg.refits() - refits, (agg.tiles() - tiles) as u64);
        assert_eq!(agg.elevation(-15.0, 1.0), Some(before));
        // Overlapping the second scan: only some tiles refitted.
        let refits = agg.refits();
        fold(&mut agg, &terrain, 12.0, 0.0, 0.0);
        let touched = agg.refits() - refits;
        assert!(
            touched > 0 && touched < agg.tiles() as u64,
            "{touched} of {}",
            agg.tiles()
        );
    }

    #[test]
    fn eviction_pages_far_tiles_out_and_they_come_back_exactly() {
        let terrain = Heightmap::flat(80.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        fold(&mut agg, &terrain, -25.0, 0.0, 0.0);
        fold(&mut agg, &terrain, 20.0, 0.0, 0.0);
        let (tiles, cells) = (agg.tiles(), agg.len());
        let near = agg.elevation(22.0, 1.0).expect("observed");
        let far_probes: Vec<(f64, f64)> = (0..40)
            .map(|k| (-24.0 + 0.17 * k as f64, 0.9 - 0.05 * k as f64))
            .collect();
        let far_before: Vec<_> = far_probes.iter().map(|&(x, y)| agg.elevation(x, y)).collect();
        assert!(far_before.iter().filter(|e| e.is_some()).count() > 20);
        let pages = agg.evict_beyond(20.0, 0.0, 20.0);
        let evicted = pages.len();
        assert!(
            evicted > 0 && agg.tiles() == tiles - evicted,
            "{evicted} of {tiles}"
        );
        assert!(agg.elevation(-25.0, 1.0).is_none(), "far scan paged out");
        assert!(agg.cells().keys().all(|&(i, _)| (i as f64 + 0.5) * 0.25 > -5.0));
        assert_eq!(agg.elevation(22.0, 1.0), Some(near), "near tiles untouched");
        assert!(agg.evict_beyond(20.0, 0.0, 20.0).is_empty(), "idempotent");
        let paged_cells: usize = pages.iter().map(|p| p.cells.len()).sum();
        assert_eq!(agg.len() + paged_cells, cells, "every cell either held or paged");
        // Back with no scan in between: the same answers, bit for bit.
        assert_eq!(agg.restore_pages(pages.clone()).expect("refit"), evicted);
        assert_eq!((agg.tiles(), agg.len()), (tiles, cells));
        let far_after: Vec<_> = far_probes.iter().map(|&(x, y)| agg.elevation(x, y)).collect();
        assert_eq!(far_after, far_before);
        assert_eq!(
            agg.restore_pages(pages).expect("no-op"),
            0,
            "held tiles are not replaced"
        );
    }

    #[test]
    fn a_scan_far_from_everything_mapped_evicts_nothing() {
        let terrain = Heightmap::flat(80.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        let insert = |agg: &mut WorldAggregate, x: f64| {
            let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.75), UnitQuaternion::identity());
            let scan = scan_of(&terrain, pose);
            let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
            agg.insert_and_evict(&scan, &local, 20.0).expect("insert")
        };
        assert_eq!(insert(&mut agg, -25.0), 0);
        let before = agg.elevation(-22.0, 1.0).expect("observed");
        assert_eq!(insert(&mut agg, 20.0), 0, "45 m from every tile: nothing evicted");
        assert_eq!(
            agg.elevation(-22.0, 1.0),
            Some(before),
            "the mapped area survives one scan"
        );
        assert!(
            insert(&mut agg, 21.0) > 0,
            "a second scan there confirms the move"
        );
        assert!(agg.elevation(-22.0, 1.0).is_none());
    }

    #[test]
    fn a_restored_state_answers_like_the_original() {
        let terrain = Heightmap::flat(60.0, 0.05, 0.2);
        let mut agg = WorldAggregate::new(WorldParams::default());
        fold(&mut agg, &terrain, 0.0, 0.0, 0.4);
        let state = agg.state();
        let restored = WorldAggregate::from_state(state.clone()).expect("refit");
        assert_eq!(restored.state(), state);
        assert_eq!(restored.tiles(), agg.tiles());
        let json = serde_json::to_string(&state).expect("serialise");
        let back: WorldState = serde_json::from_str(&json).expect("deserialise");
        let from_json = WorldAggregate::from_state(back).expect("refit");
        for (x, y) in [(3.0, 1.0), (5.0, 3.0), (7.5, 4.0), (-20.0, 0.0)] {
            let want = agg.elevation(x, y);
            assert_eq!(restored.elevation(x, y), want, "at ({x}, {y})");
            // Text floats may lose the last bit; the map must not move by more.
            match (from_json.elevation(x, y), want) {
                (Some(a), Some(b)) => assert!((a.z - b.z).abs() < 1e-9 && (a.var - b.var).abs() < 1e-12),
                (a, b) => assert_eq!(a, b, "at ({x}, {y})"),
            }
        }
    }

    /// Scans of `terrain` from `truth`, fused with the poses `sent` (drifted or not); returns
    /// the aggregate and the ledger of what each scan fused.
    fn fused_with(
        terrain: &Heightmap,
        truth: &[Isometry3<f64>],
        sent: &[Isometry3<f64>],
    ) -> (WorldAggregate, super::super::ledger::Ledger) {
        let mut agg = WorldAggregate::new(WorldParams::default());
        let mut ledger = super::super::ledger::Ledger::new(1 << 30);
        for (k, (t, s)) in truth.iter().zip(sent).enumerate() {
            let mut scan = scan_of(terrain, *t);
            scan.pose = *s;
            scan.sequence = k as u64;
            let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
            for raster in agg.insert_all_within(&[(&scan, &local)], 8.0).expect("insert").0 {
                ledger.push(raster);
            }
        }
        (agg, ledger)
    }

    fn pose(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(x, y, 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    /// RMS height difference of two aggregates over the cells of `a`, and how many.
    fn cell_rms(a: &WorldAggregate, b: &WorldAggregate) -> (f64, usize) {
        let d: Vec<f64> = a
            .cells()
            .iter()
            .filter_map(|(c, cell)| b.cells().get(c).map(|o| o.z - cell.z))
            .collect();
        (
            (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt(),
            d.len(),
        )
    }

    #[test]
    fn a_correction_moves_drifted_scans_onto_the_map_the_true_poses_make() {
        let terrain = crate::map::test_support::family_terrain("fbm-h05-16deg", 3, 60.0);
        let level = |x: f64, y: f64, yaw: f64| {
            let p = pose(x, y, yaw);
            let ground = terrain.height(x, y).expect("on the terrain");
            Isometry3::from_parts(Translation3::new(x, y, ground + 0.75), p.rotation)
        };
        let truth: Vec<_> = (0..4)
            .map(|k| level(2.0 * k as f64, 0.5 * k as f64, 0.1 * k as f64))
            .collect();
        // Odometry drifting 5 % of the distance sideways and 2° of heading per scan.
        let drifted: Vec<_> = truth
            .iter()
            .enumerate()
            .map(|(k, t)| pose(0.0, 0.1 * k as f64, 0.035 * k as f64) * t)
            .collect();
        let (right, _) = fused_with(&terrain, &truth, &truth);
        let (mut wrong, mut ledger) = fused_with(&terrain, &truth, &drifted);
        let (before, _) = cell_rms(&right, &wrong);
        let plan = ledger.plan(|r| Some(truth[r.sequence as usize]), 0.25, &|_, _| false);
        assert_eq!(plan.moved.len(), 4);
        // A copy of the drifted map on disk, to be corrected page by page.
        let mut on_disk = wrong.clone();
        let mut pages = on_disk.evict_beyond(0.0, 0.0, -1.0);
        assert!(on_disk.tiles() == 0 && !pages.is_empty());
        let applied = wrong.apply_edits(plan.edits.clone(), &|_| false).expect("refit");
        assert!(applied.page_edits.is_empty() && applied.tiles_refitted > 0);
        ledger.commit(plan.moved);
        let (after, n) = cell_rms(&right, &wrong);
        assert!(n > 500, "{n} cells compared");
        assert!(after < 0.05 * before, "cell RMS {before:.4} m → {after:.4} m");
        // Against the terrain, at the cells the true poses mapped: as good as that map.
        let truth_rms = |agg: &WorldAggregate| {
            let e: Vec<f64> = right
                .cells()
                .keys()
                .filter_map(|&c| {
                    let (x, y) = right.centre(c);
                    Some(agg.elevation(x, y)?.z - terrain.height(x, y)?)
                })
                .collect();
            (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt()
        };
        let (corrected, ideal) = (truth_rms(&wrong), truth_rms(&right));
        assert!(
            corrected < 1.1 * ideal,
            "RMSE {corrected:.4} m corrected, {ideal:.4} m with the true poses"
        );
        // The same edits through the pages: the cells match the corrected map's in memory, and the
        // tiles fitted from the pages agree with its tiles.
        let keys: BTreeSet<(i32, i32)> = pages.iter().map(|p| p.key).collect();
        // Cells the correction moved beyond every paged tile are made in memory.
        let mut restored = WorldAggregate::new(WorldParams::default());
        let paged = restored
            .apply_edits(plan.edits, &|t| keys.contains(&t))
            .expect("refit");
        assert!(restored
            .cells()
            .keys()
            .all(|&c| !keys.contains(&restored.tile_of(c))));
        for page in &mut pages {
            if let Some(edits) = paged.page_edits.get(&page.key) {
                page.apply_edits(edits, &WorldParams::default());
            }
        }
        restored.restore_pages(pages).expect("refit");
        for (c, cell) in wrong.cells() {
            let o = restored.cells().get(c).expect("a corrected cell is on its page");
            assert!((o.z - cell.z).abs() < 1e-9 && (o.var - cell.var).abs() < 1e-12 && o.scans == cell.scans);
        }
        assert_eq!(restored.len(), wrong.len());
        // Where every tile around came back from a page (tiles made in memory for the cells
        // the correction moved beyond them were fitted without their paged neighbours' margins).
        let mut compared = 0;
        let mut inner: Vec<(i32, i32)> = wrong
            .cells()
            .keys()
            .copied()
            .filter(|&c| {
                let (ti, tj) = wrong.tile_of(c);
                (-1..=1).all(|di| (-1..=1).all(|dj| keys.contains(&(ti + di, tj + dj))))
            })
            .collect();
        inner.sort_unstable();
        for c in inner.iter().step_by(37) {
            let (x, y) = wrong.centre(*c);
            let a = wrong.elevation(x, y).expect("a fused cell is known");
            let b = restored.elevation(x, y).expect("so is its page's");
            assert!((a.z - b.z).abs() < 2e-3, "({x}, {y}): {} vs {}", a.z, b.z);
            compared += 1;
        }
        assert!(compared > 20);
    }
}
