//! The project's aggregate: a world-frame grid of cells, each holding the height of the ground
//! at its centre as predicted by the scans' range GPs (root-finding down the vertical line,
//! delta-method variance), fused across scans by inverse variance — the per-cell elevation
//! filter (seed 001 keeps the highest point per cell, a filter against vegetation that this
//! terrain does not have; a variance-weighted mean also shrinks the noise). Cells are grouped
//! into square tiles; each tile is an exact elevation GP (Matérn + the cells' fused variances as
//! known heteroscedastic noise, seed 003's two-stage idea) on the cells of the tile grown by a
//! margin, so a tile holds a bounded number of points. A new scan refits only the tiles whose
//! cells it changed. Predictions blend the covering tiles with a partition of unity (no seams).

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
use std::collections::{BTreeSet, HashMap, VecDeque};
use std::sync::Arc;

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
        }
    }
}

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
            .map(|pages| pages.len())
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
    ) -> Result<Vec<TilePage>, AggregateError> {
        let Some((_, newest)) = batch.last() else {
            return Ok(Vec::new());
        };
        let s = newest.sensor_position();
        let connected = self.tiles.is_empty()
            || self
                .tiles
                .keys()
                .any(|&t| self.tile_distance(t, s.x, s.y) <= radius_m);
        self.insert_all_within(batch, reach_m)?;
        Ok(if connected {
            self.evict_beyond(s.x, s.y, radius_m)
        } else {
            Vec::new()
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
    ) -> Result<(), AggregateError> {
        let mut dirty = BTreeSet::new();
        let insert = self.history.back().map_or(0, |r| r.insert + 1);
        let reach_m = reach_m.min(self.params.max_reach_m);
        for (scan, local) in batch {
            for (c, e) in self.predicted_cells(local, reach_m) {
                let cell = self.cells.entry(c).or_insert(Cell {
                    z: e.z,
                    var: e.var,
                    scans: 0,
                });
                if cell.scans > 0 {
                    let var = 1.0 / (1.0 / cell.var + 1.0 / e.var);
                    cell.z = var * (cell.z / cell.var + e.z / e.var);
                    cell.var = var;
                }
                cell.scans += 1;
                dirty.extend(self.tiles_covering(c));
            }
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
        self.refit(dirty)
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
                local
                    .elevation(x, y)
                    .filter(|e| e.var <= max_var && e.var > 0.0)
                    .map(|e| (c, e))
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
        self.cells.retain(|&(i, j), cell| {
            let tile = (i.div_euclid(n), j.div_euclid(n));
            match pages.get_mut(&tile) {
                Some(page) => {
                    page.cells.push(((i, j), *cell));
                    false
                }
                None => true,
            }
        });
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

    fn centre(&self, (i, j): (i32, i32)) -> (f64, f64) {
        (
            (i as f64 + 0.5) * self.params.cell_m,
            (j as f64 + 0.5) * self.params.cell_m,
        )
    }

    fn cell_of(&self, x: f64, y: f64) -> (i32, i32) {
        (
            (x / self.params.cell_m).floor() as i32,
            (y / self.params.cell_m).floor() as i32,
        )
    }

    fn tile_of(&self, (i, j): (i32, i32)) -> (i32, i32) {
        (
            i.div_euclid(self.params.tile_cells),
            j.div_euclid(self.params.tile_cells),
        )
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
        let reach = (self.params.max_gap_m / self.params.cell_m).ceil() as i32;
        let mut nearest = f64::INFINITY;
        for di in -reach..=reach {
            for dj in -reach..=reach {
                let key = (ci + di, cj + dj);
                if self.cells.contains_key(&key) {
                    let (cx, cy) = self.centre(key);
                    nearest = nearest.min((cx - x).hypot(cy - y));
                }
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
    /// fused cell against the experts' length scale (`None` where nothing is answered).
    pub fn provenance(&self, x: f64, y: f64) -> Provenance {
        self.graded(x, y).map_or(Provenance::None, |(_, p)| p)
    }

    /// The height at (x, y) with its provenance: the tiles blended with a partition of unity,
    /// where a fused cell lies within `max_gap_m`.
    fn graded(&self, x: f64, y: f64) -> Option<(HeightEstimate, Provenance)> {
        let datum_m = self.nearest_cell(x, y)?;
        let (ti, tj) = self.tile_of(self.cell_of(x, y));
        let (mut wsum, mut m1, mut m2) = (0.0, 0.0, 0.0);
        for di in -1..=1 {
            for dj in -1..=1 {
                let t = (ti + di, tj + dj);
                let Some(gp) = self.tiles.get(&t) else { continue };
                let w = self.weight(t, x, y);
                if w > 0.0 {
                    let (m, v) = gp.predict(x, y);
                    wsum += w;
                    m1 += w * m;
                    m2 += w * (v + m * m);
                }
            }
        }
        (wsum > 0.0).then(|| {
            let z = m1 / wsum;
            let var = (m2 / wsum - z * z).max(0.0);
            let estimate = HeightEstimate {
                z,
                var,
                grazing: f64::INFINITY,
                point_sd: [0.0, 0.0, var.sqrt()],
            };
            (estimate, provenance_of(datum_m, self.params.length_scale))
        })
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
    }

    fn elevation(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        self.graded(x, y).map(|(e, _)| e)
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
}
