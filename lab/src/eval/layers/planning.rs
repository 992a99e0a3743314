//! A* between random start and goal cells over the cost layer, against the oracle's plan over
//! the true labels.

use super::{TruthLayers, MIN_PAIR_DISTANCE_M, RISK_WEIGHT_SWEEP};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_proto::msg::{GridReply, Layer};

/// What planning over one case gave.
#[derive(Default)]
pub(super) struct Plan {
    pub(super) pairs: usize,
    pub(super) no_path: usize,
    pub(super) path_cells: usize,
    pub(super) unsafe_cells: usize,
    pub(super) predicted_unsafe_cells: f64,
    pub(super) ratios: Vec<f64>,
}

/// A* between `pairs` random start / goal cells over the cost layer, once per weight of
/// [`RISK_WEIGHT_SWEEP`] (the same pairs each time), and over the true labels.
pub(super) fn plan_pairs(reply: &GridReply, truth: &TruthLayers, pairs: usize, seed: u64) -> Vec<Plan> {
    let (cols, rows) = (reply.cols as usize, reply.rows as usize);
    let res = reply.resolution_m;
    let robot = &reply.robot;
    let risk = reply.layer(Layer::TraversalCost).unwrap_or(&[]);
    let stop_risk = reply.layer(Layer::Risk).unwrap_or(&[]);
    let blocked_map: Vec<bool> = reply.costmap.iter().map(|&c| c == 100 || c < 0).collect();
    let observed: Vec<bool> = reply.costmap.iter().map(|&c| c >= 0).collect();
    let untraversable: Vec<bool> = truth
        .cells
        .iter()
        .map(|t| t.is_none_or(|t| t.slope > robot.max_slope_deg.to_radians() || t.step > robot.max_step_m))
        .collect();
    let blocked_truth: Vec<bool> = (0..cols * rows)
        .map(|k| untraversable[k] || !observed[k])
        .collect();
    let cell_risk = |k: usize| risk.get(k).copied().flatten().map_or(1.0, f64::from);
    let mut plans: Vec<Plan> = RISK_WEIGHT_SWEEP.iter().map(|_| Plan::default()).collect();
    let free: Vec<usize> = (0..cols * rows)
        .filter(|&k| !blocked_map[k] && !blocked_truth[k])
        .collect();
    if free.len() < 2 {
        return plans;
    }
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut attempts = 0;
    let mut planned = 0;
    while planned < pairs && attempts < 50 * pairs {
        attempts += 1;
        let (a, b) = (
            free[rng.random_range(0..free.len())],
            free[rng.random_range(0..free.len())],
        );
        let d = ((a % cols) as f64 - (b % cols) as f64).hypot((a / cols) as f64 - (b / cols) as f64) * res;
        if d < MIN_PAIR_DISTANCE_M {
            continue;
        }
        let Some((_, oracle_len)) = astar(cols, rows, a, b, &blocked_truth, &|_| 1.0) else {
            continue;
        };
        planned += 1;
        for (plan, weight) in plans.iter_mut().zip(RISK_WEIGHT_SWEEP) {
            plan.pairs += 1;
            match astar(cols, rows, a, b, &blocked_map, &|k| 1.0 + weight * cell_risk(k)) {
                None => plan.no_path += 1,
                Some((path, length)) => {
                    plan.path_cells += path.len();
                    plan.unsafe_cells += path.iter().filter(|&&k| untraversable[k]).count();
                    plan.predicted_unsafe_cells += path
                        .iter()
                        .map(|&k| stop_risk.get(k).copied().flatten().map_or(0.0, f64::from))
                        .sum::<f64>();
                    plan.ratios.push(length / oracle_len.max(1e-9));
                }
            }
        }
    }
    plans
}

/// The cheapest 8-connected path from `a` to `b` avoiding `blocked`, each step its length in
/// cells times the mean `cost` of its two cells; with the path's length in cells.
fn astar(
    cols: usize,
    rows: usize,
    a: usize,
    b: usize,
    blocked: &[bool],
    cost: &dyn Fn(usize) -> f64,
) -> Option<(Vec<usize>, f64)> {
    const SCALE: f64 = 1000.0;
    let (bx, by) = ((b % cols) as i64, (b / cols) as i64);
    let (path, _) = pathfinding::prelude::astar(
        &a,
        |&k| {
            let (x, y) = ((k % cols) as i64, (k / cols) as i64);
            let mut next = Vec::with_capacity(8);
            for (dx, dy) in [
                (-1, -1),
                (0, -1),
                (1, -1),
                (-1, 0),
                (1, 0),
                (-1, 1),
                (0, 1),
                (1, 1),
            ] {
                let (nx, ny) = (x + dx, y + dy);
                if nx < 0 || ny < 0 || nx >= cols as i64 || ny >= rows as i64 {
                    continue;
                }
                let j = ny as usize * cols + nx as usize;
                if blocked[j] {
                    continue;
                }
                let step = if dx != 0 && dy != 0 { 2f64.sqrt() } else { 1.0 };
                next.push((j, (step * 0.5 * (cost(k) + cost(j)) * SCALE).round() as u64));
            }
            next
        },
        |&k| {
            let (x, y) = ((k % cols) as i64, (k / cols) as i64);
            let (dx, dy) = ((x - bx).abs(), (y - by).abs());
            let octile = (dx.max(dy) - dx.min(dy)) as f64 + 2f64.sqrt() * dx.min(dy) as f64;
            (octile * SCALE).floor() as u64
        },
        |&k| k == b,
    )?;
    let length = path
        .windows(2)
        .map(|w| {
            if w[0] % cols != w[1] % cols && w[0] / cols != w[1] / cols {
                2f64.sqrt()
            } else {
                1.0
            }
        })
        .sum();
    Some((path, length))
}
