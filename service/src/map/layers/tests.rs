use super::*;
use crate::map::scales::ErrorCorrelation;
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
