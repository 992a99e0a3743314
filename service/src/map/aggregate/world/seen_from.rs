//! How far from each cell the scans that fused it stood: the sensors' horizontal distances,
//! fused by inverse variance as the heights are. The aggregate's σ factors are learnt and looked
//! up by it (`query::raw_aggregate_elevation`): a cell seen from 3 m errs unlike one seen only
//! from 15 m, wherever the robot stands now (docs/EVALUATION.md "Calibration", step 22).

use super::{fused, Cell, WorldAggregate};

impl WorldAggregate {
    /// Folds a `view` from `distance_m` into cell `c`'s distance by [`fused`], as its height:
    /// `before` is the cell before the view (`None`: a new cell). A cell that holds evidence of
    /// unknown views (restored, paged in, corrected or replaced since) starts again from this
    /// view.
    pub(super) fn fold_seen_from(
        &mut self,
        c: (i32, i32),
        before: Option<Cell>,
        view: Cell,
        distance_m: f64,
    ) {
        let distance = match (before, self.seen_from.get(&c)) {
            (Some(cell), Some(&mean)) => {
                let known = Cell {
                    z: f64::from(mean),
                    ..cell
                };
                fused(
                    known,
                    Cell {
                        z: distance_m,
                        ..view
                    },
                )
                .z
            }
            _ => distance_m,
        };
        if distance.is_finite() {
            self.seen_from.insert(c, distance as f32);
        } else {
            self.seen_from.remove(&c);
        }
    }

    /// The fusing sensors' distance at map (x, y), metres: bilinear between the neighbouring
    /// cells' centres, a cell without one counting as `fallback_m` (so the answer is continuous
    /// in (x, y) wherever cells gain or lack it).
    pub fn seen_from_m(&self, x: f64, y: f64, fallback_m: f64) -> f64 {
        let u = x / self.params.cell_m - 0.5;
        let v = y / self.params.cell_m - 0.5;
        let (i0, j0) = (u.floor() as i32, v.floor() as i32);
        let (fu, fv) = (u - u.floor(), v - v.floor());
        let mut sum = 0.0;
        for (di, wu) in [(0, 1.0 - fu), (1, fu)] {
            for (dj, wv) in [(0, 1.0 - fv), (1, fv)] {
                let w = wu * wv;
                if w > 0.0 {
                    let d = self.seen_from.get(&(i0 + di, j0 + dj)).copied();
                    sum += w * d.map_or(fallback_m, f64::from);
                }
            }
        }
        sum
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::fold;
    use super::super::{WorldAggregate, WorldParams};
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
        assert!((agg.seen_from_m(x, y, f64::NAN) - d1).abs() < 1e-5);
        // A second view from 4 m farther back: the distances weigh as the heights did.
        fold(&mut agg, &terrain, -4.0, 0.0, 0.0);
        let vf = agg.cells()[&c].var;
        let v2 = 1.0 / (1.0 / vf - 1.0 / v1);
        let want = vf * (d1 / v1 + d2 / v2);
        let got = agg.seen_from_m(x, y, f64::NAN);
        assert!(d1 < got && got < d2, "{got} outside ({d1}, {d2})");
        assert!((got - want).abs() < 1e-4, "{got} against {want}");
        // Where no cell is fused, the caller's distance; between, a blend that never jumps.
        assert_eq!(agg.seen_from_m(500.0, 500.0, 7.5), 7.5);
        // (The fused cells begin about x = −1 m, 3 m ahead of the second view.)
        let step = |x: f64| (agg.seen_from_m(x + 1e-6, 0.3, 50.0) - agg.seen_from_m(x, 0.3, 50.0)).abs();
        assert!((0..200).all(|k| step(-2.0 + 0.01 * f64::from(k)) < 1e-3));
        assert!(agg.seen_from_m(-2.0, 0.3, 50.0) > 49.0 && agg.seen_from_m(0.0, 0.3, 50.0) < 5.0);
    }
}
