//! Motion deskew in CI: `rangegp-eval world --quick` must meet the bar (deskewed within
//! 10 % of a static scan) and beat the same sweeps taken as fired at the stamp, which a daemon
//! ignoring the motion would equal.

use rangegp_lab::eval::world::run_world;
use rangegp_lab::eval::FamilyOptions;

#[test]
fn quick_deskew_stays_within_a_tenth_of_a_static_scan_and_beats_ignoring_the_motion() -> anyhow::Result<()> {
    let report = run_world(&FamilyOptions::quick())?;
    assert!(report.failures.is_empty(), "{report:?}");
    assert!(report.points > 500, "{report:?}");
    assert!(report.deskew_rmse < report.no_deskew_rmse, "{report:?}");
    Ok(())
}
