//! What the aggregate answers: heights blended over the tile experts, rays cast over them, and
//! how much data stands behind an answer.

use super::WorldAggregate;
use crate::map::elevation_gp::ElevationGp;
use crate::map::local::{provenance_of, HeightEstimate, RayEstimate};
use crate::map::root;
use nalgebra::Vector3;
use rangegp_proto::msg::Provenance;

impl WorldAggregate {
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
    pub(super) fn nearest_cell(&self, x: f64, y: f64) -> Option<f64> {
        self.nearest_cell_within(x, y, self.params.max_gap_m)
    }

    /// Distance from map (x, y) to the nearest fused cell's centre, if one lies within
    /// `reach_m`.
    fn nearest_cell_within(&self, x: f64, y: f64, reach_m: f64) -> Option<f64> {
        let (ci, cj) = self.cell_of(x, y);
        let cell = self.params.cell_m;
        let reach = (reach_m / cell).ceil() as i32;
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
        (nearest <= reach_m).then_some(nearest)
    }

    /// Casts a map-frame ray (unit `dir`) over the aggregate's surface up to `max_range`: the
    /// first crossing of the ray below the fused heights (sampled every half cell, then
    /// refined), its variance by the delta method through the height's, and the probability of
    /// a hit before `max_range`. Only ground within a correlation length of fused cells counts
    /// (observed or interpolated), farther than a height is answered
    /// ([`WorldParams::max_gap_m`](super::WorldParams::max_gap_m)): a ray crossing a gap of a cell or two between known ground must still meet the surface
    /// beyond it. `None` when the aggregate knows the ground nowhere along the
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
        let reach = self.params.length_scale;
        let known = |x: f64, y: f64| self.within(x, y, reach).map(|(e, _)| e);
        let gap = |t: f64| {
            let p = point(t);
            known(p.x, p.y).map(|e| e.z - p.z)
        };
        let samples = ((max_range / (0.5 * self.params.cell_m)).ceil() as usize).clamp(8, 4000);
        if let Some(root) = root::first_crossing(gap, 0.0, max_range, samples) {
            let hit = point(root.t);
            let (e, datum_m) = self.within(hit.x, hit.y, reach)?;
            let provenance = provenance_of(datum_m, self.params.length_scale);
            let f = sd_factor(&hit);
            let step = 0.25 * self.params.cell_m;
            let band = root::band_variance(gap, root, f * e.var.sqrt(), step, 0.0, max_range);
            let var = (f * f * root::root_variance(gap, root, e.var)?).max(band);
            return Some(RayEstimate {
                range: Some(root.t),
                range_var: Some(var),
                hit_probability: distrs::Normal::cdf((max_range - root.t) / var.sqrt().max(1e-12), 0.0, 1.0),
                provenance,
            });
        }
        // The closest approach by the tiles' own σ; the calibration's factor is asked once, there.
        let (closest, at) = (0..=samples)
            .filter_map(|k| {
                let p = point(max_range * k as f64 / samples as f64);
                known(p.x, p.y).map(|e| ((e.z - p.z) / e.var.sqrt().max(1e-12), p))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(RayEstimate {
            range: None,
            range_var: None,
            hit_probability: distrs::Normal::cdf(closest / sd_factor(&at), 0.0, 1.0),
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
    pub(super) fn estimate(&self, x: f64, y: f64) -> Option<HeightEstimate> {
        self.within(x, y, self.params.max_gap_m).map(|(e, _)| e)
    }

    /// The height at (x, y) where a fused cell lies within `reach_m`, with that cell's distance.
    fn within(&self, x: f64, y: f64, reach_m: f64) -> Option<(HeightEstimate, f64)> {
        let datum_m = self.nearest_cell_within(x, y, reach_m)?;
        self.blend(x, y).map(|e| (e, datum_m))
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
                rise: 0.0,
                departure: 0.0,
            }
        })
    }
}
