//! The `rangegp-ros2` command line: the configuration it prints loads back unchanged, and a bad
//! one stops it with the field named, before any DDS or daemon traffic.

use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_rangegp-ros2");

#[test]
fn printed_configuration_loads_back_and_bad_values_are_named() -> anyhow::Result<()> {
    let out = Command::new(BIN).arg("--print-config").output()?;
    anyhow::ensure!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let printed = String::from_utf8(out.stdout)?;
    let parsed = rangegp_ros2::BridgeConfig::from_toml(&printed)?;
    assert_eq!(parsed, rangegp_ros2::BridgeConfig::default());

    let dir = std::env::temp_dir().join(format!("rangegp-ros2-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, printed.replace("rate_hz = 2.0", "rate_hz = -1.0"))?;
    let out = Command::new(BIN).arg("--config").arg(&bad).output()?;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("grid.rate_hz"), "{err}");
    std::fs::write(&bad, "[ros]\nqos = 1\n")?;
    let out = Command::new(BIN).arg("--config").arg(&bad).output()?;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("unknown field"), "{err}");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
