//! `rangegp-eval layers --quick` in CI: the bars of issue 18 on three terrains of the family
//! (craters, fBm at 30°, boulders) with a VLP-16, limits from the full run
//! (docs/EVALUATION.md "Planner layers"): slope 95 % coverage in [0.90, 0.98], a risk whose Brier
//! score beats thresholding the mean slope and step, ≥ 50 planned pairs whose paths stay on
//! traversable ground and within 15 % of the oracle's length; and few cells whose slope or step
//! is wrong by more than 4 σ (the guard against overconfident layers).

use rangegp_lab::eval::layers::{failures, run_layers};
use rangegp_lab::eval::FamilyOptions;

#[test]
fn quick_layers_meet_the_coverage_risk_and_planning_bars() -> anyhow::Result<()> {
    let dir = rangegp_tests::TempDir::new("layers-eval")?;
    let out = dir.path();
    let r = run_layers(&FamilyOptions::quick(), out)?;
    assert!(
        r.quick && r.cases.iter().all(|c| c.cells > 10_000),
        "{:?}",
        r.cases
    );
    assert!(out.join("layers_risk_reliability.png").exists());
    drop(dir);
    assert_eq!(failures(&r), Vec::<String>::new(), "{r:#?}");
    assert!(
        r.no_path * 10 <= r.pairs,
        "{} of {} pairs without a path",
        r.no_path,
        r.pairs
    );
    Ok(())
}
