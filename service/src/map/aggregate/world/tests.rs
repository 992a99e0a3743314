use super::*;
use crate::map::test_support::{params, scan_of};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rangegp_proto::msg::Provenance;
use rangegp_sim::Heightmap;

/// Fits the seed-000 scanner's scan of `terrain` from (x, y) at `heading` and folds it in.
pub(super) fn fold(agg: &mut WorldAggregate, terrain: &Heightmap, x: f64, y: f64, heading: f64) {
    let pose = Isometry3::from_parts(
        Translation3::new(x, y, 0.75),
        UnitQuaternion::from_euler_angles(0.0, 0.0, heading),
    );
    let scan = scan_of(terrain, pose);
    let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
    agg.insert(&scan, &local).expect("insert");
}

/// An aggregate whose cells are exactly a flat 4 m × 4 m block at height 0.2 m, cells
/// (0..16, 0..16) of 0.25 m.
fn block() -> WorldAggregate {
    let cells = (0..16)
        .flat_map(|i| {
            (0..16).map(move |j| {
                (
                    (i, j),
                    Cell {
                        z: 0.2,
                        var: 1e-4,
                        scans: 1,
                    },
                )
            })
        })
        .collect();
    WorldAggregate::from_state(WorldState {
        params: WorldParams::default(),
        cells,
        inserts: 1,
        history: Vec::new(),
        views: Vec::new(),
        seen: Vec::new(),
    })
    .expect("refit")
}

#[test]
fn a_scan_from_where_the_last_stood_adds_nothing_and_a_near_one_adds_its_share() {
    let terrain = Heightmap::flat(40.0, 0.05, 0.0);
    let mut agg = WorldAggregate::new(WorldParams::default());
    fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
    let first = agg.cells().clone();
    // Standing still: the same view again leaves every cell as it was.
    fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
    assert_eq!(agg.cells(), &first);
    // Creeping by less than the least share a scan: nothing until the distance from the last
    // view that counted reaches it.
    let creep = 0.4 * MIN_VIEW_SHARE * INDEPENDENT_VIEW_M;
    fold(&mut agg, &terrain, creep, 0.0, 0.0);
    fold(&mut agg, &terrain, 2.0 * creep, 0.0, 0.0);
    assert_eq!(
        agg.cells()
            .iter()
            .filter(|(c, cell)| first.get(c) == Some(cell))
            .count(),
        first.len()
    );
    fold(&mut agg, &terrain, 3.0 * creep, 0.0, 0.0);
    assert!(agg
        .cells()
        .iter()
        .any(|(c, cell)| first.get(c).is_some_and(|f| f != cell)));
    let first = agg.cells().clone();
    let fold_at = |agg: &mut WorldAggregate, x: f64| fold(agg, &terrain, 3.0 * creep + x, 0.0, 0.0);
    // A quarter of the independent distance on: cells seen before take its height at a quarter
    // of its weight (every view of flat ground gives about the same variance), new cells in full.
    fold_at(&mut agg, 0.25 * INDEPENDENT_VIEW_M);
    let (mut narrowed, mut new) = (Vec::new(), 0);
    for (c, cell) in agg.cells() {
        match first.get(c) {
            Some(before) => narrowed.push(cell.var / before.var),
            None => new += 1,
        }
    }
    narrowed.sort_by(f64::total_cmp);
    let median = narrowed[narrowed.len() / 2];
    // Two independent views would halve it (0.5); a quarter of one leaves 1 / 1.25.
    assert!((0.75..0.9).contains(&median), "variance ratio {median}");
    assert!(new > 0, "the step uncovers new cells");
    // A scan an independent distance away counts in full.
    let mut far = WorldAggregate::new(WorldParams::default());
    fold(&mut far, &terrain, 0.0, 0.0, 0.0);
    let before = far.cells().clone();
    fold(&mut far, &terrain, INDEPENDENT_VIEW_M, 0.0, 0.0);
    let mut ratios: Vec<f64> = far
        .cells()
        .iter()
        .filter_map(|(c, cell)| Some(cell.var / before.get(c)?.var))
        .collect();
    ratios.sort_by(f64::total_cmp);
    let median = ratios[ratios.len() / 2];
    assert!((0.4..0.6).contains(&median), "variance ratio {median}");
}

#[test]
fn the_ring_search_finds_the_nearest_cell_of_the_whole_square() {
    let mut agg = block();
    // Holes and an outlier, so the nearest cell is not always the one underneath.
    agg.cells.retain(|&(i, j), _| (i + 2 * j) % 5 != 0);
    let reach = (agg.params.max_gap_m / agg.params.cell_m).ceil() as i32;
    let brute = |x: f64, y: f64| {
        let (ci, cj) = agg.cell_of(x, y);
        let mut nearest = f64::INFINITY;
        for di in -reach..=reach {
            for dj in -reach..=reach {
                if agg.cells.contains_key(&(ci + di, cj + dj)) {
                    let (cx, cy) = agg.centre((ci + di, cj + dj));
                    nearest = nearest.min((cx - x).hypot(cy - y));
                }
            }
        }
        (nearest <= agg.params.max_gap_m).then_some(nearest)
    };
    let mut rng = rand_pcg::Pcg64::new(11, 3);
    for _ in 0..2000 {
        use rand::Rng;
        let (x, y) = (rng.random_range(-1.5..5.5), rng.random_range(-1.5..5.5));
        assert_eq!(agg.nearest_cell(x, y), brute(x, y), "at ({x}, {y})");
    }
}

#[test]
fn provenance_follows_the_distance_to_the_nearest_fused_cell() {
    let agg = block();
    let at = |x: f64, y: f64| agg.elevation(x, y).map(|_| agg.provenance(x, y));
    // On a cell centre, and at a cell corner (0.18 m from four centres, within 0.3 ℓ).
    assert_eq!(at(2.125, 2.125), Some(Provenance::Observed));
    assert_eq!(at(2.0, 2.0), Some(Provenance::Observed));
    // Beyond the block's edge (the last centres are at 3.875 m): 0.25 m out is interpolated,
    // 0.35 m out lies beyond the gap the aggregate answers across (half its experts' length
    // scale), so it is never asked to extrapolate.
    assert_eq!(at(4.125, 2.125), Some(Provenance::Interpolated));
    assert_eq!(at(4.225, 2.125), None);
    let wide = WorldAggregate::from_state(WorldState {
        params: WorldParams {
            max_gap_m: 0.75,
            ..WorldParams::default()
        },
        ..agg.state()
    })
    .expect("refit");
    assert_eq!(
        wide.elevation(4.575, 2.125)
            .map(|_| wide.provenance(4.575, 2.125)),
        Some(Provenance::Extrapolated)
    );
    let e = agg.elevation(2.125, 2.125).expect("inside");
    assert!((e.z - 0.2).abs() < 1e-3 && e.point_sd == [0.0, 0.0, e.var.sqrt()]);
}

#[test]
fn a_ray_meets_the_surface_across_a_gap_too_wide_to_answer_a_height_in() {
    // The block without its columns 8 and 9: a 0.5 m strip whose middle lies 0.375 m from the
    // nearest centres, beyond the gap heights are answered across, within a correlation length.
    let mut state = block().state();
    state.cells.retain(|&((i, _), _)| i != 8 && i != 9);
    let agg = WorldAggregate::from_state(state).expect("refit");
    assert!(agg.elevation(2.25, 2.125).is_none());
    let hit = agg
        .cast(Vector3::new(2.25, 2.125, 1.0), -Vector3::z(), 2.0, &|_| 1.0)
        .expect("known to rays");
    let t = hit.range.expect("a hit");
    assert!((t - 0.8).abs() < 5e-3, "range {t}");
    assert_eq!(hit.provenance, Provenance::Interpolated);
}

#[test]
fn a_ray_meets_the_fused_surface_where_geometry_says() {
    let agg = block();
    // From 1 m above the block's middle, 45° down along +x: the surface at z = 0.2 is met
    // 0.8 m down, i.e. after 0.8·√2 m.
    let origin = Vector3::new(1.0, 2.0, 1.0);
    let dir = Vector3::new(1.0, 0.0, -1.0).normalize();
    let hit = agg.cast(origin, dir, 5.0, &|_| 1.0).expect("known ground");
    let t = hit.range.expect("a hit");
    assert!((t - 0.8 * 2f64.sqrt()).abs() < 5e-3, "range {t}");
    assert!(hit.hit_probability > 0.99 && hit.range_var.is_some_and(|v| v > 0.0));
    assert_eq!(hit.provenance, Provenance::Observed);
    // Level and above the surface: no crossing, a small hit probability, not none.
    let miss = agg
        .cast(Vector3::new(0.5, 2.0, 1.0), Vector3::x(), 3.0, &|_| 1.0)
        .expect("known ground");
    assert!(miss.range.is_none() && miss.hit_probability < 1e-6);
    // Over nothing the aggregate knows: no answer at all.
    assert!(agg
        .cast(Vector3::new(50.0, 50.0, 1.0), Vector3::x(), 5.0, &|_| 1.0)
        .is_none());
}

#[test]
fn flat_ground_is_fused_level_and_unseen_places_are_none() {
    let terrain = Heightmap::flat(60.0, 0.05, 0.0);
    let mut agg = WorldAggregate::new(WorldParams::default());
    assert!(agg.is_empty() && agg.elevation(3.0, 0.0).is_none());
    fold(&mut agg, &terrain, 0.0, 0.0, 0.0);
    fold(&mut agg, &terrain, 4.0, 0.0, 0.0);
    assert!(agg.cells().values().any(|c| c.scans == 2), "overlap fused");
    for (x, y) in [(3.0, 1.0), (6.0, -1.0), (8.0, 2.5), (11.0, 0.0)] {
        let e = agg.elevation(x, y).expect("observed");
        assert!(e.z.abs() < 3e-3, "z at ({x}, {y}) = {}", e.z);
        assert!(e.var > 0.0 && e.var.sqrt() < 0.02, "σ {}", e.var.sqrt());
    }
    assert!(agg.elevation(-15.0, -15.0).is_none(), "never seen");
}

#[test]
fn a_scan_refits_only_the_tiles_it_touches() {
    let terrain = Heightmap::flat(60.0, 0.05, 0.0);
    let mut agg = WorldAggregate::new(WorldParams::default());
    fold(&mut agg, &terrain, -20.0, 0.0, 0.0);
    let (tiles, refits) = (agg.tiles(), agg.refits());
    assert_eq!(refits, tiles as u64, "first scan fits each of its tiles once");
    let before = agg.elevation(-15.0, 1.0).expect("observed");
    // Far from the first scan: its tiles are new, the old ones untouched.
    fold(&mut agg, &terrain, 10.0, 0.0, 0.0);
    assert_eq!(agg.refits() - refits, (agg.tiles() - tiles) as u64);
    assert_eq!(agg.elevation(-15.0, 1.0), Some(before));
    // Overlapping the second scan: only some tiles refitted.
    let refits = agg.refits();
    fold(&mut agg, &terrain, 12.0, 0.0, 0.0);
    let touched = agg.refits() - refits;
    assert!(
        touched > 0 && touched < agg.tiles() as u64,
        "{touched} of {}",
        agg.tiles()
    );
}

#[test]
fn a_page_forgets_how_a_cell_was_seen_only_when_a_correction_edits_it() {
    let params = WorldParams::default();
    let n = params.tile_cells;
    let cell = Cell {
        z: 0.1,
        var: 1e-4,
        scans: 2,
    };
    let page = TilePage {
        key: (0, 0),
        cells: vec![((1, 1), cell), ((2, 1), cell)],
        points: Vec::new(),
        noise_var: Vec::new(),
        seen: vec![((1, 1), [3.0, 0.5]), ((2, 1), [4.0, 1.0])],
    };
    let lift = CellEdit {
        precision: 1e4,
        weighted_z: 3e3,
        scans: 1,
    };
    // An edit of a margin cell (another tile's) leaves the records.
    let mut margin = page.clone();
    margin.apply_edits(&[((n, 1), lift)], &params);
    assert_eq!(margin.seen, page.seen);
    // An edit of one of its own cells forgets that cell's record alone, as in memory.
    let mut own = page.clone();
    own.apply_edits(&[((2, 1), lift)], &params);
    assert_eq!(own.seen, vec![((1, 1), [3.0, 0.5])]);
}

#[test]
fn eviction_pages_far_tiles_out_and_they_come_back_exactly() {
    let terrain = Heightmap::flat(80.0, 0.05, 0.0);
    let mut agg = WorldAggregate::new(WorldParams::default());
    fold(&mut agg, &terrain, -25.0, 0.0, 0.0);
    fold(&mut agg, &terrain, 20.0, 0.0, 0.0);
    let (tiles, cells) = (agg.tiles(), agg.len());
    let near = agg.elevation(23.0, 1.0).expect("observed");
    let far_probes: Vec<(f64, f64)> = (0..40)
        .map(|k| (-24.0 + 0.17 * k as f64, 0.9 - 0.05 * k as f64))
        .collect();
    let far_before: Vec<_> = far_probes.iter().map(|&(x, y)| agg.elevation(x, y)).collect();
    assert!(far_before.iter().filter(|e| e.is_some()).count() > 20);
    let seen_far = |agg: &WorldAggregate| -> Vec<Seen> {
        far_probes.iter().map(|&(x, y)| agg.seen_at(x, y, 99.0)).collect()
    };
    let seen_before = seen_far(&agg);
    assert!(
        seen_before.iter().filter(|s| s.distance_m < 10.0).count() > 20,
        "the premise: the far cells keep how they were seen"
    );
    let pages = agg.evict_beyond(20.0, 0.0, 20.0);
    assert!(
        pages.iter().any(|p| !p.seen.is_empty()),
        "the records go with the pages"
    );
    let evicted = pages.len();
    assert!(
        evicted > 0 && agg.tiles() == tiles - evicted,
        "{evicted} of {tiles}"
    );
    assert!(agg.elevation(-25.0, 1.0).is_none(), "far scan paged out");
    assert!(agg.cells().keys().all(|&(i, _)| (i as f64 + 0.5) * 0.25 > -5.0));
    assert_eq!(agg.elevation(23.0, 1.0), Some(near), "near tiles untouched");
    assert!(agg.evict_beyond(20.0, 0.0, 20.0).is_empty(), "idempotent");
    let paged_cells: usize = pages.iter().map(|p| p.cells.len()).sum();
    assert_eq!(agg.len() + paged_cells, cells, "every cell either held or paged");
    // Back with no scan in between: the same answers, bit for bit.
    assert_eq!(agg.restore_pages(pages.clone()).expect("refit"), evicted);
    assert_eq!((agg.tiles(), agg.len()), (tiles, cells));
    let far_after: Vec<_> = far_probes.iter().map(|&(x, y)| agg.elevation(x, y)).collect();
    assert_eq!(far_after, far_before);
    assert_eq!(seen_far(&agg), seen_before, "and how they were seen");
    assert_eq!(
        agg.restore_pages(pages).expect("no-op"),
        0,
        "held tiles are not replaced"
    );
}

#[test]
fn a_scan_far_from_everything_mapped_evicts_nothing() {
    let terrain = Heightmap::flat(80.0, 0.05, 0.0);
    let mut agg = WorldAggregate::new(WorldParams::default());
    let insert = |agg: &mut WorldAggregate, x: f64| {
        let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.75), UnitQuaternion::identity());
        let scan = scan_of(&terrain, pose);
        let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
        agg.insert_and_evict(&scan, &local, 20.0).expect("insert")
    };
    assert_eq!(insert(&mut agg, -25.0), 0);
    let before = agg.elevation(-22.0, 1.0).expect("observed");
    assert_eq!(insert(&mut agg, 20.0), 0, "45 m from every tile: nothing evicted");
    assert_eq!(
        agg.elevation(-22.0, 1.0),
        Some(before),
        "the mapped area survives one scan"
    );
    assert!(
        insert(&mut agg, 21.0) > 0,
        "a second scan there confirms the move"
    );
    assert!(agg.elevation(-22.0, 1.0).is_none());
}

#[test]
fn a_restored_state_answers_like_the_original() {
    let terrain = Heightmap::flat(60.0, 0.05, 0.2);
    let mut agg = WorldAggregate::new(WorldParams::default());
    fold(&mut agg, &terrain, 0.0, 0.0, 0.4);
    let state = agg.state();
    let restored = WorldAggregate::from_state(state.clone()).expect("refit");
    assert_eq!(restored.state(), state);
    assert_eq!(restored.tiles(), agg.tiles());
    let json = serde_json::to_string(&state).expect("serialise");
    let back: WorldState = serde_json::from_str(&json).expect("deserialise");
    let from_json = WorldAggregate::from_state(back).expect("refit");
    for (x, y) in [(3.0, 1.0), (5.0, 3.0), (7.5, 4.0), (-20.0, 0.0)] {
        let want = agg.elevation(x, y);
        assert_eq!(restored.elevation(x, y), want, "at ({x}, {y})");
        // Text floats may lose the last bit; the map must not move by more.
        match (from_json.elevation(x, y), want) {
            (Some(a), Some(b)) => assert!((a.z - b.z).abs() < 1e-9 && (a.var - b.var).abs() < 1e-12),
            (a, b) => assert_eq!(a, b, "at ({x}, {y})"),
        }
    }
}

/// Scans of `terrain` from `truth`, fused with the poses `sent` (drifted or not); returns
/// the aggregate and the ledger of what each scan fused.
fn fused_with(
    terrain: &Heightmap,
    truth: &[Isometry3<f64>],
    sent: &[Isometry3<f64>],
) -> (WorldAggregate, super::super::ledger::Ledger) {
    let mut agg = WorldAggregate::new(WorldParams::default());
    let mut ledger = super::super::ledger::Ledger::new(1 << 30);
    for (k, (t, s)) in truth.iter().zip(sent).enumerate() {
        let mut scan = scan_of(terrain, *t);
        scan.pose = *s;
        scan.sequence = k as u64;
        let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
        for raster in agg.insert_all_within(&[(&scan, &local)], 8.0).expect("insert").0 {
            ledger.push(raster);
        }
    }
    (agg, ledger)
}

fn pose(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(x, y, 0.75),
        UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
    )
}

/// RMS height difference of two aggregates over the cells of `a`, and how many.
fn cell_rms(a: &WorldAggregate, b: &WorldAggregate) -> (f64, usize) {
    let d: Vec<f64> = a
        .cells()
        .iter()
        .filter_map(|(c, cell)| b.cells().get(c).map(|o| o.z - cell.z))
        .collect();
    (
        (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt(),
        d.len(),
    )
}

#[test]
fn a_correction_moves_drifted_scans_onto_the_map_the_true_poses_make() {
    let terrain = crate::map::test_support::family_terrain("fbm-h05-16deg", 3, 60.0);
    let level = |x: f64, y: f64, yaw: f64| {
        let p = pose(x, y, yaw);
        let ground = terrain.height(x, y).expect("on the terrain");
        Isometry3::from_parts(Translation3::new(x, y, ground + 0.75), p.rotation)
    };
    let truth: Vec<_> = (0..4)
        .map(|k| level(2.0 * k as f64, 0.5 * k as f64, 0.1 * k as f64))
        .collect();
    // Odometry drifting 5 % of the distance sideways and 2° of heading per scan.
    let drifted: Vec<_> = truth
        .iter()
        .enumerate()
        .map(|(k, t)| pose(0.0, 0.1 * k as f64, 0.035 * k as f64) * t)
        .collect();
    let (right, _) = fused_with(&terrain, &truth, &truth);
    let (mut wrong, mut ledger) = fused_with(&terrain, &truth, &drifted);
    let (before, _) = cell_rms(&right, &wrong);
    let plan = ledger.plan(|r| Some(truth[r.sequence as usize]), 0.25, &|_, _| false);
    assert_eq!(plan.moved.len(), 4);
    // A copy of the drifted map on disk, to be corrected page by page.
    let mut on_disk = wrong.clone();
    let mut pages = on_disk.evict_beyond(0.0, 0.0, -1.0);
    assert!(on_disk.tiles() == 0 && !pages.is_empty());
    let had_records = pages.iter().any(|p| !p.seen.is_empty());
    let applied = wrong.apply_edits(plan.edits.clone(), &|_| false).expect("refit");
    assert!(applied.page_edits.is_empty() && applied.tiles_refitted > 0);
    ledger.commit(plan.moved);
    let (after, n) = cell_rms(&right, &wrong);
    assert!(n > 500, "{n} cells compared");
    assert!(after < 0.05 * before, "cell RMS {before:.4} m → {after:.4} m");
    // Against the terrain, at the cells the true poses mapped: as good as that map.
    let truth_rms = |agg: &WorldAggregate| {
        let e: Vec<f64> = right
            .cells()
            .keys()
            .filter_map(|&c| {
                let (x, y) = right.centre(c);
                Some(agg.elevation(x, y)?.z - terrain.height(x, y)?)
            })
            .collect();
        (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt()
    };
    let (corrected, ideal) = (truth_rms(&wrong), truth_rms(&right));
    assert!(
        corrected < 1.1 * ideal,
        "RMSE {corrected:.4} m corrected, {ideal:.4} m with the true poses"
    );
    // The same edits through the pages: the cells match the corrected map's in memory, and the
    // tiles fitted from the pages agree with its tiles.
    let keys: BTreeSet<(i32, i32)> = pages.iter().map(|p| p.key).collect();
    // Cells the correction moved beyond every paged tile are made in memory.
    let mut restored = WorldAggregate::new(WorldParams::default());
    let paged = restored
        .apply_edits(plan.edits, &|t| keys.contains(&t))
        .expect("refit");
    assert!(restored
        .cells()
        .keys()
        .all(|&c| !keys.contains(&restored.tile_of(c))));
    for page in &mut pages {
        if let Some(edits) = paged.page_edits.get(&page.key) {
            page.apply_edits(edits, &WorldParams::default());
        }
    }
    restored.restore_pages(pages).expect("refit");
    for (c, cell) in wrong.cells() {
        let o = restored.cells().get(c).expect("a corrected cell is on its page");
        assert!((o.z - cell.z).abs() < 1e-9 && (o.var - cell.var).abs() < 1e-12 && o.scans == cell.scans);
    }
    assert_eq!(restored.len(), wrong.len());
    // A cell a correction edited forgets how it was seen, on disk as in memory.
    assert!(
        had_records,
        "the premise: the pages held how their cells were seen"
    );
    assert_eq!(restored.state().seen, wrong.state().seen);
    // Where every tile around came back from a page (tiles made in memory for the cells
    // the correction moved beyond them were fitted without their paged neighbours' margins).
    let mut compared = 0;
    let mut inner: Vec<(i32, i32)> = wrong
        .cells()
        .keys()
        .copied()
        .filter(|&c| {
            let (ti, tj) = wrong.tile_of(c);
            (-1..=1).all(|di| (-1..=1).all(|dj| keys.contains(&(ti + di, tj + dj))))
        })
        .collect();
    inner.sort_unstable();
    for c in inner.iter().step_by(37) {
        let (x, y) = wrong.centre(*c);
        let a = wrong.elevation(x, y).expect("a fused cell is known");
        let b = restored.elevation(x, y).expect("so is its page's");
        assert!((a.z - b.z).abs() < 2e-3, "({x}, {y}): {} vs {}", a.z, b.z);
        compared += 1;
    }
    assert!(compared > 20);
}

#[test]
fn a_window_answer_is_fused_with_its_departure_as_the_window_learnt_to_weigh_it() {
    let terrain = crate::map::test_support::family_terrain("fbm-h05-16deg", 3, 60.0);
    let ground = terrain.height(0.0, 0.0).expect("on the terrain");
    let pose = Isometry3::from_parts(
        Translation3::new(0.0, 0.0, ground + 0.75),
        UnitQuaternion::identity(),
    );
    let scan = scan_of(&terrain, pose);
    let local = LocalRangeMap::fit(&scan, &params()).expect("fit");
    let fused_with = |departure: f64| {
        let mut agg = WorldAggregate::new(WorldParams::default());
        agg.set_window_scales(&SigmaScales {
            departure: [departure; crate::map::scales::BINS],
            ..SigmaScales::default()
        });
        agg.insert(&scan, &local).expect("insert");
        agg.cells().clone()
    };
    let (unweighed, weighed) = (fused_with(0.0), fused_with(1.0));
    assert_eq!(unweighed.len(), weighed.len());
    let mut wider = 0;
    for (c, cell) in &weighed {
        let (x, y) = ((c.0 as f64 + 0.5) * 0.25, (c.1 as f64 + 0.5) * 0.25);
        let e = local.elevation(x, y).expect("a fused cell is predicted");
        let own = unweighed[c];
        // One scan: each cell holds its answer, with the variance it owns.
        assert!((own.var - e.var).abs() <= 1e-6 * e.var, "{c:?}");
        let expected = e.var + e.departure * e.departure;
        assert!(
            (cell.var - expected).abs() <= 1e-6 * expected,
            "{c:?}: {} vs {expected}",
            cell.var
        );
        wider += (cell.var > 1.5 * own.var) as usize;
    }
    // Between rings and over the relief's edges, answers depart from their data.
    assert!(
        wider > weighed.len() / 20,
        "{wider} of {} cells wider",
        weighed.len()
    );
}
