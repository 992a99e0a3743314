//! The σ calibration matrix in its quick form (docs/EVALUATION.md "Calibration"): three terrains
//! of the sim family × three sensors through the daemon's code path, at three world seeds. Every cell of the bar is not
//! met yet (the full run lists them); until it is, CI guards against regression: pooled coverage
//! of window, aggregate and occluded answers and the window's median NLPD must stay where
//! self-calibration brought them (`quick_regressions`; the matrix without the prequential
//! calibration fails it, and so do the matrix without the learnt noise floor and the one without
//! the other views' disagreement, as the next three tests check; another checks what the opt-in
//! unseen relief adds, pooled over the same seeds). The last runs the quick matrix on a DEM read
//! from a file, relief the family does not have (`--dem`, "Real geography"), with the sensors
//! level and tilting with the ground (`--chassis-m`, step 29).

use rangegp_lab::dem::DemTerrain;
use rangegp_lab::eval::calibration::{quick_regressions, run_calibration, run_quick_calibration, BANDS};
use rangegp_lab::eval::FamilyOptions;
use rangegp_service::config::Config;

#[test]
fn the_quick_calibration_matrix_does_not_regress() -> anyhow::Result<()> {
    let reports = run_quick_calibration(&Config::default())?;
    let report = &reports[0];
    let json = serde_json::to_value(report)?;
    for key in [
        "terrain",
        "sensor",
        "band",
        "source",
        "n",
        "rmse",
        "cov68",
        "cov95",
        "cov99",
        "nlpd",
        "reliability",
    ] {
        anyhow::ensure!(
            json["cells"]
                .as_array()
                .is_some_and(|c| !c.is_empty() && c.iter().all(|c| c.get(key).is_some())),
            "every cell has {key}"
        );
    }
    anyhow::ensure!(json["failures"].is_array());
    let bands: Vec<&str> = BANDS.iter().map(|b| b.2).collect();
    for sensor in ["seed000", "vlp16", "os1-64"] {
        anyhow::ensure!(
            report
                .cells
                .iter()
                .any(|c| c.sensor == sensor && bands.contains(&c.band.as_str())),
            "{sensor} scored"
        );
    }
    anyhow::ensure!(
        report
            .cells
            .iter()
            .any(|c| c.band == "occluded" && c.n + c.refused > 0),
        "an occluded-ground cell (answered or refused)"
    );
    let regressions = quick_regressions(&reports);
    anyhow::ensure!(regressions.is_empty(), "{regressions:?}");
    Ok(())
}

/// The guard's regressions on the quick matrices with one self-calibration step taken away by
/// `without` (it edits the defaults).
fn regressions_without(without: impl FnOnce(&mut Config)) -> anyhow::Result<Vec<String>> {
    let mut config = Config::default();
    without(&mut config);
    Ok(quick_regressions(&run_quick_calibration(&config)?))
}

#[test]
fn the_guard_fails_without_the_prequential_calibration() -> anyhow::Result<()> {
    let regressions = regressions_without(|c| c.gp.prequential_calibration = false)?;
    anyhow::ensure!(
        regressions.len() >= 2,
        "leave-one-out alone passes the guard: {regressions:?}"
    );
    Ok(())
}

#[test]
fn the_guard_fails_when_the_devices_noise_floor_is_not_learnt() -> anyhow::Result<()> {
    let regressions = regressions_without(|c| c.ingest.learn_noise_floor = false)?;
    anyhow::ensure!(
        regressions.len() >= 2,
        "the header's noise model alone passes the guard: {regressions:?}"
    );
    Ok(())
}

#[test]
fn the_guard_fails_without_the_other_views_disagreement() -> anyhow::Result<()> {
    let regressions = regressions_without(|c| c.gp.view_disagreement = 0.0)?;
    anyhow::ensure!(
        regressions.iter().any(|r| r.contains("occluded")),
        "occluded ground is covered without the other views' disagreement: {regressions:?}"
    );
    Ok(())
}

#[test]
fn the_unseen_relief_widens_sigma_where_no_scan_saw() -> anyhow::Result<()> {
    // Opt-in (`gp.unseen_relief`): on the quick matrices of the three guard seeds, pooled, it
    // lifts occluded ground's 95 % coverage from 0.884 to 0.888 (measured at step 26, whose
    // tests of patch means leave the factors less to widen; 0.884 to 0.891 at step 22; 0.876 to
    // 0.883 before the aggregate's factors were keyed on where its cells were seen from, step
    // 22; 0.875 to 0.882 before the aggregate fused with the departure, step 17). On seed 0
    // alone it lifted it
    // from 0.854 to 0.864 before the departure from the data entered σ (step 16; 0.869 to 0.870
    // since), 0.872 to 0.891 before the level classes, 0.835 to 0.848 before the other views'
    // disagreement, 0.814 to 0.846 before each return also tested maps that looked from
    // farther (docs/EVALUATION.md "Calibration", steps 6, 7, 9, 15 and 16).
    let occluded = |config: Config| -> anyhow::Result<f64> {
        let reports = run_quick_calibration(&config)?;
        let cells: Vec<_> = reports
            .iter()
            .flat_map(|r| &r.cells)
            .filter(|c| c.band == "occluded" && c.n > 0)
            .collect();
        let n: usize = cells.iter().map(|c| c.n).sum();
        anyhow::ensure!(n > 0, "occluded ground answered");
        Ok(cells.iter().map(|c| c.cov95 * c.n as f64).sum::<f64>() / n as f64)
    };
    let without = occluded(Config::default())?;
    let mut config = Config::default();
    config.gp.unseen_relief = true;
    let with = occluded(config)?;
    // Deterministic runs: a relief that widened nothing would give the same figure.
    anyhow::ensure!(with > without + 0.002, "occluded cov95 {without:.3} -> {with:.3}");
    Ok(())
}

/// An ESRI ASCII grid of valley-and-ridge relief no member of the family has: ridges 9 m apart
/// running north-east, cross-cut by a shorter swell, 0.2 m cells, 70 m a side.
fn ridges_grid() -> String {
    let (n, cell) = (351, 0.2);
    let mut text = format!("ncols {n}\nnrows {n}\nxllcorner 500000\nyllcorner 4100000\ncellsize {cell}\n");
    for row in 0..n {
        let y = (n - 1 - row) as f64 * cell;
        let line: Vec<String> = (0..n)
            .map(|col| {
                let x = col as f64 * cell;
                let tau = std::f64::consts::TAU;
                let z = 0.4 * (tau * (x - y) / (9.0 * std::f64::consts::SQRT_2)).sin()
                    + 0.12 * (tau * x / 3.7).sin() * (tau * y / 5.3).cos();
                format!("{z:.4}")
            })
            .collect();
        text.push_str(&line.join(" "));
        text.push('\n');
    }
    text
}

#[test]
fn a_dem_from_a_file_is_mapped_and_scored_through_the_daemons_code_level_or_tilted() -> anyhow::Result<()> {
    let dir = rangegp_tests::TempDir::new("dem")?;
    let path = dir.path().join("ridges.asc");
    std::fs::write(&path, ridges_grid())?;
    let dem = DemTerrain::load(&path, None, None)?;
    // Window answers on seen ground, pooled. Measured: the full run (`rangegp-eval calibration
    // --ends 5 --dem ridges.asc`) 0.955; this quick form 0.939 (seeds 1 and 2: 0.950, 0.915);
    // without the prequential calibration 0.753 (docs/EVALUATION.md "Real geography").
    let (level_cov95, level_rmse, n) = seen_window(&dem, None)?;
    eprintln!("ridges, level: window cov95 {level_cov95:.3}, RMSE {level_rmse:.4} m over {n} answers on seen ground");
    anyhow::ensure!(
        (0.90..=0.99).contains(&level_cov95),
        "window cov95 {level_cov95:.3} over {n} answers"
    );
    // The sensor on a 1 m chassis resting on the ridges, tilting 13° (median) to 20° with them.
    // Measured: cov95 0.955, RMSE 0.109 m against the level sensor's 0.113 m; with the tilt left
    // out of the poses the daemon is told, 0.808 and 0.432 m ("Calibration", step 29).
    let (cov95, rmse, n) = seen_window(&dem, Some(1.0))?;
    eprintln!("ridges, tilted: window cov95 {cov95:.3}, RMSE {rmse:.4} m over {n} answers on seen ground");
    anyhow::ensure!(
        (0.90..=0.99).contains(&cov95),
        "tilted: window cov95 {cov95:.3} over {n} answers"
    );
    anyhow::ensure!(
        rmse <= 1.3 * level_rmse,
        "tilted: window RMSE {rmse:.4} m against {level_rmse:.4} m level"
    );
    Ok(())
}

/// The quick matrix on `dem` with the sensors on a chassis `chassis_m` a side (level without):
/// the window's pooled cov95 and RMSE on seen ground and its answers there, after checking
/// that every cell is the DEM's and that each sensor answered near the robot.
fn seen_window(dem: &DemTerrain, chassis_m: Option<f64>) -> anyhow::Result<(f64, f64, usize)> {
    let report = run_calibration(&FamilyOptions {
        dem: Some(dem.clone()),
        chassis_m,
        ..FamilyOptions::quick()
    })?;
    anyhow::ensure!(
        report.cells.iter().all(|c| c.terrain == "ridges"),
        "{:?}",
        report.cells
    );
    for sensor in ["seed000", "vlp16", "os1-64"] {
        for band in ["0-5", "5-10"] {
            anyhow::ensure!(
                report
                    .cells
                    .iter()
                    .any(|c| c.sensor == sensor && c.band == band && c.source == "window" && c.n > 0),
                "{sensor} answered at {band} m"
            );
        }
    }
    let seen: Vec<_> = report
        .cells
        .iter()
        .filter(|c| c.source == "window" && c.band != "occluded")
        .collect();
    let n: usize = seen.iter().map(|c| c.n).sum();
    let weight = n.max(1) as f64;
    let cov95 = seen.iter().map(|c| c.cov95 * c.n as f64).sum::<f64>() / weight;
    let rmse = (seen.iter().map(|c| c.rmse.powi(2) * c.n as f64).sum::<f64>() / weight).sqrt();
    Ok((cov95, rmse, n))
}
