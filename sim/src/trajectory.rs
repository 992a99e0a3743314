//! Rover trajectories of seed 000 §IV: A* between a random start and goal on the heightmap, with
//! obstacles wherever |height − mean height| exceeds a threshold, downsampled to a scan every few
//! metres, headings from the direction of travel. The search is `pathfinding`'s A*.

use crate::path::Path;
use crate::terrain::Heightmap;
use pathfinding::prelude::astar;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// How trajectories are planned.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryParams {
    /// Planning grid cell, metres.
    pub grid_m: f64,
    /// Cells whose |height − mean| exceeds this are obstacles, metres.
    pub obstacle_threshold_m: f64,
    /// Start and goal stay this far inside the map edge (a full scan stays on the map), metres.
    pub margin_m: f64,
    /// Start and goal at least this far apart, metres.
    pub min_length_m: f64,
    /// Distance between scans along the path, metres.
    pub spacing_m: f64,
}

impl Default for TrajectoryParams {
    fn default() -> Self {
        Self {
            grid_m: 0.5,
            obstacle_threshold_m: 0.3,
            margin_m: 12.0,
            min_length_m: 50.0,
            spacing_m: 5.0,
        }
    }
}

/// A planned trajectory: the dense A* polyline and the scan poses sampled along it.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Grid-cell centres of the A* path, (x, y) metres.
    pub dense: Vec<[f64; 2]>,
    /// Scan poses every `spacing_m` metres of arc length, heading along the path.
    pub scans: Path,
}

/// Obstacle grid of a heightmap.
struct Grid<'a> {
    terrain: &'a Heightmap,
    p: TrajectoryParams,
    cells: i64,
    blocked: Vec<bool>,
}

impl<'a> Grid<'a> {
    fn new(terrain: &'a Heightmap, p: TrajectoryParams) -> Self {
        let cells = (2.0 * terrain.half_extent() / p.grid_m).floor() as i64;
        let mean = terrain.mean_height();
        let mut g = Self {
            terrain,
            p,
            cells,
            blocked: Vec::new(),
        };
        g.blocked = (0..cells * cells)
            .map(|k| {
                let [x, y] = g.centre((k % cells, k / cells));
                terrain
                    .height(x, y)
                    .is_none_or(|h| (h - mean).abs() > p.obstacle_threshold_m)
            })
            .collect();
        g
    }

    fn centre(&self, (i, j): (i64, i64)) -> [f64; 2] {
        let h = self.terrain.half_extent();
        [
            -h + (i as f64 + 0.5) * self.p.grid_m,
            -h + (j as f64 + 0.5) * self.p.grid_m,
        ]
    }

    fn cell_of(&self, x: f64, y: f64) -> (i64, i64) {
        let h = self.terrain.half_extent();
        (
            ((x + h) / self.p.grid_m).floor() as i64,
            ((y + h) / self.p.grid_m).floor() as i64,
        )
    }

    fn free(&self, (i, j): (i64, i64)) -> bool {
        (0..self.cells).contains(&i)
            && (0..self.cells).contains(&j)
            && !self.blocked[(j * self.cells + i) as usize]
    }

    /// 8-connected free neighbours with costs in millimetres.
    fn neighbours(&self, (i, j): (i64, i64)) -> Vec<((i64, i64), u64)> {
        let straight = (self.p.grid_m * 1000.0).round() as u64;
        let diagonal = (self.p.grid_m * std::f64::consts::SQRT_2 * 1000.0).round() as u64;
        let mut out = Vec::with_capacity(8);
        for dj in -1..=1 {
            for di in -1..=1 {
                if (di, dj) == (0, 0) {
                    continue;
                }
                let n = (i + di, j + dj);
                // No corner cutting between two blocked cells.
                if self.free(n) && self.free((i + di, j)) && self.free((i, j + dj)) {
                    out.push((n, if di != 0 && dj != 0 { diagonal } else { straight }));
                }
            }
        }
        out
    }

    fn heuristic(&self, a: (i64, i64), b: (i64, i64)) -> u64 {
        let d = ((a.0 - b.0) as f64).hypot((a.1 - b.1) as f64) * self.p.grid_m * 1000.0;
        d.floor() as u64
    }
}

/// Fraction of the map's planning cells that are obstacles.
pub fn obstacle_fraction(terrain: &Heightmap, p: TrajectoryParams) -> f64 {
    let g = Grid::new(terrain, p);
    g.blocked.iter().filter(|&&b| b).count() as f64 / g.blocked.len() as f64
}

/// Plans `count` trajectories with random start / goal pairs drawn from `seed`. Pairs with no
/// path are redrawn (at most 100 draws per trajectory); `None` if the map has no room for them.
pub fn plan_trajectories(
    terrain: &Heightmap,
    seed: u64,
    count: usize,
    p: TrajectoryParams,
) -> Option<Vec<Trajectory>> {
    let grid = Grid::new(terrain, p);
    let mut rng = Pcg64::seed_from_u64(seed);
    let lim = terrain.half_extent() - p.margin_m;
    let mut out = Vec::with_capacity(count);
    let mut draws = 0;
    while out.len() < count {
        draws += 1;
        if draws > 100 * count {
            return None;
        }
        let mut pick = || grid.cell_of(rng.random_range(-lim..lim), rng.random_range(-lim..lim));
        let (start, goal) = (pick(), pick());
        if !grid.free(start)
            || !grid.free(goal)
            || grid.heuristic(start, goal) < (p.min_length_m * 1000.0) as u64
        {
            continue;
        }
        let Some((cells, _)) = astar(
            &start,
            |&c| grid.neighbours(c),
            |&c| grid.heuristic(c, goal),
            |&c| c == goal,
        ) else {
            continue;
        };
        let dense: Vec<[f64; 2]> = cells.iter().map(|&c| grid.centre(c)).collect();
        out.push(Trajectory {
            scans: resample(&dense, p.spacing_m),
            dense,
        });
    }
    Some(out)
}

/// Poses every `spacing` metres of arc length along a polyline, heading along the segment.
fn resample(line: &[[f64; 2]], spacing: f64) -> Path {
    let mut waypoints = Vec::new();
    let mut next = 0.0;
    let mut walked = 0.0;
    for seg in line.windows(2) {
        let (dx, dy) = (seg[1][0] - seg[0][0], seg[1][1] - seg[0][1]);
        let len = dx.hypot(dy);
        let heading = dy.atan2(dx);
        while next <= walked + len {
            let f = (next - walked) / len;
            waypoints.push([seg[0][0] + f * dx, seg[0][1] + f * dy, heading]);
            next += spacing;
        }
        walked += len;
    }
    Path { waypoints }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::terrain::CraterParams;

    #[test]
    fn trajectories_avoid_obstacles_and_are_evenly_spaced() {
        let terrain = Heightmap::cratered(3, &CraterParams::sized(60.0));
        let p = TrajectoryParams {
            min_length_m: 20.0,
            ..TrajectoryParams::default()
        };
        let frac = obstacle_fraction(&terrain, p);
        assert!(frac > 0.0 && frac < 0.5, "obstacle fraction {frac}");
        let grid = Grid::new(&terrain, p);
        for t in plan_trajectories(&terrain, 9, 3, p).expect("planned") {
            assert!(t.dense.iter().all(|c| grid.free(grid.cell_of(c[0], c[1]))));
            let w = &t.scans.waypoints;
            assert!(w.len() >= 4, "{} scans", w.len());
            for pair in w.windows(2) {
                let d = (pair[1][0] - pair[0][0]).hypot(pair[1][1] - pair[0][1]);
                assert!(d <= p.spacing_m + 1e-9 && d > 0.5 * p.spacing_m, "spacing {d}");
            }
        }
    }

    #[test]
    fn resampling_a_straight_line_gives_exact_poses() {
        let path = resample(&[[0.0, 0.0], [0.0, 12.0]], 5.0);
        assert_eq!(path.waypoints.len(), 3);
        assert!((path.waypoints[2][1] - 10.0).abs() < 1e-12);
        assert!((path.waypoints[1][2] - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }
}
