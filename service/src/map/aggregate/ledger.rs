//! The aggregate's ledger: what each scan fused into which cells, kept so that a corrected pose
//! can take a scan's evidence out of the cells it was fused into and put it where it belongs.
//!
//! A scan's contribution is its range GP's height at the centre of every cell it reached: a
//! raster in the world grid at the pose it was fused with. A correction moves that pose by a
//! rigid transform D; the moved raster's height at a new cell centre c is the old surface's point
//! that D carries above c (bilinear between the old centres, found by a few fixed-point steps),
//! raised as D raises it. A range map lives in its sensor's frame, so its predictions move with
//! the sensor exactly; the interpolation between the old centres is the only approximation (a
//! quarter of a cell's curvature). Heights and variances are kept as f32, and fused as f32
//! (rounded before fusing), so taking a scan out of a cell removes exactly what went in.

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};

/// A fused cell: the height at its centre and its variance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    /// Height, metres.
    pub z: f64,
    /// Variance, m².
    pub var: f64,
    /// Scans fused into it.
    pub scans: u32,
}

/// One scan's fused cells and the pose it was fused with.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanRaster {
    /// Publisher id.
    pub publisher_id: u64,
    /// Sequence number.
    pub sequence: u64,
    /// Acquisition time, ns.
    pub stamp_ns: u64,
    /// The sensor pose the cells were predicted from.
    pub pose: Isometry3<f64>,
    /// The aggregate's count of scans when this one was fused (a cell replaced by a change at a
    /// later count no longer holds its evidence).
    pub insert: u64,
    origin: (i32, i32),
    cols: usize,
    rows: usize,
    /// Heights, metres, row-major from `origin` (NaN: no cell).
    z: Vec<f32>,
    /// Variances, m² (NaN: no cell).
    var: Vec<f32>,
}

/// A cell index with the height and variance a scan fused into it.
pub type FusedCell = ((i32, i32), f32, f32);

impl ScanRaster {
    /// The raster of `cells` (any order) fused from a scan at `pose`.
    pub fn new(
        (publisher_id, sequence, stamp_ns): (u64, u64, u64),
        pose: Isometry3<f64>,
        cells: &[FusedCell],
    ) -> Self {
        let lo = cells.iter().fold((i32::MAX, i32::MAX), |a, &((i, j), _, _)| {
            (a.0.min(i), a.1.min(j))
        });
        let hi = cells.iter().fold((i32::MIN, i32::MIN), |a, &((i, j), _, _)| {
            (a.0.max(i), a.1.max(j))
        });
        let (cols, rows) = if cells.is_empty() {
            (0, 0)
        } else {
            ((hi.0 - lo.0 + 1) as usize, (hi.1 - lo.1 + 1) as usize)
        };
        let mut raster = Self {
            publisher_id,
            sequence,
            stamp_ns,
            pose,
            insert: 0,
            origin: lo,
            cols,
            rows,
            z: vec![f32::NAN; cols * rows],
            var: vec![f32::NAN; cols * rows],
        };
        for &((i, j), z, var) in cells {
            let k = raster.index(i, j).expect("inside its own bounds");
            raster.z[k] = z;
            raster.var[k] = var;
        }
        raster
    }

    fn index(&self, i: i32, j: i32) -> Option<usize> {
        let (a, b) = (i - self.origin.0, j - self.origin.1);
        (a >= 0 && b >= 0 && (a as usize) < self.cols && (b as usize) < self.rows)
            .then(|| b as usize * self.cols + a as usize)
    }

    fn at(&self, i: i32, j: i32) -> Option<(f32, f32)> {
        let k = self.index(i, j)?;
        (!self.var[k].is_nan()).then(|| (self.z[k], self.var[k]))
    }

    /// The cells it fused, with their heights and variances.
    pub fn cells(&self) -> impl Iterator<Item = FusedCell> + '_ {
        (0..self.rows).flat_map(move |b| {
            (0..self.cols).filter_map(move |a| {
                let k = b * self.cols + a;
                (!self.var[k].is_nan()).then(|| {
                    let c = (self.origin.0 + a as i32, self.origin.1 + b as i32);
                    (c, self.z[k], self.var[k])
                })
            })
        })
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        std::mem::size_of::<Self>() + 8 * self.z.len()
    }

    /// Height and variance of the scan's surface at (x, y), from the four nearest cell centres:
    /// precision bilinear, height bilinear weighted by precision (a range map's heights are
    /// surest on its rings and vary fast between them: plain bilinear let the unsure samples
    /// between rings pull as hard as the sure ones, +8 % RMSE after a correction on the sim
    /// family; weighted by precision the corrected map equals the one mapped with the true poses).
    /// Past the raster's edge (a corner missing) the present ones are used when they hold at
    /// least half the weight.
    fn interpolate(&self, x: f64, y: f64, cell_m: f64) -> Option<(f64, f64)> {
        let (u, v) = (x / cell_m - 0.5, y / cell_m - 0.5);
        let (i, j) = (u.floor() as i32, v.floor() as i32);
        let (fu, fv) = (u - i as f64, v - j as f64);
        let (mut w, mut precision, mut weighted_z) = (0.0, 0.0, 0.0);
        for (di, dj, wk) in [
            (0, 0, (1.0 - fu) * (1.0 - fv)),
            (1, 0, fu * (1.0 - fv)),
            (0, 1, (1.0 - fu) * fv),
            (1, 1, fu * fv),
        ] {
            if let Some((zk, vk)) = self.at(i + di, j + dj) {
                let pk = wk / vk as f64;
                w += wk;
                precision += pk;
                weighted_z += pk * zk as f64;
            }
        }
        (w >= 0.5 && precision > 0.0).then(|| (weighted_z / precision, w / precision))
    }

    /// The raster this scan fuses at `pose` instead (see the module's description).
    pub fn moved(&self, pose: Isometry3<f64>, cell_m: f64) -> Self {
        let delta = pose * self.pose.inverse();
        let inverse = delta.inverse();
        let cells: Vec<FusedCell> = self.cells().collect();
        let n = cells.len().max(1) as f64;
        let mean_z = cells.iter().map(|c| c.1 as f64).sum::<f64>() / n;
        // The old box's corners, carried by the correction: the new box.
        let corner = |i: i32, j: i32| delta * Point3::new(i as f64 * cell_m, j as f64 * cell_m, mean_z);
        let (i1, j1) = (self.origin.0 + self.cols as i32, self.origin.1 + self.rows as i32);
        let corners = [
            corner(self.origin.0, self.origin.1),
            corner(i1, self.origin.1),
            corner(self.origin.0, j1),
            corner(i1, j1),
        ];
        let span = |f: fn(&Point3<f64>) -> f64| {
            let lo = corners.iter().map(f).fold(f64::INFINITY, f64::min);
            let hi = corners.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
            ((lo / cell_m).floor() as i32 - 1, (hi / cell_m).ceil() as i32 + 1)
        };
        let ((ilo, ihi), (jlo, jhi)) = (span(|p| p.x), span(|p| p.y));
        // A correction about the vertical only (the common case: a loop closure's x, y, z and
        // yaw) carries a point's height by its z shift alone: no fixed point to find.
        let level = (delta.rotation * Vector3::z()).z > 1.0 - 1e-12;
        let mut moved = Vec::new();
        if !cells.is_empty() {
            for i in ilo..=ihi {
                for j in jlo..=jhi {
                    let target = Vector3::new((i as f64 + 0.5) * cell_m, (j as f64 + 0.5) * cell_m, 0.0);
                    let carried = if level {
                        let p = inverse * Point3::new(target.x, target.y, 0.0);
                        self.interpolate(p.x, p.y, cell_m)
                            .map(|(z, var)| (z + delta.translation.z, var))
                    } else {
                        self.carried(&delta, &inverse, target, mean_z, cell_m)
                    };
                    if let Some((z, var)) = carried {
                        moved.push(((i, j), z as f32, var as f32));
                    }
                }
            }
        }
        let mut raster = Self::new((self.publisher_id, self.sequence, self.stamp_ns), pose, &moved);
        raster.insert = self.insert;
        raster
    }

    /// The old surface's point that `delta` carries above `target` (x, y): its new height and
    /// its variance.
    fn carried(
        &self,
        delta: &Isometry3<f64>,
        inverse: &Isometry3<f64>,
        target: Vector3<f64>,
        mean_z: f64,
        cell_m: f64,
    ) -> Option<(f64, f64)> {
        let mut p = inverse * Point3::new(target.x, target.y, mean_z);
        for _ in 0..4 {
            let (z, var) = self.interpolate(p.x, p.y, cell_m)?;
            p.z = z;
            let q = delta * p;
            let off = Vector3::new(target.x - q.x, target.y - q.y, 0.0);
            if off.norm() < 1e-6 {
                return Some((q.z, var));
            }
            p += inverse.rotation * off;
        }
        let (z, var) = self.interpolate(p.x, p.y, cell_m)?;
        p.z = z;
        Some(((delta * p).z, var))
    }
}

/// A change to one cell's fused evidence: precision (1/σ²) and precision-weighted height added
/// (negative when a scan is taken out), and scans added.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CellEdit {
    /// Precision added, 1/m².
    pub precision: f64,
    /// Precision × height added, 1/m.
    pub weighted_z: f64,
    /// Scans added.
    pub scans: i64,
}

/// Left of a cell's precision after a subtraction, relative to what was taken out, below which
/// nothing is left (rounding of an exact cancellation).
const CANCELLED: f64 = 1e-9;

impl CellEdit {
    /// Adds (`sign` = 1) or takes out (−1) one scan's height `z` of variance `var`.
    pub fn add(&mut self, z: f64, var: f64, sign: f64) {
        self.precision += sign / var;
        self.weighted_z += sign * z / var;
        self.scans += sign as i64;
    }

    /// `cell` (absent: none yet) after the edit; `None` when no evidence is left.
    pub fn apply(&self, cell: Option<Cell>) -> Option<Cell> {
        let (p0, pz0, n0) = cell.map_or((0.0, 0.0, 0), |c| (1.0 / c.var, c.z / c.var, c.scans as i64));
        let (p, n) = (p0 + self.precision, n0 + self.scans);
        if n <= 0 || p <= CANCELLED * p0.max(self.precision.abs()) {
            return None;
        }
        Some(Cell {
            z: (pz0 + self.weighted_z) / p,
            var: 1.0 / p,
            scans: n as u32,
        })
    }
}

/// Whether a scan fused at the given count no longer holds evidence in a cell (it was replaced
/// by a change since).
pub type Stale<'a> = &'a (dyn Fn((i32, i32), u64) -> bool + Sync);

/// The cells that moving `rasters` from their poses to the new ones changes (only those whose
/// evidence changes; cells `stale` for a scan are left alone: its evidence is not in them).
pub fn edits_of_moves(moves: &[(&ScanRaster, &ScanRaster)], stale: Stale) -> HashMap<(i32, i32), CellEdit> {
    use rayon::prelude::*;
    moves
        .par_iter()
        .fold(EditBlocks::default, |mut blocks, (old, new)| {
            blocks.add(old, -1.0, stale);
            blocks.add(new, 1.0, stale);
            blocks
        })
        .reduce(EditBlocks::default, EditBlocks::merge)
        .into_edits()
}

/// A block's index and its cells' edits, row-major.
type Block = ((i32, i32), Box<[CellEdit]>);

/// Edits to cells, each with its cell's index.
pub type CellEdits = Vec<((i32, i32), CellEdit)>;

/// Side of an [`EditBlocks`] block, cells.
const BLOCK: i32 = 16;

/// Cell edits accumulated in dense 16 × 16 blocks: a raster's row touches a new block every 16
/// cells, so a few lookups serve thousands of cells (a hash per cell cost half a second over a
/// 500 m trajectory's 23 million).
#[derive(Debug, Default)]
struct EditBlocks {
    index: HashMap<(i32, i32), usize>,
    blocks: Vec<Block>,
}

impl EditBlocks {
    fn block(&mut self, key: (i32, i32)) -> usize {
        let next = self.blocks.len();
        let k = *self.index.entry(key).or_insert(next);
        if k == next {
            let empty = vec![CellEdit::default(); (BLOCK * BLOCK) as usize].into_boxed_slice();
            self.blocks.push((key, empty));
        }
        k
    }

    fn add(&mut self, raster: &ScanRaster, sign: f64, stale: Stale) {
        let mut last: Option<((i32, i32), usize)> = None;
        for ((i, j), z, var) in raster.cells() {
            if stale((i, j), raster.insert) {
                continue;
            }
            let key = (i.div_euclid(BLOCK), j.div_euclid(BLOCK));
            let k = match last {
                Some((at, k)) if at == key => k,
                _ => {
                    let k = self.block(key);
                    last = Some((key, k));
                    k
                }
            };
            let slot = (j.rem_euclid(BLOCK) * BLOCK + i.rem_euclid(BLOCK)) as usize;
            self.blocks[k].1[slot].add(z as f64, var as f64, sign);
        }
    }

    fn merge(mut self, other: Self) -> Self {
        for (key, block) in other.blocks {
            let k = self.block(key);
            for (a, b) in self.blocks[k].1.iter_mut().zip(block.iter()) {
                a.precision += b.precision;
                a.weighted_z += b.weighted_z;
                a.scans += b.scans;
            }
        }
        self
    }

    fn into_edits(self) -> HashMap<(i32, i32), CellEdit> {
        let mut edits = HashMap::new();
        for ((bi, bj), block) in self.blocks {
            for (slot, e) in block.iter().enumerate() {
                if *e != CellEdit::default() {
                    let (a, b) = (slot as i32 % BLOCK, slot as i32 / BLOCK);
                    edits.insert((bi * BLOCK + a, bj * BLOCK + b), *e);
                }
            }
        }
        edits
    }
}

/// The rasters of the scans fused lately, newest last, within a memory budget.
#[derive(Debug, Clone, Default)]
pub struct Ledger {
    scans: VecDeque<ScanRaster>,
    bytes: usize,
    budget_bytes: usize,
    forgotten: u64,
}

impl Ledger {
    /// An empty ledger that keeps at most `budget_bytes` (the oldest scans leave first).
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            budget_bytes,
            ..Self::default()
        }
    }

    /// Records a fused scan, forgetting the oldest beyond the budget.
    pub fn push(&mut self, raster: ScanRaster) {
        self.bytes += raster.bytes();
        self.scans.push_back(raster);
        while self.bytes > self.budget_bytes {
            let Some(old) = self.scans.pop_front() else { break };
            self.bytes -= old.bytes();
            self.forgotten += 1;
        }
    }

    /// Scans kept.
    pub fn len(&self) -> usize {
        self.scans.len()
    }

    /// True when no scan is kept.
    pub fn is_empty(&self) -> bool {
        self.scans.is_empty()
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Scans forgotten for the budget.
    pub fn forgotten(&self) -> u64 {
        self.forgotten
    }

    /// The (publisher, sequence) of every kept scan.
    pub fn ids(&self) -> std::collections::HashSet<(u64, u64)> {
        self.scans.iter().map(|r| (r.publisher_id, r.sequence)).collect()
    }

    /// Where every kept scan `new_pose` gives a pose for moves, and the edits to the cells
    /// that makes; nothing changes until [`Self::commit`].
    pub fn plan(
        &self,
        new_pose: impl Fn(&ScanRaster) -> Option<Isometry3<f64>> + Sync,
        cell_m: f64,
        stale: Stale,
    ) -> Moves {
        use rayon::prelude::*;
        let moved: Vec<(usize, ScanRaster)> = self
            .scans
            .par_iter()
            .enumerate()
            .filter_map(|(k, r)| new_pose(r).map(|p| (k, r.moved(p, cell_m))))
            .collect();
        let pairs: Vec<(&ScanRaster, &ScanRaster)> =
            moved.iter().map(|(k, new)| (&self.scans[*k], new)).collect();
        Moves {
            edits: edits_of_moves(&pairs, stale),
            moved,
        }
    }

    /// Keeps the moved scans' new rasters (once their edits are applied).
    pub fn commit(&mut self, moved: Vec<(usize, ScanRaster)>) {
        for (k, new) in moved {
            if let Some(old) = self.scans.get_mut(k) {
                self.bytes = self.bytes - old.bytes() + new.bytes();
                *old = new;
            }
        }
    }
}

/// A planned correction of the ledger's scans.
#[derive(Debug, Clone)]
pub struct Moves {
    /// Ledger positions with their moved rasters.
    pub moved: Vec<(usize, ScanRaster)>,
    /// What moving them does to the cells.
    pub edits: HashMap<(i32, i32), CellEdit>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    const CELL: f64 = 0.25;

    /// A raster of the plane z = 0.1 x + 0.05 y + 0.3 over the cells of a 4 m square, but for a
    /// hole of one cell (around it three corners are averaged: not exact).
    fn plane_raster(pose: Isometry3<f64>) -> ScanRaster {
        let cells: Vec<FusedCell> = (-8..8)
            .flat_map(|i| (-8..8).map(move |j| (i, j)))
            .filter(|&c| c != (2, 2))
            .map(|(i, j)| {
                let (x, y) = ((i as f64 + 0.5) * CELL, (j as f64 + 0.5) * CELL);
                ((i, j), (0.1 * x + 0.05 * y + 0.3) as f32, 1e-4)
            })
            .collect();
        ScanRaster::new((1, 1, 0), pose, &cells)
    }

    #[test]
    fn a_moved_raster_is_the_surface_carried_by_the_correction() {
        let raster = plane_raster(Isometry3::identity());
        let delta = Isometry3::from_parts(
            Translation3::new(0.4, -0.3, 0.2),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.3),
        );
        let moved = raster.moved(delta, CELL);
        assert_eq!(moved.pose, delta);
        let mut n = 0;
        for ((i, j), z, var) in moved.cells() {
            let c = Point3::new((i as f64 + 0.5) * CELL, (j as f64 + 0.5) * CELL, 0.0);
            // The carried plane: points p of the old plane map to delta · p; check c is on it.
            let p = delta.inverse() * Point3::new(c.x, c.y, z as f64);
            let on_plane = 0.1 * p.x + 0.05 * p.y + 0.3;
            // Between four old centres (all of one variance) the plane is carried exactly; past
            // the outer centres the present ones are averaged (at most half a cell's slope off).
            let hole = (p.x - 0.625).abs() < 0.25 && (p.y - 0.625).abs() < 0.25;
            let inside = p.x.abs() < 1.875 && p.y.abs() < 1.875 && !hole;
            let tolerance = if inside { 1e-5 } else { 0.5 * 0.25 * 0.1 };
            assert!(
                (p.z - on_plane).abs() < tolerance,
                "cell ({i}, {j}) off by {}",
                p.z - on_plane
            );
            assert!((var - 1e-4).abs() < 1e-9);
            n += 1;
        }
        // The square turned by 17°: most of its cells have a place in the new grid.
        assert!(n > 200, "{n} cells");
        // Moving back undoes it (within the interpolation of a plane: exact).
        let back = moved.moved(Isometry3::identity(), CELL);
        let again: HashMap<(i32, i32), f32> = back.cells().map(|(c, z, _)| (c, z)).collect();
        let inner = raster
            .cells()
            .filter(|((i, j), _, _)| i.abs() < 6 && j.abs() < 6 && ((i - 2).abs() > 1 || (j - 2).abs() > 1))
            .inspect(|(c, z, _)| {
                let z2 = again.get(c).expect("inner cells survive the round trip");
                assert!((z - z2).abs() < 1e-5);
            })
            .count();
        assert_eq!(inner, 112);
    }

    #[test]
    fn taking_out_what_went_in_leaves_the_rest() {
        let mut e = CellEdit::default();
        e.add(1.0, 0.01, 1.0);
        e.add(2.0, 0.04, 1.0);
        let cell = e.apply(None).expect("fused");
        assert_eq!(cell.scans, 2);
        assert!((cell.z - (1.0 / 0.01 + 2.0 / 0.04) / (1.0 / 0.01 + 1.0 / 0.04)).abs() < 1e-12);
        let mut out = CellEdit::default();
        out.add(2.0, 0.04, -1.0);
        let left = out.apply(Some(cell)).expect("one left");
        assert!((left.z - 1.0).abs() < 1e-12 && (left.var - 0.01).abs() < 1e-12 && left.scans == 1);
        let mut all = CellEdit::default();
        all.add(1.0, 0.01, -1.0);
        assert_eq!(all.apply(Some(left)), None);
    }

    #[test]
    fn the_ledger_keeps_to_its_budget_and_moves_only_the_scans_named() {
        let one = plane_raster(Isometry3::identity());
        let mut ledger = Ledger::new(3 * one.bytes());
        for s in 0..5 {
            let mut r = one.clone();
            r.sequence = s;
            ledger.push(r);
        }
        assert_eq!((ledger.len(), ledger.forgotten()), (3, 2));
        let ids = ledger.ids();
        assert!(!ids.contains(&(1, 1)) && ids.contains(&(1, 4)));
        let shift = Isometry3::translation(1.0, 0.0, 0.0);
        let plan = ledger.plan(|r| (r.sequence == 3).then_some(shift), CELL, &|_, _| false);
        assert_eq!(plan.moved.len(), 1);
        // The cells it left lose a scan, the ones it reached gain one.
        assert_eq!(plan.edits.get(&(-8, 0)).map(|e| e.scans), Some(-1));
        assert_eq!(plan.edits.get(&(11, 0)).map(|e| e.scans), Some(1));
        let bytes = ledger.bytes();
        ledger.commit(plan.moved);
        assert_eq!(ledger.bytes(), bytes);
        let again = ledger.plan(|r| (r.sequence == 3).then_some(shift), CELL, &|_, _| false);
        assert!(again.edits.values().all(|e| e.scans == 0), "already there");
    }
}
