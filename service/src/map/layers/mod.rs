//! Planner layers over a grid of heights with σ: slope, aspect, roughness and step over a
//! robot's footprint, each with its σ by the delta method, and the risks and cost they give.
//!
//! Every layer is a function of the heights at the grid cells inside the footprint (a disc around
//! the cell centre): slope and aspect from the least-squares plane, roughness the RMS of the
//! plane's residuals, step the largest height difference. Their errors follow from the heights'
//! errors through the Jacobian of that function (exact for the linear slope gradient, first order
//! for the rest). The heights' errors are not independent: two cells a few centimetres apart are
//! answered by the same GP experts from the same returns, so their errors move together, which is
//! what keeps a smooth map's slope error small. The covariance between cells i and j is taken as
//! σᵢ σⱼ ρ(dᵢⱼ), with σ the calibrated height σ of each answer and ρ a Matérn-3/2 correlation of
//! length [`LayerModel::error_length_m`] (see docs/ARCHITECTURE.md "Planner layers").
//!
//! The terrain's own increments bound what a map can fail to know: two points s apart differ by
//! 2γ(s) in mean square, γ the semivariogram the calibrator's relief gives
//! ([`super::scales::Semivariogram`]). A map knows a slope or a step no worse than the terrain's
//! own slopes and steps let one guess them, so their variances are bounded by what γ gives
//! (see [`cell_layers`]). With `gp.unseen_relief` an answer's variance carries the relief unseen
//! at its distance from data, rᵢ²: that share is the terrain itself between returns, so it is
//! taken apart (σᵢ² above is the rest) and correlated as the terrain is, max(0, rᵢrⱼ − γ(dᵢⱼ)):
//! two cells deep in a gap differ by what the terrain differs by over their distance.
//!
//! A cell whose height σ is wider than the robot's step limit counts as unknown: a height known
//! no better than that cannot tell a drivable footprint from a step, and the terrain's bounds
//! above, learnt from the relief the scans saw, say nothing of a riser no scan saw (a terrace's
//! face seen from above, its foot hidden behind its edge, is mapped as a smooth extrapolation of
//! σ 0.5–1 m that the bounds would call a 4 % risk).

use super::scales::{Relief, TailShape};
use super::window::MapSnapshot;
use nalgebra::{Matrix3, Vector3};
use rangegp_proto::msg::RobotModel;

mod stencil;

pub use stencil::Stencil;

/// Largest footprint radius in grid cells a layer request may ask for: the per-cell work grows
/// as the fourth power of it (a quadratic form over the footprint's cells), so a finer grid is
/// refused rather than left to run for minutes.
pub const MAX_FOOTPRINT_REACH: f64 = 8.0;

/// Cells of a footprint of `radius_m` beyond its centre along each axis at `resolution_m` (the
/// margin a grid needs around its box).
pub fn footprint_reach(radius_m: f64, resolution_m: f64) -> usize {
    (radius_m / resolution_m + 1e-9).floor() as usize
}

/// A footprint needs at least this share of its cells answered to give layers.
pub const MIN_KNOWN_SHARE: f64 = 0.5;

/// How the layers are judged: the robot and the correlation of height errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerModel {
    /// The robot's footprint and limits.
    pub robot: RobotModel,
    /// Correlation length of height errors between nearby cells, metres.
    pub error_length_m: f64,
    /// Shape of the calibrated errors (the snapshot's, learnt with its σ scales).
    pub tails: TailShape,
    /// The unseen relief by distance from data (the snapshot's; zero when not learnt).
    pub relief: Relief,
}

impl LayerModel {
    /// The layers of `robot` over `snapshot`'s maps: their error correlation length and the
    /// tail shape learnt with their σ scales.
    pub fn new(robot: RobotModel, snapshot: &MapSnapshot) -> Self {
        Self {
            robot,
            error_length_m: snapshot.scales.correlation.length_m,
            tails: snapshot.scales.tails,
            relief: snapshot.scales.relief,
        }
    }
}

/// Heights and their σ on a regular grid, row-major from the lower-left cell; NaN where no map
/// answers.
#[derive(Debug, Clone, Copy)]
pub struct HeightGrid<'a> {
    /// Cells along x.
    pub cols: usize,
    /// Cells along y.
    pub rows: usize,
    /// Height per cell, metres.
    pub z: &'a [f64],
    /// σ of the height per cell, metres.
    pub sd: &'a [f64],
    /// σ of the unseen relief's share of it per cell (`gp.unseen_relief`), metres, or empty.
    pub relief_sd: &'a [f64],
}

/// The layers at one cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellLayers {
    /// Slope angle, radians.
    pub slope: f64,
    /// σ of the slope, radians.
    pub slope_sd: f64,
    /// Downhill direction, radians counter-clockwise from +x.
    pub aspect: f64,
    /// Unit normal of the footprint's plane.
    pub normal: [f64; 3],
    /// RMS deviation from the plane, metres.
    pub roughness: f64,
    /// σ of the roughness, metres.
    pub roughness_sd: f64,
    /// Largest height difference, metres.
    pub step: f64,
    /// σ of the step, metres.
    pub step_sd: f64,
    /// P(slope > max slope).
    pub slope_risk: f64,
    /// P(step > max step).
    pub step_risk: f64,
    /// Share of the footprint unknown: unanswered, or answered with a σ wider than the robot's
    /// step limit.
    pub unknown_risk: f64,
    /// P(slope or step stops the robot): the larger of the two (they share their height errors).
    pub risk: f64,
    /// Traversal cost: `risk` and `unknown_risk` taken as independent.
    pub traversal_cost: f64,
}

impl CellLayers {
    /// The ROS costmap value of this cell: traversal cost × 100 rounded, 100 at and above
    /// `lethal_risk`.
    pub fn cost(&self, lethal_risk: f64) -> i8 {
        if self.traversal_cost >= lethal_risk {
            100
        } else {
            (self.traversal_cost * 100.0).round().clamp(0.0, 99.0) as i8
        }
    }
}

/// The layers of cell (col, row) of `grid`, or `None` when its centre is unknown or less than
/// [`MIN_KNOWN_SHARE`] of its footprint is known (at least three cells, not all in a line). A cell
/// is known where a map answers it with a σ no wider than the robot's step limit.
pub fn cell_layers(
    grid: &HeightGrid,
    stencil: &Stencil,
    model: &LayerModel,
    col: usize,
    row: usize,
) -> Option<CellLayers> {
    let at = |i: i64, j: i64| -> Option<usize> {
        let ok = i >= 0 && j >= 0 && (i as usize) < grid.cols && (j as usize) < grid.rows;
        ok.then(|| j as usize * grid.cols + i as usize)
    };
    // A height known no better than ± the robot's step limit cannot tell a drivable footprint
    // from a step: such a cell counts as unknown (see the module doc).
    let judged = |c: usize| grid.z[c].is_finite() && grid.sd[c] <= model.robot.max_step_m;
    let centre = at(col as i64, row as i64)?;
    if !judged(centre) {
        return None;
    }
    let m = stencil.len();
    let mut known: Vec<usize> = Vec::with_capacity(m);
    // Per footprint cell: height, σ without the relief, the relief's σ, and the weights on
    // σ-scaled heights of the gradient's two components and of the roughness, and the same on
    // the heights themselves for the relief's share (zero where the cell is unknown).
    let mut buf = vec![0.0; 10 * m];
    let (z, rest) = buf.split_at_mut(m);
    let (sd, rest) = rest.split_at_mut(m);
    let (rd, rest) = rest.split_at_mut(m);
    let (px, rest) = rest.split_at_mut(m);
    let (py, rest) = rest.split_at_mut(m);
    let (pr, rest) = rest.split_at_mut(m);
    let (w0, rest) = rest.split_at_mut(m);
    let (wx, rest) = rest.split_at_mut(m);
    let (wy, wr) = rest.split_at_mut(m);
    for (k, &(di, dj)) in stencil.offsets.iter().enumerate() {
        let Some(c) = at(col as i64 + i64::from(di), row as i64 + i64::from(dj)) else {
            continue;
        };
        if judged(c) {
            known.push(k);
            z[k] = grid.z[c];
            let total = grid.sd[c].max(0.0);
            let relief = grid.relief_sd.get(c).copied().unwrap_or(0.0);
            if relief > 0.0 {
                let relief = relief.min(total);
                rd[k] = relief;
                sd[k] = (total * total - relief * relief).max(0.0).sqrt();
            } else {
                sd[k] = total;
            }
        }
    }
    let n = known.len();
    let unknown_risk = 1.0 - n as f64 / m as f64;
    if n < 3 || (n as f64) < MIN_KNOWN_SHARE * m as f64 {
        return None;
    }
    plane_weights(&stencil.uv, &known, [&mut *w0, &mut *wx, &mut *wy])?;
    let mut coef = Vector3::zeros();
    for &k in &known {
        coef += Vector3::new(w0[k], wx[k], wy[k]) * z[k];
        px[k] = wx[k] * sd[k];
        py[k] = wy[k] * sd[k];
    }
    let (gx, gy) = (coef.y, coef.z);
    let mut sum_r2 = 0.0;
    for &k in &known {
        let r = z[k] - (coef.x + gx * stencil.uv[k].0 + gy * stencil.uv[k].1);
        pr[k] = r;
        sum_r2 += r * r;
    }
    let roughness = (sum_r2 / n as f64).sqrt();
    // Roughness as a linear functional of the heights near its value: weights r / (n · rms).
    let scale = if roughness > 1e-12 {
        1.0 / (n as f64 * roughness)
    } else {
        0.0
    };
    for &k in &known {
        wr[k] = pr[k] * scale;
        pr[k] *= scale * sd[k];
    }
    // The covariances of the gradient's two components and of the roughness, Σ pₐ Cₐᵦ pᵦ with
    // p the σ-scaled weights, over the upper triangle of the symmetric correlations (each pair
    // once: Cₐₐ pₐ² + 2 Σ_{b>a} pₐ Cₐᵦ pᵦ) of the known cells' rows (an unknown cell's weights
    // are zero).
    let (mut vxx, mut vyy, mut vxy, mut vrr) = (0.0, 0.0, 0.0, 0.0);
    for &a in &known {
        let row = &stencil.corr[a * m..a * m + m];
        let (cx, cy, cr) = dot3(&row[a + 1..], &px[a + 1..], &py[a + 1..], &pr[a + 1..]);
        let caa = row[a];
        vxx += px[a] * (caa * px[a] + 2.0 * cx);
        vyy += py[a] * (caa * py[a] + 2.0 * cy);
        vxy += caa * px[a] * py[a] + px[a] * cy + py[a] * cx;
        vrr += pr[a] * (caa * pr[a] + 2.0 * cr);
    }
    if known.iter().any(|&k| rd[k] > 0.0) {
        // The relief's share, Σ wₐ wᵦ max(0, rₐrᵦ − γ(dₐᵦ)) (fully correlated where γ is not
        // learnt).
        for &a in &known {
            let row = &stencil.gamma[a * m..a * m + m];
            for &b in &known {
                let q = (rd[a] * rd[b] - row[b]).max(0.0);
                if q > 0.0 {
                    vxx += wx[a] * wx[b] * q;
                    vyy += wy[a] * wy[b] * q;
                    vxy += wx[a] * wy[b] * q;
                    vrr += wr[a] * wr[b] * q;
                }
            }
        }
    }
    // The terrain's own gradient covariance over the footprint: the gradient's weights sum to
    // zero, so only the terrain's increments enter, Var Σ wz = −Σ wₐ wᵦ γ(dₐᵦ).
    let learnt = stencil.bounded;
    let [qxx, qxy, qyy] = if !learnt {
        [0.0; 3]
    } else if n == m {
        stencil.terrain_gradient
    } else {
        terrain_gradient(wx, wy, &known, &stencil.gamma, m)
    };
    let g = gx.hypot(gy);
    let (ux, uy) = if g > 1e-12 { (gx / g, gy / g) } else { (1.0, 0.0) };
    let along_dir = |xx: f64, xy: f64, yy: f64| ux * ux * xx + 2.0 * ux * uy * xy + uy * uy * yy;
    let across_dir = |xx: f64, xy: f64, yy: f64| uy * uy * xx - 2.0 * ux * uy * xy + ux * ux * yy;
    // A map can know a slope no worse than the terrain's own slopes let one guess it: far from
    // data its heights' σ is wide and smooth, and the delta method over it (with the short error
    // length learnt near data) would claim slopes of any angle.
    let (mut var_along, mut var_across) = (along_dir(vxx, vxy, vyy), across_dir(vxx, vxy, vyy));
    if learnt {
        var_along = var_along.min(along_dir(qxx, qxy, qyy));
        var_across = var_across.min(across_dir(qxx, qxy, qyy));
    }
    let g_var = if g > 1e-12 {
        var_along
    } else {
        0.5 * (var_along + var_across)
    };
    let g_sd = g_var.max(0.0).sqrt();
    let slope = g.atan();
    let slope_sd = g_sd / (1.0 + g * g);
    let norm = (1.0 + g * g).sqrt();
    let normal = [-gx / norm, -gy / norm, 1.0 / norm];
    let aspect = (-gy).atan2(-gx);
    let roughness_sd = vrr.max(0.0).sqrt();

    let (mut hi, mut lo) = (known[0], known[0]);
    for &k in &known[1..] {
        if z[k] > z[hi] {
            hi = k;
        }
        if z[k] < z[lo] {
            lo = k;
        }
    }
    let step = z[hi] - z[lo];
    let rho = stencil.corr[hi * m + lo];
    let relief_cov = (rd[hi] * rd[lo] - stencil.gamma[hi * m + lo]).max(0.0);
    let mut step_var =
        sd[hi] * sd[hi] + sd[lo] * sd[lo] - 2.0 * rho * sd[hi] * sd[lo] + rd[hi] * rd[hi] + rd[lo] * rd[lo]
            - 2.0 * relief_cov;
    if learnt {
        // No worse known than the terrain's own difference across the footprint (the widest
        // pair: on ground mapped flat the two cells the step spans may be any two).
        step_var = step_var.min(stencil.step_bound);
    }
    let step_sd = step_var.max(0.0).sqrt();

    // The true gradient lies outside the disc of the limit's gradient whenever either of its
    // components (along the mapped gradient and across it) lies outside [−limit, limit]: the
    // probability of that (the two taken as independent) is the slope risk. It is the one-sided
    // exceedance along the gradient where σ is small, and tends to 1 as σ grows, where a
    // one-sided exceedance would stop at ½ on ground mapped flat.
    let robot = &model.robot;
    let (sd_along, sd_across) = (var_along.max(0.0).sqrt(), var_across.max(0.0).sqrt());
    let limit = robot.max_slope_deg.to_radians().tan();
    let along = model.tails.outside(g, sd_along, limit);
    let across = model.tails.outside(0.0, sd_across, limit);
    let slope_risk = 1.0 - (1.0 - along) * (1.0 - across);
    // The true step is at least the true difference of the two cells the mapped step spans, of
    // either sign.
    let step_risk = model.tails.outside(step, step_sd, robot.max_step_m);
    let risk = slope_risk.max(step_risk);
    let traversal_cost = 1.0 - (1.0 - risk) * (1.0 - unknown_risk);
    Some(CellLayers {
        slope,
        slope_sd,
        aspect,
        normal,
        roughness,
        roughness_sd,
        step,
        step_sd,
        slope_risk,
        step_risk,
        unknown_risk,
        risk,
        traversal_cost,
    })
}

/// The least-squares plane z = a + gₓu + g_yv over the cells `known` of offsets `uv`: the rows
/// of (XᵀX)⁻¹Xᵀ, the weights on the heights that give a, gₓ and g_y, written at the known cells
/// of `w`; `None` when the cells lie on a line.
fn plane_weights(uv: &[(f64, f64)], known: &[usize], w: [&mut [f64]; 3]) -> Option<()> {
    let mut xtx = Matrix3::zeros();
    for &k in known {
        let x = Vector3::new(1.0, uv[k].0, uv[k].1);
        xtx += x * x.transpose();
    }
    let inv = xtx.try_inverse()?;
    let [w0, wx, wy] = w;
    for &k in known {
        let c = inv * Vector3::new(1.0, uv[k].0, uv[k].1);
        (w0[k], wx[k], wy[k]) = (c.x, c.y, c.z);
    }
    Some(())
}

/// The terrain's own covariance (xx, xy, yy) of the gradient with weights `wx`, `wy` over the
/// cells `known`: −Σ wₐ wᵦ γ(dₐᵦ), γ at `a * m + b` of `gamma` (see the module doc).
fn terrain_gradient(wx: &[f64], wy: &[f64], known: &[usize], gamma: &[f64], m: usize) -> [f64; 3] {
    let mut q = [0.0; 3];
    for &a in known {
        let row = &gamma[a * m..a * m + m];
        for &b in known {
            q[0] -= wx[a] * wx[b] * row[b];
            q[1] -= wx[a] * wy[b] * row[b];
            q[2] -= wy[a] * wy[b] * row[b];
        }
    }
    q
}

/// The dot products of `row` with `a`, `b` and `c` (equal lengths), four lanes at a time.
fn dot3(row: &[f64], a: &[f64], b: &[f64], c: &[f64]) -> (f64, f64, f64) {
    let mut acc = [[0.0; 4]; 3];
    let n4 = row.len() / 4 * 4;
    for i in (0..n4).step_by(4) {
        for l in 0..4 {
            let r = row[i + l];
            acc[0][l] += a[i + l] * r;
            acc[1][l] += b[i + l] * r;
            acc[2][l] += c[i + l] * r;
        }
    }
    let lanes = |v: [f64; 4]| (v[0] + v[1]) + (v[2] + v[3]);
    let (mut x, mut y, mut z) = (lanes(acc[0]), lanes(acc[1]), lanes(acc[2]));
    for i in n4..row.len() {
        x += a[i] * row[i];
        y += b[i] * row[i];
        z += c[i] * row[i];
    }
    (x, y, z)
}

#[cfg(test)]
mod tests;
