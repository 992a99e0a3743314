//! How each cell was seen: how far from it the scans that fused it stood, and how squarely
//! their rays met it, each fused by inverse variance as the heights are. The aggregate's σ
//! factors are learnt and looked up by both (`query::raw_aggregate_elevation`): a cell seen from
//! 3 m errs unlike one seen only from 15 m, wherever the robot stands now, and one every view saw
//! at the edge of a shadow unlike one seen squarely (docs/EVALUATION.md "Calibration", steps 22
//! and 23).

use super::{fused, Cell, WorldAggregate};

/// The grazing a view's squareness is capped at before fusing: flat ground's, the centre of the
/// widest grazing class (an unmeasured, infinite grazing counts as this too).
pub const SQUARE: f64 = 1.0;

/// One cell's record as checkpointed and paged: its index, and the fusing sensors' distance
/// (metres) and their rays' grazing.
pub type SeenRecord = ((i32, i32), [f32; 2]);

/// Whether a checkpointed or paged record's (distance, grazing) could have been fused: a
/// finite distance not below 0, a grazing in [0, [`SQUARE`]].
pub fn record_in_domain([distance_m, grazing]: [f32; 2]) -> bool {
    distance_m.is_finite() && distance_m >= 0.0 && (0.0..=SQUARE as f32).contains(&grazing)
}

/// How one cell was seen ([`WorldAggregate::seen_at`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct SeenFrom {
    /// The fusing sensors' horizontal distance, metres.
    distance_m: f32,
    /// The views' grazing ([`HeightEstimate::grazing`](crate::map::local::HeightEstimate::grazing)),
    /// each capped at [`SQUARE`].
    grazing: f32,
}

/// How the fusing scans saw map (x, y) ([`WorldAggregate::seen_at`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seen {
    /// Horizontal distance from the fusing sensors, metres.
    pub distance_m: f64,
    /// Grazing of their rays there, at most [`SQUARE`].
    pub grazing: f64,
}

impl WorldAggregate {
    /// Folds a view from `distance_m` at `grazing` into how cell `c` was seen, by [`fused`], as
    /// its height: `before` is the cell before the view (`None`: a new cell). A cell that holds
    /// evidence of unknown views (from a format-5 checkpoint or format-3 page, corrected or replaced
    /// since) starts again from this view.
    pub(super) fn fold_seen_from(
        &mut self,
        c: (i32, i32),
        before: Option<Cell>,
        view: Cell,
        distance_m: f64,
        grazing: f64,
    ) {
        // `min` takes the number over a NaN: an unmeasured grazing counts as square too.
        let grazing = grazing.min(SQUARE);
        let seen = match (before, self.seen_from.get(&c)) {
            (Some(cell), Some(s)) => {
                let fold = |known: f32, new: f64| {
                    let known = Cell {
                        z: f64::from(known),
                        ..cell
                    };
                    fused(known, Cell { z: new, ..view }).z
                };
                (fold(s.distance_m, distance_m), fold(s.grazing, grazing))
            }
            _ => (distance_m, grazing),
        };
        if seen.0.is_finite() && seen.1.is_finite() {
            self.seen_from.insert(
                c,
                SeenFrom {
                    distance_m: seen.0 as f32,
                    grazing: seen.1 as f32,
                },
            );
        } else {
            self.seen_from.remove(&c);
        }
    }

    /// Every cell's record as checkpointed ([`WorldState::seen`](super::WorldState::seen)):
    /// (distance, grazing), sorted by index.
    pub(super) fn seen_records(&self) -> Vec<SeenRecord> {
        let mut records: Vec<_> = self
            .seen_from
            .iter()
            .map(|(&c, s)| (c, [s.distance_m, s.grazing]))
            .collect();
        records.sort_by_key(|&(c, _)| c);
        records
    }

    /// Removes the records of `cells` and returns them as [`Self::seen_records`] does, in
    /// `cells`' order (a tile's page takes its cells' records to disk).
    pub(super) fn take_seen(&mut self, cells: impl Iterator<Item = (i32, i32)>) -> Vec<SeenRecord> {
        cells
            .filter_map(|c| {
                let s = self.seen_from.remove(&c)?;
                Some((c, [s.distance_m, s.grazing]))
            })
            .collect()
    }

    /// Takes checkpointed or paged records back, for cells the aggregate holds; a record out of
    /// its domain ([`record_in_domain`]; a checkpoint with one is refused before this, a page's
    /// is dropped here) leaves its cell answering as one without a record.
    pub(super) fn restore_seen_from(&mut self, records: &[SeenRecord]) {
        for &(c, [distance_m, grazing]) in records {
            if record_in_domain([distance_m, grazing]) && self.cells.contains_key(&c) {
                self.seen_from.insert(c, SeenFrom { distance_m, grazing });
            }
        }
    }

    /// How the fusing scans saw map (x, y): bilinear between the neighbouring cells' centres, a
    /// cell without a record counting as seen squarely from `fallback_m` (so the answer is
    /// continuous in (x, y) wherever cells gain or lack one).
    pub fn seen_at(&self, x: f64, y: f64, fallback_m: f64) -> Seen {
        let u = x / self.params.cell_m - 0.5;
        let v = y / self.params.cell_m - 0.5;
        let (i0, j0) = (u.floor() as i32, v.floor() as i32);
        let (fu, fv) = (u - u.floor(), v - v.floor());
        let mut seen = Seen {
            distance_m: 0.0,
            grazing: 0.0,
        };
        for (di, wu) in [(0, 1.0 - fu), (1, fu)] {
            for (dj, wv) in [(0, 1.0 - fv), (1, fv)] {
                let w = wu * wv;
                if w > 0.0 {
                    let s = self.seen_from.get(&(i0 + di, j0 + dj));
                    seen.distance_m += w * s.map_or(fallback_m, |s| f64::from(s.distance_m));
                    seen.grazing += w * s.map_or(SQUARE, |s| f64::from(s.grazing));
                }
            }
        }
        seen
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::fold;
    use super::super::{WorldAggregate, WorldParams};
    use super::SQUARE;
    use rangegp_sim::Heightmap;

    #[test]
    fn a_cell_is_seen_from_its_views_distances_fused_as_its_height() {
        let terrain = Heightmap::flat(60.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        let c = agg.cell_of(3.0, 0.3);
        let (x, y) = agg.centre(c);
        let (d1, d2) = (x.hypot(y), (x + 4.0).hypot(y));
        fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
        let v1 = agg.cells()[&c].var;
        assert!((agg.seen_at(x, y, f64::NAN).distance_m - d1).abs() < 1e-5);
        // A second view from 4 m farther back: the distances weigh as the heights did.
        fold(&mut agg, &terrain, -4.0, 0.0, 0.0);
        let vf = agg.cells()[&c].var;
        let v2 = 1.0 / (1.0 / vf - 1.0 / v1);
        let want = vf * (d1 / v1 + d2 / v2);
        let got = agg.seen_at(x, y, f64::NAN).distance_m;
        assert!(d1 < got && got < d2, "{got} outside ({d1}, {d2})");
        assert!((got - want).abs() < 1e-4, "{got} against {want}");
        // Where no cell is fused, the caller's distance, seen squarely; between, a blend that
        // never jumps.
        let far = agg.seen_at(500.0, 500.0, 7.5);
        assert_eq!((far.distance_m, far.grazing), (7.5, SQUARE));
        // (The fused cells begin about x = −1 m, 3 m ahead of the second view.)
        let at = |x: f64| agg.seen_at(x, 0.3, 50.0).distance_m;
        let step = |x: f64| (at(x + 1e-6) - at(x)).abs();
        assert!((0..200).all(|k| step(-2.0 + 0.01 * f64::from(k)) < 1e-3));
        assert!(at(-2.0) > 49.0 && at(0.0) < 5.0);
    }

    #[test]
    fn a_correction_forgets_how_the_cells_it_edits_were_seen_and_no_others() {
        use crate::map::aggregate::ledger::CellEdit;
        let terrain = Heightmap::flat(60.0, 0.05, 0.0);
        let mut agg = WorldAggregate::new(WorldParams::default());
        fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
        let edited = agg.cell_of(3.0, 0.3);
        let kept = (edited.0 + 1, edited.1);
        assert_eq!(agg.tile_of(edited), agg.tile_of(kept), "the premise: one tile");
        // At a cell's centre the record is that cell's alone (the fallback where it has none).
        let seen = |agg: &WorldAggregate, c: (i32, i32)| {
            let (x, y) = agg.centre(c);
            agg.seen_at(x, y, 99.0).distance_m
        };
        let before = seen(&agg, kept);
        assert!(
            before < 5.0 && seen(&agg, edited) < 5.0,
            "the premise: both were seen"
        );
        let lift = CellEdit {
            precision: 1e4,
            weighted_z: 1e3,
            scans: 1,
        };
        let edits = std::collections::HashMap::from([(edited, lift)]);
        agg.apply_edits(edits, &|_| false).expect("refit");
        assert_eq!(seen(&agg, edited), 99.0);
        assert_eq!(seen(&agg, kept), before);
    }

    #[test]
    fn a_cell_seen_only_at_a_shadows_edge_keeps_its_views_grazing() {
        let mut agg = WorldAggregate::new(WorldParams::default());
        let c = (40, 3);
        let view = |var: f64| super::super::Cell {
            z: 0.0,
            var,
            scans: 1,
        };
        agg.fold_seen_from(c, None, view(1e-4), 5.0, 0.3);
        let (x, y) = agg.centre(c);
        assert!((agg.seen_at(x, y, 0.0).grazing - 0.3).abs() < 1e-6);
        // A square view four times surer weighs four times as much; an unmeasured one counts as
        // square.
        agg.fold_seen_from(c, Some(view(1e-4)), view(2.5e-5), 5.0, f64::INFINITY);
        let got = agg.seen_at(x, y, 0.0).grazing;
        assert!((got - (0.3 + 4.0 * SQUARE) / 5.0).abs() < 1e-6, "{got}");
        agg.fold_seen_from((41, 3), None, view(1e-4), 5.0, f64::NAN);
        let (x, y) = agg.centre((41, 3));
        assert_eq!(agg.seen_at(x, y, 0.0).grazing, SQUARE);
    }
}
