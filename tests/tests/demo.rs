//! The demo (daemon + rover over iceoryx2 + planner over Zenoh) meets its accuracy bars and
//! writes its summary and pictures. A reduced run of `rangegp demo`.

use rangegp_lab::demo::{run, DemoOptions};

#[test]
fn demo_meets_its_accuracy_bars_and_writes_its_outputs() -> anyhow::Result<()> {
    let dir = rangegp_tests::TempDir::new("demo")?;
    let out = dir.path();
    let opts = DemoOptions {
        scans: 15,
        seed: 0,
        step_m: 1.0,
        rate_hz: 100.0,
        queries_per_scan: 20,
        grid_resolution_m: 1.0,
        out: out.to_path_buf(),
        quiet: true,
    };
    let s = run(&opts)?;
    assert_eq!((s.scans_accepted, s.scans_rejected), (15, 0));
    assert!(s.points_observed >= 250, "{} points observed", s.points_observed);
    assert!(s.elevation_rmse_m <= 0.05, "RMSE {}", s.elevation_rmse_m);
    assert!((0.85..=0.99).contains(&s.coverage95), "coverage {}", s.coverage95);
    assert!(
        s.query_p50_us.is_finite() && s.query_p50_us > 0.0,
        "p50 {}",
        s.query_p50_us
    );
    // summary.json says what the run measured, field for field.
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json"))?)?;
    let measured = serde_json::to_value(&s)?;
    for key in [
        "scans_accepted",
        "scans_rejected",
        "elevation_rmse_m",
        "coverage95",
        "query_p50_us",
        "query_p99_us",
    ] {
        let written = summary.get(key);
        assert!(written.is_some(), "summary.json lacks {key}");
        assert_eq!(
            written,
            measured.get(key),
            "summary.json's {key} differs from the run's"
        );
    }
    for png in ["elevation.png", "sigma.png"] {
        let bytes = std::fs::read(out.join(png))?;
        assert!(bytes.starts_with(b"\x89PNG"), "{png} is not a PNG");
    }
    Ok(())
}
