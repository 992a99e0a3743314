//! Moving objects in `rangegp-eval world` (issue 17): a robot drives past the same place three
//! times; an object (a box with vertical faces) stands there on the second pass only. Scored: the
//! cells the aggregate reports replaced on the second pass (the object appeared) and the third
//! (it left) against the truth, how many scans that see its ground it takes the object to leave
//! the map, and the changes reported on the first pass, where nothing changed.
//!
//! Every scan goes through the daemon's validation, local fit and the world aggregate's insert.

use super::drive::ScaleLearner;
use super::FamilyOptions;
use crate::scangen::to_message;
use anyhow::Result;
use nalgebra::{Isometry3, Vector3};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_proto::msg::Provenance;
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::aggregate::Aggregate;
use rangegp_service::map::LocalRangeMap;
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, level_pose, simulate_scan, Heightmap, ScannerPreset};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// The change part of `world.json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ChangeReport {
    /// Replaced cells that truly changed over those reported (appearance and removal pooled).
    pub precision: f64,
    /// Truly changed cells reported over those the passes saw.
    pub recall: f64,
    /// Cells reported replaced (appearance, removal).
    pub reported: [usize; 2],
    /// Of them, truly changed (height moved by more than 10 cm).
    pub true_positives: [usize; 2],
    /// Of them, truly unchanged (by less than 2 cm) and not touching a changed cell.
    pub false_positives: [usize; 2],
    /// Of them, not changed but touching a changed cell (the object's boundary at the grid's
    /// resolution: neither true nor false).
    pub boundary: [usize; 2],
    /// Truly changed cells the aggregate held before the pass, that the pass saw in at least
    /// the scans a change needs, and that were not reported.
    pub missed: [usize; 2],
    /// After the object left, the most scans that had seen one of its cells' ground by the scan
    /// after which that cell first stood no more than 10 cm above the ground (`None`: some cell
    /// still stood at the end of the pass).
    pub scans_to_clear: Option<usize>,
    /// The first definition: scans that saw any of the object's ground until none of it stood.
    /// It counts from the first scan that sees a near corner, which, 10 m off, cannot yet reach
    /// the far side (beyond the fusion reach): kept for comparison.
    pub scans_to_clear_any_view: Option<usize>,
    /// Cells reported replaced on the first pass, where nothing changed.
    pub static_changes: usize,
    /// Cells fused on the first pass.
    pub static_cells: usize,
    /// Each terrain and object, in words.
    pub cases: Vec<String>,
}

/// A cell whose true height moved by more than this changed, metres.
const CHANGED_M: f64 = 0.1;
/// A cell whose true height moved by less than this did not, metres.
const UNCHANGED_M: f64 = 0.02;

/// Runs the moving-object evaluation.
pub fn run_change(opts: &FamilyOptions) -> Result<ChangeReport> {
    // Objects: a car-sized box 0.5 m tall 4 m beside the path; a boulder-sized one 0.3 m tall
    // 6 m to the other side.
    let cases: &[(&str, Object)] = if opts.quick {
        &[
            ("fbm-h05-8deg", ((0.0, 4.0), [1.0, 0.8], 0.5)),
            ("fbm-h05-16deg", ((0.0, 4.0), [1.0, 0.8], 0.5)),
        ]
    } else {
        &[
            ("fbm-h05-8deg", ((0.0, 4.0), [1.0, 0.8], 0.5)),
            ("fbm-h05-8deg", ((2.0, -6.0), [0.4, 0.4], 0.3)),
            ("craters", ((0.0, 4.0), [1.0, 0.8], 0.5)),
            ("craters", ((2.0, -6.0), [0.4, 0.4], 0.3)),
            ("fbm-h05-16deg", ((0.0, 4.0), [1.0, 0.8], 0.5)),
            ("fbm-h05-16deg", ((2.0, -6.0), [0.4, 0.4], 0.3)),
        ]
    };
    let mut total = ChangeReport::default();
    for (name, object) in cases {
        let ground = family()
            .into_iter()
            .find(|t| t.name == *name)
            .map(|t| t.build(opts.seed, FAMILY_SIZE_M))
            .ok_or_else(|| anyhow::anyhow!("no {name} terrain"))?;
        let r = one_case(opts, &ground, *object)?;
        for p in 0..2 {
            total.reported[p] += r.reported[p];
            total.true_positives[p] += r.true_positives[p];
            total.false_positives[p] += r.false_positives[p];
            total.boundary[p] += r.boundary[p];
            total.missed[p] += r.missed[p];
        }
        total.static_changes += r.static_changes;
        total.static_cells += r.static_cells;
        // The slowest case counts; one that never cleared makes the whole `None`.
        let slowest = |all: Option<usize>, now: Option<usize>| match (total.cases.is_empty(), all, now) {
            (true, _, now) => now,
            (false, Some(a), Some(b)) => Some(a.max(b)),
            _ => None,
        };
        total.scans_to_clear = slowest(total.scans_to_clear, r.scans_to_clear);
        total.scans_to_clear_any_view = slowest(total.scans_to_clear_any_view, r.scans_to_clear_any_view);
        total.cases.push(format!(
            "{name}: box {:.1} × {:.1} × {:.1} m at ({:.0}, {:.0}): reported {:?}, true {:?}, false {:?}, missed {:?}, cleared after {:?} (any view: {:?})",
            2.0 * object.1[0], 2.0 * object.1[1], object.2, object.0 .0, object.0 .1,
            r.reported, r.true_positives, r.false_positives, r.missed, r.scans_to_clear, r.scans_to_clear_any_view
        ));
    }
    let tp: usize = total.true_positives.iter().sum();
    let fp: usize = total.false_positives.iter().sum();
    let missed: usize = total.missed.iter().sum();
    total.precision = tp as f64 / (tp + fp).max(1) as f64;
    total.recall = tp as f64 / (tp + missed).max(1) as f64;
    Ok(total)
}

/// An object: centre (x, y), half sides and height, metres.
type Object = ((f64, f64), [f64; 2], f64);

/// Three passes by one object on one terrain.
fn one_case(
    opts: &FamilyOptions,
    ground: &Heightmap,
    ((ox, oy), half, height): Object,
) -> Result<ChangeReport> {
    let object = ground.with_box(ox, oy, half, height);
    let preset = ScannerPreset::vlp16();
    let step = if opts.quick { 1.0 } else { 0.5 };
    let xs: Vec<f64> = (0..=((20.0 / step) as usize))
        .map(|k| -10.0 + k as f64 * step)
        .collect();
    let pass = |back: bool| -> Vec<Isometry3<f64>> {
        let heading = if back { std::f64::consts::PI } else { 0.0 };
        let order: Vec<f64> = if back {
            xs.iter().rev().copied().collect()
        } else {
            xs.clone()
        };
        order
            .iter()
            .map(|&x| level_pose(ground, x, 0.0, heading, preset.mount_height_m))
            .collect()
    };
    let passes = [
        (pass(false), ground),
        (pass(true), &object),
        (pass(false), ground),
    ];
    let params = WorldParams {
        change_detection: true,
        ..WorldParams::default()
    };
    let cell = params.cell_m;
    // The cells the object stands on (changed ones lie within 3 m of it).
    let near: Vec<(i32, i32)> = {
        let r = ((half[0].max(half[1]) + 3.0) / cell).ceil() as i32;
        let (ci, cj) = ((ox / cell).floor() as i32, (oy / cell).floor() as i32);
        (-r..=r)
            .flat_map(|di| (-r..=r).map(move |dj| (ci + di, cj + dj)))
            .collect()
    };
    let centre = |(i, j): (i32, i32)| ((i as f64 + 0.5) * cell, (j as f64 + 0.5) * cell);
    let moved = |c: (i32, i32)| {
        let (x, y) = centre(c);
        Some((object.height(x, y)? - ground.height(x, y)?).abs())
    };
    let positives: BTreeSet<(i32, i32)> = near
        .iter()
        .copied()
        .filter(|&c| moved(c).is_some_and(|d| d > CHANGED_M))
        .collect();
    let limits = ValidationLimits {
        max_future_ns: u64::MAX,
        ..opts.config.validation_limits()
    };
    let map_params = opts.config.map_params();
    let mut world = WorldAggregate::new(params);
    let mut scales = ScaleLearner::new(&opts.config);
    let mut report = ChangeReport::default();
    let mut sequence = 0u64;
    for (k, (poses, terrain)) in passes.iter().enumerate() {
        let fitted: Vec<_> = poses
            .par_iter()
            .enumerate()
            .map(|(i, pose)| -> Result<_> {
                let seed = opts.seed ^ ((k as u64) << 40) ^ ((i as u64) << 16) ^ 0xc4a;
                let rays = simulate_scan(*terrain, pose, &preset, &mut Pcg64::seed_from_u64(seed));
                let (mut header, points) = to_message(&preset, pose, &rays, 1_000 + i as u64);
                header.publisher_id = 1;
                header.sequence = sequence + i as u64 + 1;
                let input = validate(&header, &points, &limits, 0)
                    .map_err(|r| anyhow::anyhow!("scan rejected: {}", r.as_str()))?;
                let map = LocalRangeMap::fit(&input, &map_params)?;
                Ok((input, map))
            })
            .collect::<Result<_>>()?;
        sequence += poses.len() as u64;
        // The cells the aggregate holds as they stood before this pass: the ones that must change.
        let before = if k == 2 { &object } else { ground };
        let known_before: BTreeSet<(i32, i32)> = positives
            .iter()
            .copied()
            .filter(|&c| {
                let (x, y) = centre(c);
                let cell = world.cells().get(&c);
                cell.zip(before.height(x, y))
                    .is_some_and(|(cell, z)| (cell.z - z).abs() < CHANGED_M)
            })
            .collect();
        let mut seen = BTreeMap::<(i32, i32), usize>::new();
        let mut reported = BTreeSet::new();
        let cells_before = world.len();
        let mut clearing = 0usize;
        // Per cell of the object, the scans that had seen its ground when it first stood no more.
        let mut cleared_after = BTreeMap::<(i32, i32), usize>::new();
        let stands = |world: &WorldAggregate, c: (i32, i32)| {
            let (x, y) = centre(c);
            let g = ground.height(x, y).unwrap_or(f64::NEG_INFINITY);
            world.elevation(x, y).is_some_and(|e| e.z > g + CHANGED_M)
        };
        for (input, map) in fitted {
            let map = Arc::new(map);
            scales.observe(&input, Arc::clone(&map), &mut world);
            let (_, changes) = world.insert_all_within(&[(&input, map.as_ref())], params.max_reach_m)?;
            reported.extend(changes.iter().flatten().map(|c| c.cell));
            let mut sees_ground = false;
            for &c in &positives {
                let (x, y) = centre(c);
                let s = map.sensor_position();
                // Seen as the aggregate counts evidence for a change: among the scan's returns.
                let visible = (x - s.x).hypot(y - s.y) < params.max_reach_m
                    && map.elevation(x, y).is_some_and(|e| {
                        e.var <= params.max_cell_sd_m.powi(2)
                            && map.provenance(&Vector3::new(x, y, e.z)) == Provenance::Observed
                    });
                if visible {
                    *seen.entry(c).or_default() += 1;
                    sees_ground = true;
                }
            }
            if k != 2 {
                continue;
            }
            for &c in &positives {
                if !cleared_after.contains_key(&c) && !stands(&world, c) {
                    cleared_after.insert(c, seen.get(&c).copied().unwrap_or(0));
                }
            }
            if report.scans_to_clear_any_view.is_none() && sees_ground {
                clearing += 1;
                if !positives.iter().any(|&c| stands(&world, c)) {
                    report.scans_to_clear_any_view = Some(clearing);
                }
            }
        }
        if k == 2 && !positives.iter().any(|&c| stands(&world, c)) {
            report.scans_to_clear = cleared_after.values().max().copied();
        }
        if k == 0 {
            report.static_changes = reported.len();
            report.static_cells = world.len() - cells_before;
            continue;
        }
        let p = k - 1;
        report.reported[p] = reported.len();
        report.true_positives[p] = reported.intersection(&positives).count();
        // Anywhere, not only near the object: a change reported where nothing moved is false,
        // but for the cells touching the object's (a face's returns land on the cell boundary:
        // which side's cell holds them is the grid's resolution, not a detection).
        let touching =
            |(i, j): (i32, i32)| (-1..=1).any(|di| (-1..=1).any(|dj| positives.contains(&(i + di, j + dj))));
        report.false_positives[p] = reported
            .iter()
            .filter(|&&c| moved(c).is_none_or(|d| d < UNCHANGED_M) && !touching(c))
            .count();
        report.boundary[p] = reported
            .iter()
            .filter(|&&c| !positives.contains(&c) && touching(c))
            .count();
        report.missed[p] = known_before
            .iter()
            .filter(|c| !reported.contains(c))
            .filter(|c| {
                seen.get(c)
                    .is_some_and(|&n| n >= params.change_confirm_scans as usize)
            })
            .count();
    }
    Ok(report)
}
