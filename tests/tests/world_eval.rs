//! `rangegp-eval world --quick` in CI, with the bars: a deskewed sweep within 10 % of a
//! static scan and better than the same sweep taken as fired at the stamp; a drive mapped with
//! drifting odometry, once corrected, within 10 % of the drive mapped with the true poses, and
//! clearly better than before the correction.

use rangegp_lab::eval::world::run_world;
use rangegp_lab::eval::FamilyOptions;

#[test]
fn quick_world_meets_the_deskew_and_the_correction_bars() -> anyhow::Result<()> {
    let report = run_world(&FamilyOptions::quick())?;
    assert!(report.failures.is_empty(), "{:?}", report.failures);
    assert!(report.points > 500, "{} deskew points", report.points);
    assert!(report.deskew_rmse < report.no_deskew_rmse, "{report:?}");
    // The quick drive is 29 m (0.33 m of drift at its end, against 1.73 m over the full run's
    // 99 m): the correction's gain is smaller, but must show.
    let d = &report.drift;
    assert!(d.points > 1000, "{} drift points", d.points);
    assert!(
        report.drift_rmse_after_correction < 0.97 * report.drift_rmse_before_correction,
        "drifted {:.4} m, corrected {:.4} m",
        report.drift_rmse_before_correction,
        report.drift_rmse_after_correction
    );
    assert!(
        d.timing.pages_rewritten > 0 && d.timing.tiles_on_disk > 0,
        "{:?}",
        d.timing
    );
    Ok(())
}
