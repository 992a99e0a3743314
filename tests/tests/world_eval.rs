//! `rangegp-eval world --quick` in CI, held to the bars: a deskewed sweep within 10 % of a
//! static scan (and better than ignoring the motion); a drive mapped with drifting odometry, once
//! corrected, within 10 % of the drive mapped with the true poses; change precision and recall of
//! at least 0.9 with a box on gentle and on rough relief, the removed box gone within 3 scans that
//! see its ground, and the static pass all but silent.

use rangegp_lab::eval::world::{
    run_world, CHANGE_MIN, CLEAR_WITHIN_SCANS, CORRECTED_OVER_FREE_MAX, DESKEW_OVER_STATIC_MAX,
    STATIC_CHANGE_MAX_FRACTION,
};
use rangegp_lab::eval::FamilyOptions;

#[test]
fn quick_world_meets_the_deskew_correction_and_change_bars() -> anyhow::Result<()> {
    let r = run_world(&FamilyOptions::quick())?;
    assert!(r.points > 500, "{} deskew points", r.points);
    assert!(
        r.deskew_rmse <= DESKEW_OVER_STATIC_MAX * r.static_rmse,
        "{:?}",
        r.cases
    );
    assert!(r.deskew_rmse < r.no_deskew_rmse, "{:?}", r.cases);
    // The quick drive is 29 m (0.33 m of drift at its end; the full run's 99 m end 1.73 m off).
    let d = &r.drift;
    assert!(d.points > 1000, "{} drift points", d.points);
    assert!(
        r.drift_rmse_after_correction <= CORRECTED_OVER_FREE_MAX * r.drift_free_rmse
            && r.drift_rmse_after_correction < 0.97 * r.drift_rmse_before_correction,
        "drifted {:.4} m, corrected {:.4} m, true poses {:.4} m",
        r.drift_rmse_before_correction,
        r.drift_rmse_after_correction,
        r.drift_free_rmse
    );
    assert!(
        d.timing.pages_rewritten > 0 && d.timing.tiles_on_disk > 0,
        "{:?}",
        d.timing
    );
    // The quick cases: a 0.5 m box on fBm 8° and on fBm 16° (where the first method's precision
    // was 0.6), passes at 1 m.
    let c = &r.change;
    assert!(c.precision >= CHANGE_MIN && c.recall >= CHANGE_MIN, "{c:?}");
    assert!(c.scans_to_clear.is_some_and(|n| n <= CLEAR_WITHIN_SCANS), "{c:?}");
    assert!(
        c.static_changes as f64 <= STATIC_CHANGE_MAX_FRACTION * c.static_cells as f64,
        "{c:?}"
    );
    assert!(r.failures.is_empty(), "{:?}", r.failures);
    Ok(())
}
