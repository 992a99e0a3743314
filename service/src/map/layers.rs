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

use super::scales::{ErrorCorrelation, Relief, TailShape};
use super::window::MapSnapshot;
use nalgebra::{Matrix3, Vector3};
use rangegp_proto::msg::RobotModel;

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

/// The cells of a footprint on a grid and the correlation of their height errors.
#[derive(Debug, Clone)]
pub struct Stencil {
    /// Cell offsets (column, row) from the centre, within the footprint.
    offsets: Vec<(i32, i32)>,
    /// Offsets in metres.
    uv: Vec<(f64, f64)>,
    /// Error correlation between offsets a and b at `a * n + b`.
    corr: Vec<f64>,
    /// The terrain's semivariogram γ at the distance between offsets a and b, at `a * n + b`
    /// (zero where it is not learnt).
    gamma: Vec<f64>,
    /// Whether γ is learnt at every distance of the footprint (the bounds apply).
    bounded: bool,
    /// The terrain's own gradient covariance (xx, xy, yy) with every footprint cell answered
    /// (most cells' case; see [`cell_layers`]).
    terrain_gradient: [f64; 3],
    /// The terrain's mean square difference across the footprint's diameter, 2γ(2r), m².
    step_bound: f64,
    /// Largest |offset| along either axis, cells.
    reach: i32,
}

impl Stencil {
    /// The footprint of `model` sampled at `resolution_m` (positive, and at least the radius
    /// over [`MAX_FOOTPRINT_REACH`]; panics otherwise: callers validate requests first).
    pub fn new(model: &LayerModel, resolution_m: f64) -> Self {
        assert!(
            resolution_m > 0.0 && model.robot.footprint_radius_m / resolution_m <= MAX_FOOTPRINT_REACH,
            "a footprint of at most {MAX_FOOTPRINT_REACH} cells' radius"
        );
        let r = model.robot.footprint_radius_m;
        let reach = footprint_reach(r, resolution_m) as i32;
        let mut offsets = Vec::new();
        for dj in -reach..=reach {
            for di in -reach..=reach {
                let d2 = f64::from(di * di + dj * dj) * resolution_m * resolution_m;
                if d2 <= r * r * (1.0 + 1e-9) {
                    offsets.push((di, dj));
                }
            }
        }
        let uv: Vec<(f64, f64)> = offsets
            .iter()
            .map(|&(di, dj)| (f64::from(di) * resolution_m, f64::from(dj) * resolution_m))
            .collect();
        let n = uv.len();
        let correlation = ErrorCorrelation {
            length_m: model.error_length_m,
        };
        let mut corr = vec![0.0; n * n];
        let variogram = model.relief.semivariogram(2.0 * r);
        let gamma_at = |d: f64| variogram.map_or(0.0, |v| v.at(d));
        let mut gamma = vec![0.0; n * n];
        for a in 0..n {
            for b in 0..n {
                let d = (uv[a].0 - uv[b].0).hypot(uv[a].1 - uv[b].1);
                corr[a * n + b] = correlation.at(d);
                gamma[a * n + b] = gamma_at(d);
            }
        }
        let all: Vec<usize> = (0..n).collect();
        let mut w = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
        let [w0, wx, wy] = &mut w;
        let full_gradient = match plane_weights(&uv, &all, [&mut w0[..], &mut wx[..], &mut wy[..]]) {
            Some(()) => terrain_gradient(wx, wy, &all, &gamma, n),
            None => [0.0; 3],
        };
        Self {
            offsets,
            uv,
            corr,
            gamma,
            bounded: variogram.is_some(),
            terrain_gradient: full_gradient,
            step_bound: 2.0 * gamma_at(2.0 * r),
            reach,
        }
    }

    /// Cells the grid needs beyond each side of the box for the footprints of its edge cells.
    pub fn reach(&self) -> i32 {
        self.reach
    }

    /// Cells in the footprint.
    pub fn len(&self) -> usize {
        self.offsets.len()
    }

    /// Whether the footprint is empty (never: the centre is always in it).
    pub fn is_empty(&self) -> bool {
        self.offsets.is_empty()
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
mod tests {
    use super::*;
    use crate::map::test_support::layer_model;

    fn plane(cols: usize, rows: usize, res: f64, gx: f64, gy: f64) -> Vec<f64> {
        (0..rows)
            .flat_map(|j| (0..cols).map(move |i| 1.0 + gx * i as f64 * res + gy * j as f64 * res))
            .collect()
    }

    /// An 11 × 11 grid of heights `z` with σ `sd` and no relief share.
    fn grid11<'a>(z: &'a [f64], sd: &'a [f64]) -> HeightGrid<'a> {
        HeightGrid {
            cols: 11,
            rows: 11,
            z,
            sd,
            relief_sd: &[],
        }
    }

    #[test]
    fn a_plane_gives_its_slope_aspect_and_normal_with_no_roughness() {
        let (res, gx, gy) = (0.1, 0.2, -0.1);
        let z = plane(11, 11, res, gx, gy);
        let sd = vec![0.0; z.len()];
        let grid = grid11(&z, &sd);
        let m = layer_model();
        let s = Stencil::new(&m, res);
        assert_eq!(s.reach(), 3);
        let l = cell_layers(&grid, &s, &m, 5, 5).expect("inside the grid");
        assert!((l.slope - (gx.hypot(gy)).atan()).abs() < 1e-9);
        assert!((l.aspect - (-gy).atan2(-gx)).abs() < 1e-9);
        assert!(l.roughness < 1e-9);
        assert!((l.step - (gx.abs() + gy.abs()) * 0.2 - 0.0).abs() < 0.1);
        let n = Vector3::from(l.normal);
        assert!((n.norm() - 1.0).abs() < 1e-12 && n.cross(&Vector3::new(-gx, -gy, 1.0)).norm() < 1e-9);
        assert_eq!((l.slope_sd, l.slope_risk, l.unknown_risk), (0.0, 0.0, 0.0));
    }

    #[test]
    fn the_slope_sigma_matches_the_spread_of_slopes_over_correlated_height_errors() {
        // Height errors drawn with exactly the assumed covariance: the spread of the fitted
        // slope gradient must match the σ the delta method gives.
        use rand::{Rng, SeedableRng};
        let (res, n) = (0.1, 9usize);
        let m = layer_model();
        let s = Stencil::new(&m, res);
        let cells = n * n;
        let coords: Vec<(f64, f64)> = (0..cells)
            .map(|c| ((c % n) as f64 * res, (c / n) as f64 * res))
            .collect();
        let sigma = 0.02;
        let mut k = faer::Mat::<f64>::zeros(cells, cells);
        for a in 0..cells {
            for b in 0..cells {
                let d = (coords[a].0 - coords[b].0).hypot(coords[a].1 - coords[b].1);
                let rho = ErrorCorrelation {
                    length_m: m.error_length_m,
                }
                .at(d);
                k[(a, b)] = sigma * sigma * rho + if a == b { 1e-12 } else { 0.0 };
            }
        }
        let chol = k.llt(faer::Side::Lower).expect("positive definite");
        let l = chol.L();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let sd = vec![sigma; cells];
        let base = plane(n, n, res, 0.3, 0.0);
        let mut gx = Vec::new();
        let mut predicted = 0.0;
        for _ in 0..4000 {
            let w: Vec<f64> = (0..cells)
                .map(|_| {
                    let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
                    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
                })
                .collect();
            let z: Vec<f64> = (0..cells)
                .map(|a| base[a] + (0..=a).map(|b| l[(a, b)] * w[b]).sum::<f64>())
                .collect();
            let grid = HeightGrid {
                cols: n,
                rows: n,
                z: &z,
                sd: &sd,
                relief_sd: &[],
            };
            let c = cell_layers(&grid, &s, &m, 4, 4).expect("inside the grid");
            gx.push(c.slope.tan() * (-c.aspect.cos()));
            predicted = c.slope_sd * (1.0 + c.slope.tan().powi(2));
        }
        let mean = gx.iter().sum::<f64>() / gx.len() as f64;
        let spread = (gx.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / gx.len() as f64).sqrt();
        assert!((mean - 0.3).abs() < 0.01, "mean gradient {mean}");
        assert!(
            (spread / predicted - 1.0).abs() < 0.15,
            "spread {spread} against the delta method's {predicted}"
        );
    }

    #[test]
    fn unanswered_footprints_raise_the_unknown_risk_and_refuse_when_mostly_unknown() {
        let res = 0.1;
        let flat = plane(11, 11, res, 0.0, 0.0);
        let sd = vec![0.01; flat.len()];
        let m = layer_model();
        let s = Stencil::new(&m, res);
        let mut z = flat.clone();
        for j in 0..11 {
            for i in 0..5 {
                z[j * 11 + i] = f64::NAN;
            }
        }
        let grid = grid11(&z, &sd);
        let edge = cell_layers(&grid, &s, &m, 6, 5).expect("most of the footprint answered");
        assert!(edge.unknown_risk > 0.0 && edge.traversal_cost >= edge.unknown_risk);
        assert_eq!(cell_layers(&grid, &s, &m, 4, 5), None, "unanswered centre");
        // Only the centre column answered: under half the footprint.
        let column: Vec<f64> = (0..flat.len())
            .map(|k| if k % 11 == 5 { flat[k] } else { f64::NAN })
            .collect();
        let sparse = grid11(&column, &sd);
        assert_eq!(cell_layers(&sparse, &s, &m, 5, 5), None, "a line of cells");
    }

    #[test]
    fn heights_wider_than_the_step_limit_are_unknown_to_the_layers() {
        let res = 0.1;
        let z = plane(11, 11, res, 0.0, 0.0);
        let m = layer_model();
        let limit = m.robot.max_step_m;
        let s = Stencil::new(&m, res);
        let mut sd = vec![0.01; z.len()];
        let sure = cell_layers(&grid11(&z, &sd), &s, &m, 5, 5).expect("answered");
        assert_eq!(sure.unknown_risk, 0.0);
        // One footprint cell known to ± the limit, one just wider.
        sd[5 * 11 + 6] = limit;
        sd[5 * 11 + 4] = limit * 1.001;
        let one = cell_layers(&grid11(&z, &sd), &s, &m, 5, 5).expect("answered");
        assert!(
            (one.unknown_risk - 1.0 / s.len() as f64).abs() < 1e-12,
            "{} of {} cells",
            one.unknown_risk * s.len() as f64,
            s.len()
        );
        assert!(one.traversal_cost >= one.unknown_risk);
        // A smooth extrapolation of σ 0.8 m (a terrace's hidden foot): no layers, at any cell.
        let gap = vec![0.8; z.len()];
        assert_eq!(cell_layers(&grid11(&z, &gap), &s, &m, 5, 5), None);
        sd[5 * 11 + 5] = 0.8;
        assert_eq!(
            cell_layers(&grid11(&z, &sd), &s, &m, 5, 5),
            None,
            "the centre unknown"
        );
    }

    #[test]
    fn ground_mapped_flat_with_wide_sigma_is_risky_and_no_less_known_than_the_terrain() {
        let res = 0.1;
        let z = plane(11, 11, res, 0.001, 0.0);
        // As wide as a height may be and still be judged: the robot's step limit.
        let sd = vec![layer_model().robot.max_step_m; z.len()];
        let grid = grid11(&z, &sd);
        let unbounded = layer_model();
        let s = Stencil::new(&unbounded, res);
        let wide = cell_layers(&grid, &s, &unbounded, 5, 5).expect("answered");
        // A one-sided exceedance along the mapped gradient stopped at ½ here, however wide σ;
        // two-sided, the risk grows past it with σ.
        assert!(wide.slope_risk > 0.55 && wide.step_risk > 0.3, "{wide:?}");
        // A terrain learnt as a random walk of 1 cm over a metre: its slopes over the footprint
        // are of a degree or so, whatever σ the heights claim.
        let bounded = LayerModel {
            relief: Relief {
                var_m2: std::array::from_fn(|b| 1e-4 * crate::map::scales::data_centre_m(b)),
            },
            ..unbounded
        };
        let s = Stencil::new(&bounded, res);
        let known = cell_layers(&grid, &s, &bounded, 5, 5).expect("answered");
        assert!(
            known.slope_sd < 2f64.to_radians() && known.slope_sd < 0.05 * wide.slope_sd,
            "slope σ {} against {} unbounded",
            known.slope_sd.to_degrees(),
            wide.slope_sd.to_degrees()
        );
        let widest = (2.0 * bounded.relief.var_at(0.6)).sqrt();
        assert!(known.step_sd <= widest + 1e-12 && known.slope_risk < 0.01 && known.step_risk < 0.01);
    }

    #[test]
    fn a_footprint_deep_in_a_gap_takes_the_terrains_slope_from_its_relief_share() {
        let res = 0.1;
        let z = plane(11, 11, res, 0.0, 0.0);
        // A random walk of 1 cm over a metre, learnt at every distance.
        let m = LayerModel {
            relief: Relief {
                var_m2: std::array::from_fn(|b| 1e-4 * crate::map::scales::data_centre_m(b)),
            },
            ..layer_model()
        };
        let s = Stencil::new(&m, res);
        // Each cell's unseen relief at least the terrain's variation across the footprint: the
        // shares of two cells differ by what the terrain differs by over their distance, so the
        // slope they leave is the terrain's own (the share common to all moves no slope).
        let relief_sd = vec![0.05; z.len()];
        let sd = relief_sd.clone();
        let gap = HeightGrid {
            relief_sd: &relief_sd,
            ..grid11(&z, &sd)
        };
        let from_relief = cell_layers(&gap, &s, &m, 5, 5).expect("answered");
        let wide = vec![m.robot.max_step_m; z.len()];
        let bounded = cell_layers(&grid11(&z, &wide), &s, &m, 5, 5).expect("answered");
        assert!(
            (from_relief.slope_sd - bounded.slope_sd).abs() < 1e-9 * bounded.slope_sd,
            "{} against the terrain's {}",
            from_relief.slope_sd,
            bounded.slope_sd
        );
        // Fully correlated (the terrain not learnt), the same share moves no slope at all.
        let unlearnt = LayerModel {
            relief: Relief::default(),
            ..m
        };
        let s = Stencil::new(&unlearnt, res);
        let rigid = cell_layers(&gap, &s, &unlearnt, 5, 5).expect("answered");
        assert!(rigid.slope_sd < 1e-6, "{rigid:?}");
    }

    #[test]
    fn a_step_beyond_the_limit_is_lethal_and_flat_ground_is_free() {
        let res = 0.1;
        let mut z = plane(11, 11, res, 0.0, 0.0);
        let sd = vec![0.01; z.len()];
        let m = layer_model();
        let s = Stencil::new(&m, res);
        let free = cell_layers(&grid11(&z, &sd), &s, &m, 5, 5).expect("answered");
        assert_eq!(free.cost(0.5), 0);
        for j in 0..11 {
            for i in 6..11 {
                z[j * 11 + i] += 0.35;
            }
        }
        let stepped = grid11(&z, &sd);
        let wall = cell_layers(&stepped, &s, &m, 5, 5).expect("answered");
        assert!((wall.step - 0.35).abs() < 1e-9 && wall.step_risk > 0.99);
        assert_eq!(wall.cost(0.5), 100);
    }
}
