//! Views over evicted ground in CI: `rangegp-eval view --quick` must stay within the regression
//! guard derived from the measured runs (docs/EVALUATION.md "Views"), and the guard must catch
//! a map that forgets what left the window.

use rangegp_lab::eval::view::{quick_regressions, run_view};
use rangegp_lab::eval::FamilyOptions;
use rangegp_service::config::Config;

#[test]
fn quick_view_evaluation_stays_within_its_guard() -> anyhow::Result<()> {
    let report = run_view(&FamilyOptions::quick())?;
    let failures = quick_regressions(&report);
    assert!(failures.is_empty(), "{failures:?}\n{report:?}");
    Ok(())
}

#[test]
fn the_guard_fails_without_the_aggregate() -> anyhow::Result<()> {
    let mut config = Config::default();
    config.aggregate.enabled = false;
    let report = run_view(&FamilyOptions {
        config,
        ..FamilyOptions::quick()
    })?;
    assert!(!quick_regressions(&report).is_empty(), "{report:?}");
    Ok(())
}
