//! Tiles leaving memory and coming back (the site map's pages), tiles replaced from a site map,
//! and a pose correction's cell edits.

use super::{fit_tile, tile_of, Applied, Cell, TileCells, TilePage, WorldAggregate};
use crate::gp::Kernel;
use crate::map::aggregate::ledger::CellEdit;
use crate::map::aggregate::AggregateError;
use crate::map::elevation_gp::ElevationGp;
use rayon::prelude::*;
use std::collections::hash_map::Entry;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

impl WorldAggregate {
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
        if !edits.is_empty() {
            self.views.clear();
        }
        let mut dirty = BTreeSet::new();
        let mut applied = Applied::default();
        let mut edited_tiles = BTreeSet::new();
        let on_disk = |agg: &Self, t: (i32, i32)| !agg.tiles.contains_key(&t) && paged(t);
        for (c, edit) in edits {
            if edit == CellEdit::default() {
                continue;
            }
            applied.cells_changed += 1;
            // How the cell was seen moved with the scans whose evidence moved; a cell no edit
            // names keeps its views, and its record.
            self.seen_from.remove(&c);
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
                    seen: Vec::new(),
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
            page.seen = self.take_seen(page.cells.iter().map(|&(c, _)| c));
        }
        pages.sort_by_key(|p| p.key);
        pages
    }

    /// Whether tile `key` is held in memory.
    pub fn has_tile(&self, key: (i32, i32)) -> bool {
        self.tiles.contains_key(&key)
    }

    /// Brings paged-out tiles back: each page's cells (where no cell is held now) with how they
    /// were seen, and its expert, refitted from the page's own points, so a tile that left and
    /// came back with no new scan in between answers exactly as before. A page whose tile is
    /// held is skipped.
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
            let mut taken = BTreeSet::new();
            for &(c, cell) in &page.cells {
                if let Entry::Vacant(e) = self.cells.entry(c) {
                    e.insert(cell);
                    taken.insert(c);
                }
            }
            let seen: Vec<_> = page
                .seen
                .iter()
                .filter(|(c, _)| taken.contains(c))
                .copied()
                .collect();
            self.restore_seen_from(&seen);
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
                self.seen_from.remove(&c);
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
}
