//! Change detection (`change_detection`): a scan's returns tested against what earlier returns
//! measured in each cell, and the cells its rays passed below (docs/ARCHITECTURE.md "Change").

use super::{f32_cell, fused, Cell, Change, WorldAggregate};
use crate::map::aggregate::returns::Measured;
use crate::map::local::LocalRangeMap;
use crate::map::plane::{Plane, Returns};
use crate::scan::ScanInput;
use nalgebra::Vector3;
use std::collections::{BTreeSet, HashMap};

impl WorldAggregate {
    /// Tests one scan's returns in cell `c` (`plane`, through them) against what earlier returns
    /// measured there (else against the cell): agreeing, they are fused into that reference and
    /// dismiss a challenger they disagree with; disagreeing, they are held as a challenger, and
    /// `change_confirm_scans` scans that reject the reference on the same side replace the cell
    /// (not when rays of this scan, `cleared`, just did).
    /// Returns the replacement when they do: a move of the world when earlier returns were
    /// contradicted (returns against returns compare like with like, neither smoothed by a range
    /// map), a correction of the map when only predictions were.
    pub(super) fn challenge(
        &mut self,
        c: (i32, i32),
        plane: Plane,
        this: u64,
        cleared: bool,
    ) -> Option<Replaced> {
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
        self.seen_from.remove(&c);
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
    pub(super) fn carved(
        &self,
        scan: &ScanInput,
        local: &LocalRangeMap,
        reach_m: f64,
    ) -> BTreeSet<(i32, i32)> {
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
    pub(super) fn clear(&mut self, c: (i32, i32), local: &LocalRangeMap, this: u64) -> Option<Change> {
        let cell = self.cells.get(&c).copied()?;
        let (x_m, y_m) = self.centre(c);
        let height = self.window_answer(local, c).map(|(z, var, _)| Cell {
            z: z as f64,
            var: var as f64,
            scans: 1,
        });
        // The scan's own height there must disagree too: a plane through a crater's rim, carried
        // across the cell, stands above ground the rays legitimately graze.
        let reference = self.returns.get(&c).map_or(cell, |m| m.cell);
        if height.is_some_and(|h| self.agree(&reference, &h)) {
            return None;
        }
        self.challengers.remove(&c);
        self.returns.remove(&c);
        self.seen_from.remove(&c);
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
    /// their scatter about the plane where larger, through the fit: [`Returns`]). The
    /// highest return, used before, read a sloping cell differently from every view, and the
    /// top of many noisy returns lies above the ground by a couple of σ.
    pub(super) fn returns_by_cell(
        &self,
        scan: &ScanInput,
        local: &LocalRangeMap,
        reach_m: f64,
    ) -> Vec<((i32, i32), Plane)> {
        let pose = local.pose();
        let s = pose.translation.vector;
        let reach = local.max_range().min(self.params.max_reach_m).min(reach_m);
        let mut bins: HashMap<(i32, i32), Returns> = HashMap::new();
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
    pub(super) fn agree(&self, a: &Cell, b: &Cell) -> bool {
        let p = &self.params;
        let var = a.var + b.var + p.change_floor_m * p.change_floor_m;
        (a.z - b.z).powi(2) <= p.change_gate_sigmas * p.change_gate_sigmas * var
    }

    /// The insert at which cell `c` was last replaced by a change (older scans' evidence is no
    /// longer in it).
    pub fn replaced_at(&self, c: (i32, i32)) -> Option<u64> {
        self.replaced_at.get(&c).copied()
    }
}

/// A cell the returns replaced.
#[derive(Debug, Clone, Copy)]
pub(super) enum Replaced {
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
