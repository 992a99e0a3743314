//! Map quality in CI: `rangegp-eval all --quick` (Table I, the aggregate and the overhang scene
//! at reduced sizes) must meet the quick bars derived from the full run (docs/EVALUATION.md), so a
//! regression in map quality fails the build.

use rangegp_lab::eval::{run, EvalOptions, Experiment};

#[test]
fn quick_evaluation_meets_its_bars() -> anyhow::Result<()> {
    let dir = rangegp_tests::TempDir::new("eval")?;
    let out = dir.path();
    let summary = run(&EvalOptions {
        experiment: Experiment::All,
        quick: true,
        seed: 0,
        out: out.to_path_buf(),
        config: None,
        step_m: 1.0,
        stop_scans: 0,
        scans: None,
        ends: 1,
        mount_m: None,
        sensor: Default::default(),
        dem: Default::default(),
    })?;
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json"))?)?;
    let pictures = [
        "heightmap.png",
        "aggregate_elevation.png",
        "overhang_abs_error.png",
    ];
    let missing: Vec<_> = pictures.iter().filter(|p| !out.join(p).is_file()).collect();
    drop(dir);
    assert!(summary.failures.is_empty(), "bars missed: {:?}", summary.failures);
    assert!(missing.is_empty(), "pictures not written: {missing:?}");
    for key in [
        "/local/range_rmse_z",
        "/local/elev_rmse_z",
        "/local/coverage95",
        "/local/nlpd",
        "/local/ause",
        "/aggregate/rmse_z",
        "/aggregate/seed000_rmse_z",
        "/aggregate/batch_elev_rmse_z",
        "/overhang/ray_rmse",
    ] {
        let v = json.pointer(key).and_then(|v| v.as_f64());
        assert!(v.is_some_and(f64::is_finite), "summary.json {key} = {v:?}");
    }
    Ok(())
}
