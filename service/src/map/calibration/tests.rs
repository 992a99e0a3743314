use super::factors::scale_of;
use super::sample::{coprime_stride, patch_means, PATCH_RADIUS_M};
use super::*;
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use crate::map::aggregate::Aggregate;
use crate::map::scales::{BinScale, SIGMA_GROUPS};
use crate::map::test_support::{family_terrain, params, scan_by, scan_of};
use crate::map::Window;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use rangegp_sim::Heightmap;
use std::sync::Arc;

/// The seed-000 scanner 0.75 m above flat ground, at `x` along the track.
fn scan_over_flat(x: f64, sequence: u64) -> ScanInput {
    let terrain = Heightmap::flat(40.0, 0.05, 0.0);
    let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.75), UnitQuaternion::identity());
    let mut scan = scan_of(&terrain, pose);
    scan.sequence = sequence;
    scan
}

/// Share of `probes` whose true height lies within 1.96 σ of the snapshot's answer.
fn coverage95(snapshot: &MapSnapshot, terrain: &Heightmap, probes: &[[f64; 2]]) -> f64 {
    let hits: Vec<bool> = probes
        .iter()
        .filter_map(|&[x, y]| {
            let e = query::elevation(snapshot, x, y);
            let (z, var) = (e.z_m?, e.z_var_m2?);
            Some((z - terrain.height(x, y)?).abs() <= 1.96 * var.sqrt())
        })
        .collect();
    assert!(
        hits.len() > probes.len() / 2,
        "only {} of {} answered",
        hits.len(),
        probes.len()
    );
    hits.iter().filter(|&&h| h).count() as f64 / hits.len() as f64
}

#[test]
fn on_rough_terrain_the_next_scans_teach_a_sigma_that_covers_the_truth() {
    // Rough fBm relief (p95 slope 16°) and maps without their own leave-one-out calibration:
    // their σ is the kernel's, far too sure of this ground.
    let terrain = family_terrain("fbm-h05-16deg", 7, 40.0);
    let preset = rangegp_sim::ScannerPreset::seed000();
    let path = rangegp_sim::Path::wander(3, &terrain, 12, 0.5, 0.2);
    let mut window = Window::new(16);
    let mut calibrator = Calibrator::new(true);
    let mut snapshot = MapSnapshot::default();
    for i in 0..12 {
        let mut scan = scan_of(&terrain, path.pose(&terrain, i, preset.mount_height_m));
        scan.sequence = i as u64 + 1;
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        calibrator.observe(&snapshot, &scan, &map);
        window.push(Arc::new(map));
        snapshot = window.snapshot().with_scales(calibrator.scales());
    }
    // Probes 1–8 m ahead of and beside the last pose, inside the forward field of view.
    let last = path.pose(&terrain, 11, preset.mount_height_m);
    let probes: Vec<[f64; 2]> = (0..400)
        .map(|k| {
            let r = 1.0 + 7.0 * ((k * 37) % 400) as f64 / 400.0;
            let a = -1.2 + 2.4 * ((k * 53) % 400) as f64 / 400.0;
            let p = last * nalgebra::Point3::new(r * a.cos(), r * a.sin(), 0.0);
            [p.x, p.y]
        })
        .collect();
    let raw = coverage95(&window.snapshot(), &terrain, &probes);
    let calibrated = coverage95(&snapshot, &terrain, &probes);
    assert!(
        raw < 0.8,
        "the raw σ already covers {raw:.3}: the test proves nothing"
    );
    assert!(
        calibrated > 0.88,
        "calibrated coverage {calibrated:.3} (raw {raw:.3})"
    );
    let (window_counts, _) = calibrator.counts();
    assert!(window_counts.iter().sum::<usize>() >= 3 * MIN_RESIDUALS);
}

#[test]
fn before_the_first_map_nothing_is_learnt() {
    let mut calibrator = Calibrator::new(true);
    let scan = scan_over_flat(0.0, 1);
    let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
    assert_eq!(calibrator.observe(&MapSnapshot::default(), &scan, &map), 0);
    let nothing = SigmaScales {
        relief_in_heights: true,
        view_disagreement: DEFAULT_VIEW_DISAGREEMENT,
        ..SigmaScales::default()
    };
    assert_eq!(calibrator.scales(), nothing);
}

#[test]
fn a_return_tests_a_map_from_farther_where_one_answers_else_the_nearest() {
    // A creeping robot: its returns land on the nearest map's rings and would teach σ too
    // narrow for the ground between them, so a map from farther is tested where it answers.
    let map_at = |x: f64, sequence: u64| {
        let scan = scan_over_flat(x, sequence);
        Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit"))
    };
    let mut window = Window::new(16);
    window.push(map_at(-1.0, 1));
    window.push(map_at(-0.1, 2));
    let snapshot = window.snapshot();
    let sensor = Vector3::new(0.0, 0.0, 0.75);
    let (x, y) = (3.0, 0.5);
    let own = query::raw_elevation(&snapshot, x, y).expect("answered");
    assert_eq!(own.by, Answerer::Window(0), "the query takes the map from -0.1 m");
    let tested = primary_answer(&snapshot, &sensor, x, y).expect("tested");
    assert_eq!(tested.by, Answerer::Window(1), "the map from -1 m is tested");
    assert!((tested.rho_m - (x + 1.0).hypot(y)).abs() < 1e-9);
    // Standing still with no map from farther: the nearest is tested (its σ at its own rings
    // still shows what the map claims too surely there).
    let mut still = Window::new(16);
    still.push(map_at(-0.1, 2));
    let tested = primary_answer(&still.snapshot(), &sensor, x, y).expect("tested");
    assert_eq!(tested.by, Answerer::Window(0));
}

#[test]
fn observing_a_scan_learns_from_a_map_that_looked_from_farther_where_one_answers() {
    // A map fitted 1 m back over ground 5 cm higher than the ground now scanned, and an exact
    // map 0.1 m back. The scan's returns must test the first: the robot stands beside the
    // second, on its rings.
    let fit = |ground_z: f64, x: f64, sequence: u64| {
        let terrain = Heightmap::flat(40.0, 0.05, ground_z);
        let pose = Isometry3::from_parts(
            Translation3::new(x, 0.0, 0.75 + ground_z),
            UnitQuaternion::identity(),
        );
        let mut scan = scan_of(&terrain, pose);
        scan.sequence = sequence;
        Arc::new(LocalRangeMap::fit(&scan, &params()).expect("fit"))
    };
    let sd_after_one_scan = |biased_back_m: f64| {
        let mut window = Window::new(16);
        window.push(fit(0.05, -biased_back_m, 1));
        window.push(fit(0.0, -0.1, 2));
        let snapshot = window.snapshot();
        let scan = scan_over_flat(0.0, 3);
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        let mut calibrator = Calibrator::new(false);
        let answered = calibrator.observe(&snapshot, &scan, &map);
        assert!(answered >= MIN_RESIDUALS, "{answered} returns answered");
        let a = query::raw_elevation(&snapshot, 5.0, 0.5).expect("answered");
        assert_eq!(
            a.by,
            Answerer::Window(0),
            "queries take the exact map beside the robot"
        );
        calibrator
            .scales()
            .calibrate(Source::Window, a.rho_m, &a.estimate)
            .var_m2
            .sqrt()
    };
    let from_farther = sd_after_one_scan(1.0);
    let beside = sd_after_one_scan(0.3);
    assert!(
        from_farther > 0.02,
        "the map 1 m back errs by 5 cm, σ {from_farther}"
    );
    assert!(
        beside < 0.25 * from_farther,
        "no map lay 0.5 m back: the nearest is tested, σ {beside} against {from_farther}"
    );
}

#[test]
fn an_empty_cell_takes_its_nearest_learnt_neighbours_scales() {
    let mut residuals = Residuals::default();
    let r = |sd: f64| error_of(sd, 1e-6);
    // Only range bins 1 and 4 of the last class of level ground have residuals: errors 2 mm
    // and 20 mm.
    residuals[LEVEL][CLASSES - 1][1] = (0..200)
        .map(|i| r(0.002 * (1.0 + (i % 7) as f64 / 7.0)))
        .collect();
    residuals[LEVEL][CLASSES - 1][4] = (0..200).map(|i| r(0.02 * (1.0 + (i % 7) as f64 / 7.0))).collect();
    let table = table_of(&residuals, None).0;
    let f = |c: usize, b: usize| table[LEVEL][c][b].factor(1e-3);
    assert_eq!(f(CLASSES - 1, 0), f(CLASSES - 1, 1), "bin 0 from bin 1");
    assert_eq!(f(CLASSES - 1, 6), f(CLASSES - 1, 4), "bin 6 from bin 4");
    // Bins 2 and 3 lie between: 2 is nearer 1, and 3 nearer 4.
    assert_eq!(f(CLASSES - 1, 2), f(CLASSES - 1, 1));
    assert_eq!(f(CLASSES - 1, 3), f(CLASSES - 1, 4));
    // Classes with no residuals at all copy the nearest class, and levels the nearest level.
    assert_eq!(table[LEVEL][0], table[LEVEL][CLASSES - 1]);
    assert_eq!(table[0], table[LEVEL]);
    assert_eq!(table[LEVELS - 1], table[LEVEL]);
    assert!(f(CLASSES - 1, 4) > 5.0 * f(CLASSES - 1, 1));
}

/// A prior table of factors 1 with no cell learnt, to be filled in.
fn empty_prior() -> (ScaleTable, crate::map::scales::CellFlags) {
    (Default::default(), Default::default())
}

/// Scales of `s` for every σ group.
fn scale(s: f64) -> BinScale {
    BinScale {
        scale: [s; SIGMA_GROUPS],
        ..BinScale::default()
    }
}

#[test]
fn a_cell_the_prior_learnt_keeps_its_scales_one_it_filled_is_filled_again() {
    let mut residuals = Residuals::default();
    let last = CLASSES - 1;
    // Now: range bin 3 learns errors of 2 mm against answers of 1 mm (a scale of about 2).
    residuals[LEVEL][last][3] = (0..200)
        .map(|i| error_of(0.002 * (0.5 + (i % 7) as f64 / 6.0), 1e-6))
        .collect();
    // Before the restart: bin 5 learnt a scale of 7; bin 1 had only been filled, with 9.
    let (mut prior, mut flags) = empty_prior();
    for level in 0..LEVELS {
        prior[level][last][5] = scale(7.0);
        prior[level][last][1] = scale(9.0);
        flags[level][last][5] = true;
    }
    let (table, learnt) = table_of(&residuals, Some((&prior, &flags)));
    let f = |b: usize| table[LEVEL][last][b].factor(1e-3);
    assert_eq!(f(5), 7.0, "learnt before: kept");
    assert_eq!(f(6), 7.0, "filled from the prior's learnt cell");
    assert_eq!(f(1), f(3), "filled before: filled again from what is learnt now");
    assert!((f(3) - 7.0).abs() > 2.0 && (f(3) - 9.0).abs() > 2.0);
    assert!(learnt[LEVEL][last][3] && learnt[LEVEL][last][5] && !learnt[LEVEL][last][1]);
    // Without the prior, bin 5 would be filled from bin 3.
    let (fresh, fresh_learnt) = table_of(&residuals, None);
    assert_eq!(fresh[LEVEL][last][5].factor(1e-3), f(3));
    assert!(!fresh_learnt[LEVEL][last][5]);
    // Departure weights alike: bin 6 kept, bin 0 filled from the nearest learnt.
    let mut weights = [0.0; BINS];
    weights[6] = 1.0;
    weights[0] = 0.25;
    let mut learnt_weights = [false; BINS];
    learnt_weights[6] = true;
    let (w, w_learnt) = departure_weights_of(&Residuals::default(), Some((&weights, &learnt_weights)));
    assert_eq!(w, [1.0; BINS]);
    assert_eq!(w_learnt, learnt_weights);
}

#[test]
fn a_prior_cell_of_a_class_not_split_by_level_counts_at_level_ground_only() {
    let last = CLASSES - 1;
    let shadow = 0;
    assert!(split_by_level(last) && !split_by_level(shadow));
    // The prior learnt the near-shadow class at level ground (scale 2), copied to every level,
    // but an off-level row of it holds a stale 9 that must not count.
    let (mut prior, mut flags) = empty_prior();
    for l in 0..LEVELS {
        prior[l][shadow][3] = scale(if l == LEVEL { 2.0 } else { 9.0 });
        flags[l][shadow][3] = true;
    }
    // Now: only the split class at level ground is learnt.
    let mut held = Residuals::default();
    held[LEVEL][last][3] = residuals(3e-3, 1e-6, 300)
        .into_iter()
        .enumerate()
        .map(|(i, r)| Residual { scan: i as u64, ..r })
        .collect();
    let (table, learnt) = table_of(&held, Some((&prior, &flags)));
    for l in 0..LEVELS {
        assert_eq!(
            table[l][shadow][3].factor(1e-3),
            2.0,
            "level {l}: level ground's prior"
        );
        assert!(learnt[l][shadow][3]);
        // The split class off level ground has nothing of its own: it takes the nearest
        // level's, not a fill from the stale near-shadow row.
        assert_eq!(table[l][last], table[LEVEL][last], "level {l}");
    }
}

#[test]
fn a_cell_narrows_sigma_only_on_residuals_from_several_scans_but_widens_at_once() {
    let last = CLASSES - 1;
    // Errors a third of σ (narrow it) in bin 2, three times σ (widen it) in bin 4, 300 of each
    // spread over `scans` scans.
    let table = |scans: u64| {
        let mut held = Residuals::default();
        for (b, ratio) in [(2, 1.0 / 3.0), (4, 3.0)] {
            held[LEVEL][last][b] = residuals(ratio * 1e-3, 1e-6, 300)
                .into_iter()
                .enumerate()
                .map(|(i, r)| Residual {
                    scan: i as u64 * scans / 300,
                    ..r
                })
                .collect();
        }
        let t = table_of(&held, None).0;
        (t[LEVEL][last][2].factor(1e-3), t[LEVEL][last][4].factor(1e-3))
    };
    let (narrow_few, wide_few) = table(MIN_SCANS_TO_NARROW as u64 - 1);
    let (narrow_many, wide_many) = table(MIN_SCANS_TO_NARROW as u64);
    assert_eq!(narrow_few, 1.0, "too few scans to narrow");
    assert!(narrow_many < 0.5, "{narrow_many}");
    assert!(wide_few > 2.5 && wide_few == wide_many, "{wide_few} {wide_many}");
}

#[test]
fn ground_off_the_robots_level_gets_scales_of_its_own_away_from_shadows() {
    let r = |sd: f64| error_of(sd, 1e-4);
    let errors =
        |sd: f64| -> VecDeque<Residual> { (0..300).map(|i| r(sd * (0.2 + (i % 9) as f64 / 4.0))).collect() };
    let mut residuals = Residuals::default();
    // 20–40 m: level ground errs by about 1 cm, ground below the robot's level by 10 cm.
    residuals[LEVEL][CLASSES - 1][4] = errors(0.01);
    residuals[0][CLASSES - 1][4] = errors(0.1);
    residuals[LEVEL][0][4] = errors(0.01);
    let table = table_of(&residuals, None).0;
    let f = |l: usize, c: usize| table[l][c][4].factor(1e-2);
    assert!(
        f(0, CLASSES - 1) > 5.0 * f(LEVEL, CLASSES - 1),
        "below the robot's level: wider"
    );
    // A level with no residuals takes the nearest level's (level ground above it), and near a
    // shadow the level is not told apart.
    assert_eq!(table[LEVELS - 1][CLASSES - 1], table[LEVEL][CLASSES - 1]);
    assert_eq!(table[0][0], table[LEVEL][0]);
    assert!(split_by_level(CLASSES - 1) && !split_by_level(0));
    assert_eq!(level_of(-0.05), 0);
    assert_eq!(level_of(0.0), LEVEL);
    assert_eq!(level_of(0.05), LEVELS - 1);
}

#[test]
fn a_bin_whose_errors_follow_the_departure_from_the_data_weighs_it_and_one_whose_errors_do_not_does_not() {
    // Gaussian quantiles: errors of σ 1 mm, except that where an answer departs from its data
    // by d the error has σ d (half the answers depart 1 mm, the others 1–30 cm).
    let n = 2000;
    let departed = |error_sd: &dyn Fn(f64) -> f64| -> VecDeque<Residual> {
        (0..n)
            .map(|i| {
                let d = if i % 2 == 0 {
                    1e-3
                } else {
                    0.01 * (1 + i % 30) as f64
                };
                let z = distrs::Normal::ppf(((i * 7919) % n) as f64 / n as f64 + 0.5 / n as f64, 0.0, 1.0);
                Residual {
                    dep2: d * d,
                    scan: i as u64,
                    ..error_of(z * error_sd(d), 1e-6)
                }
            })
            .collect()
    };
    let mut residuals = Residuals::default();
    residuals[LEVEL][CLASSES - 1][2] = departed(&|d| d.max(1e-3));
    // Range bin 5: the same departures, but every error of σ 1 mm.
    residuals[LEVEL][CLASSES - 1][5] = departed(&|_| 1e-3);
    let weights = departure_weights_of(&residuals, None).0;
    assert!(weights[2] >= 0.25, "{weights:?}");
    assert_eq!(weights[5], 0.0, "{weights:?}");
    // Bins without residuals take their nearest neighbour's.
    assert_eq!(weights[0], weights[2]);
    assert_eq!(weights[6], weights[5]);
    // And the weight enters the variances the scales are fitted to.
    let with = with_departure(&residuals, &weights);
    let r = with[LEVEL][CLASSES - 1][2][1];
    assert!((r.var - (1e-6 + weights[2] * residuals[LEVEL][CLASSES - 1][2][1].dep2)).abs() < 1e-12);
}

/// A residual of `error_m` against an answer of variance `var`, from a noiseless return of unit
/// weight.
fn error_of(error_m: f64, var: f64) -> Residual {
    Residual {
        r2: error_m * error_m,
        var,
        noise_var: 0.0,
        weight: 1.0,
        ..Residual::default()
    }
}

fn residuals(sd: f64, var: f64, n: usize) -> Vec<Residual> {
    // Deterministic standard normal quantiles: an exactly Gaussian sample.
    (0..n)
        .map(|i| {
            let u = (i as f64 + 0.5) / n as f64;
            let z = distrs::Normal::ppf(u, 0.0, 1.0);
            Residual {
                r2: (sd * z).powi(2),
                var,
                noise_var: 0.0,
                weight: 1.0,
                ..Residual::default()
            }
        })
        .collect()
}

#[test]
fn a_gaussian_error_three_times_the_claimed_sigma_gets_a_scale_of_three() {
    let r = residuals(0.03, 0.01 * 0.01, 1000);
    let s = scale_of(&r);
    assert!((s - 3.0).abs() < 0.05, "scale {s}");
}

#[test]
fn the_returns_own_noise_is_not_charged_to_the_map() {
    let mut r = residuals(0.05, 0.03 * 0.03, 1000);
    for x in &mut r {
        x.noise_var = 0.04 * 0.04;
    }
    // 0.05² = 0.03² + 0.04²: the map's σ was right.
    let s = scale_of(&r);
    assert!((s - 1.0).abs() < 0.05, "scale {s}");
}

#[test]
fn returns_noisier_than_the_map_widen_its_sigma_but_never_narrow_it() {
    // 3 cm returns against a map claiming 5 mm whose errors are 2 mm: the residuals are the
    // returns' noise; no scale below 1 is shown by them.
    let mut r = residuals(0.0301, 0.005 * 0.005, 1000);
    for x in &mut r {
        x.noise_var = 0.03 * 0.03;
    }
    assert_eq!(scale_of(&r), 1.0);
    // The same returns against a map whose errors are 6 cm (claiming 5 mm): widened.
    let mut r = residuals(0.067, 0.005 * 0.005, 1000);
    for x in &mut r {
        x.noise_var = 0.03 * 0.03;
    }
    let s = scale_of(&r);
    assert!((s - 12.0).abs() < 0.6, "scale {s}");
}

#[test]
fn weights_that_sum_to_nothing_fall_back_to_counts() {
    let mut r = residuals(0.03, 0.01 * 0.01, 1000);
    for x in &mut r {
        x.weight = 0.0;
    }
    let s = scale_of(&r);
    assert!((s - 3.0).abs() < 0.05, "scale {s}");
}

#[test]
fn few_residuals_leave_the_scale_at_one() {
    assert_eq!(scale_of(&residuals(1.0, 1e-6, MIN_RESIDUALS - 1)), 1.0);
}

#[test]
fn bins_double_in_width() {
    assert_eq!(bin_of(0.0), 0);
    assert_eq!(bin_of(2.4), 0);
    assert_eq!(bin_of(2.5), 1);
    assert_eq!(bin_of(39.0), 4);
    assert_eq!(bin_of(500.0), BINS - 1);
}

#[test]
fn the_stride_visits_every_index() {
    for n in [1, 2, 10, 64, 1000, 65_536] {
        let s = coprime_stride(n);
        let mut seen = vec![false; n];
        let mut k = 0;
        for _ in 0..n {
            seen[k] = true;
            k = (k + s) % n;
        }
        assert!(seen.iter().all(|&v| v), "n {n}");
    }
}

#[test]
fn the_aggregate_is_tested_where_a_window_map_answers_too() {
    let first = scan_over_flat(-1.0, 1);
    let map = Arc::new(LocalRangeMap::fit(&first, &params()).expect("fit"));
    let mut aggregate = WorldAggregate::new(WorldParams::default());
    aggregate.insert(&first, &map).expect("insert");
    let mut window = Window::new(16);
    window.push(map);
    let scan = scan_over_flat(0.0, 2);
    let next = LocalRangeMap::fit(&scan, &params()).expect("fit");
    let tested = |snapshot: &MapSnapshot| {
        let mut calibrator = Calibrator::new(false);
        calibrator.observe(snapshot, &scan, &next);
        let (window, aggregate) = calibrator.counts();
        (window.iter().sum::<usize>(), aggregate.iter().sum::<usize>())
    };
    let mut snapshot = window.snapshot();
    assert_eq!(tested(&snapshot).1, 0, "no aggregate, nothing to test");
    snapshot.aggregate = Some(Arc::new(aggregate));
    let (by_window, by_aggregate) = tested(&snapshot);
    assert!(by_window >= MIN_RESIDUALS, "{by_window} window residuals");
    assert!(
        by_aggregate >= by_window / 2,
        "{by_aggregate} aggregate residuals against {by_window} of the window"
    );
}

#[test]
fn a_restarted_calibrator_keeps_each_learnt_part_until_it_has_relearnt_it() {
    let terrain = family_terrain("fbm-h05-16deg", 7, 40.0);
    let preset = rangegp_sim::ScannerPreset::seed000();
    let path = rangegp_sim::Path::wander(3, &terrain, 18, 0.5, 0.2);
    let scan_at = |i: usize| {
        let mut scan = scan_of(&terrain, path.pose(&terrain, i, preset.mount_height_m));
        scan.sequence = i as u64 + 1;
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        (scan, map)
    };
    let mut before = Calibrator::new(true);
    let mut window = Window::new(16);
    let mut snapshot = MapSnapshot::default();
    for i in 0..12 {
        let (scan, map) = scan_at(i);
        before.observe(&snapshot, &scan, &map);
        window.push(Arc::new(map));
        snapshot = window.snapshot().with_scales(before.scales());
    }
    let prior = before.scales();
    assert!(
        before.correlation.learnt().is_some(),
        "the premise: a correlation was learnt"
    );
    let mut restarted = Calibrator::new(true).with_prior(prior);
    assert_eq!(
        restarted.scales(),
        prior,
        "a restarted daemon answers with the scales it had"
    );
    // After the restart the window is empty: the first scan tests nothing, the next ones the
    // maps since, and only some cells then hold enough residuals.
    let mut fresh = Calibrator::new(true);
    let mut window = Window::new(16);
    let mut snapshot = MapSnapshot::default();
    let (mut kept, mut relearnt, mut dropped, mut fresh_differs) = (0, 0, 0, 0);
    for i in 12..18 {
        let (scan, map) = scan_at(i);
        let answered = restarted.observe(&snapshot.clone().with_scales(restarted.scales()), &scan, &map);
        fresh.observe(&snapshot.clone().with_scales(fresh.scales()), &scan, &map);
        window.push(Arc::new(map));
        snapshot = window.snapshot();
        if answered == 0 {
            continue;
        }
        // Every cell: relearnt from its own residuals, or the prior's while its range bin's
        // departure weight is the prior's, or no longer counted learnt.
        let (now, fresh_now) = (restarted.scales(), fresh.scales());
        for l in 0..LEVELS {
            for c in 0..CLASSES {
                let own = if split_by_level(c) { l } else { LEVEL };
                for b in 0..BINS {
                    if restarted.window[own][c][b].len() >= MIN_RESIDUALS {
                        relearnt += 1;
                        assert!(now.learnt.window[l][c][b]);
                    } else if !prior.learnt.window[l][c][b] {
                        continue;
                    } else if now.departure[b] == prior.departure[b] {
                        assert_eq!(now.window[l][c][b], prior.window[l][c][b], "cell {l} {c} {b}");
                        assert!(now.learnt.window[l][c][b]);
                        kept += 1;
                        fresh_differs += usize::from(fresh_now.window[l][c][b] != prior.window[l][c][b]);
                    } else {
                        assert!(!now.learnt.window[l][c][b], "cell {l} {c} {b}");
                        dropped += 1;
                    }
                }
            }
        }
    }
    assert!(
        kept > 0 && relearnt > 0 && dropped > 0,
        "kept {kept}, relearnt {relearnt}, dropped {dropped}"
    );
    assert!(
        fresh_differs > 0,
        "the premise: a calibrator without the prior fills those cells otherwise"
    );
    let (now, fresh_now) = (restarted.scales(), fresh.scales());
    assert!(restarted.correlation.learnt().is_none());
    assert!(prior.learnt.correlation && now.learnt.correlation);
    assert_eq!(now.correlation, prior.correlation);
    assert_ne!(fresh_now.correlation, prior.correlation);
}

/// Every `every`-th return of `scan` whose horizontal distance from the sensor lies in `band`
/// (metres), as the sampler gives them: map point, noise variance along z, weight 1.
fn returns_in(scan: &ScanInput, band: (f64, f64), every: usize) -> Vec<Sampled> {
    let origin = scan.pose.translation.vector;
    scan.rays
        .iter()
        .filter_map(|ray| {
            let (p, noise_var) = map_return(scan, ray);
            let rho = (p.x - origin.x).hypot(p.y - origin.y);
            (band.0..band.1).contains(&rho).then_some((p, noise_var, 1.0))
        })
        .step_by(every)
        .collect()
}

/// An OS1-64 with its device's noise, 0.75 m above `terrain` at the origin.
fn os1_64_scan(terrain: &Heightmap) -> ScanInput {
    let preset = rangegp_sim::ScannerPreset::os1_64(1024).with_device_noise();
    scan_by(&preset, terrain, Isometry3::translation(0.0, 0.0, 0.75))
}

#[test]
fn a_patch_mean_has_a_fraction_of_a_returns_noise_and_claims_no_less_than_it_has() {
    let terrain = Heightmap::flat(40.0, 0.05, 0.0);
    let scan = os1_64_scan(&terrain);
    let singles = returns_in(&scan, (2.0, 8.0), 37);
    assert!(singles.len() > 300, "{} returns", singles.len());
    let mut means = singles.clone();
    patch_means(&scan, &mut means);
    // Mean claimed noise variance, and mean square height.
    let claimed = |v: &[Sampled]| v.iter().map(|r| r.1).sum::<f64>() / v.len() as f64;
    let found = |v: &[Sampled]| v.iter().map(|r| r.0.z * r.0.z).sum::<f64>() / v.len() as f64;
    // The ground is at 0: a return's height is its noise.
    assert!(
        claimed(&means) < claimed(&singles) / 3.0,
        "{} against {}",
        claimed(&means),
        claimed(&singles)
    );
    for (v, what) in [(&singles, "single returns"), (&means, "patch means")] {
        let ratio = found(v) / claimed(v);
        assert!(
            (0.7..1.4).contains(&ratio),
            "{what}: mean square {ratio} × the noise claimed"
        );
    }
    assert!(means
        .iter()
        .zip(&singles)
        .all(|(m, s)| (m.0.xy() - s.0.xy()).norm() <= PATCH_RADIUS_M));
}

#[test]
fn a_patch_at_a_step_keeps_its_returns_side() {
    // A box 0.3 m high whose face stands 2.5 m in front of the sensor: the ground at its foot and
    // the face above it lie within a patch of each other.
    let terrain = Heightmap::flat(40.0, 0.05, 0.0).with_box(3.0, 0.0, [0.5, 2.0], 0.3);
    let scan = os1_64_scan(&terrain);
    let foot: Vec<_> = returns_in(&scan, (2.0, 3.0), 1)
        .into_iter()
        .filter(|(p, _, _)| p.x > 2.5 - PATCH_RADIUS_M && p.x < 2.49 && p.y.abs() < 1.5 && p.z < 0.02)
        .collect();
    assert!(foot.len() > 20, "{} returns at the foot", foot.len());
    // The face's returns lie within a patch of the foot's: a mean over every return within
    // the radius would rise well above the ground.
    let all = returns_in(&scan, (2.0, 3.0), 1);
    let unguarded = foot
        .iter()
        .map(|(p, _, _)| {
            let within: Vec<f64> = all
                .iter()
                .filter(|(q, _, _)| (q.xy() - p.xy()).norm() <= PATCH_RADIUS_M)
                .map(|(q, _, _)| q.z)
                .collect();
            within.iter().sum::<f64>() / within.len() as f64
        })
        .fold(f64::MIN, f64::max);
    assert!(
        unguarded > 0.1,
        "the face reaches no patch at its foot ({unguarded} m)"
    );
    let mut means = foot.clone();
    patch_means(&scan, &mut means);
    // Within the radius plus three noise σ of both returns (about 3 cm here) of its side.
    let worst = means.iter().map(|(p, _, _)| p.z).fold(f64::MIN, f64::max);
    assert!(worst < 0.08, "a patch at the foot of the face rose to {worst} m");
}
