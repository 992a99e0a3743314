//! GP engine acceptance in reduced form: online hyperparameters against per-scan optima on
//! random seed-000 scans (the full 100-scan run is `rangegp-bench hyper`).

use rangegp_lab::bench::hyper::{run_hyper, HyperOptions};

#[test]
fn online_hyperparameters_track_the_batch_optimum() -> anyhow::Result<()> {
    let dir = rangegp_tests::TempDir::new("hyper")?;
    let r = run_hyper(&HyperOptions {
        scans: 30,
        seed: 3,
        out: dir.path().to_path_buf(),
    })?;
    drop(dir);
    assert!(r.online_within_one_sd, "{r:?}");
    // Tighter than one (skewed) standard deviation: within a factor 2 of the batch median.
    let ratio = |a: f64, b: f64| (a / b).ln().abs();
    assert!(
        ratio(r.online_variance, r.batch_variance.median) < 2f64.ln(),
        "{r:?}"
    );
    assert!(
        ratio(r.online_length_scale, r.batch_length_scale.median) < 2f64.ln(),
        "{r:?}"
    );
    Ok(())
}
