//! The C++17 example (`examples/cpp/elevation.cpp`) is compiled with the system's C++ compiler
//! against the generated header and the `rangegp-c` shared library, then publishes a scan over
//! iceoryx2 and answers elevation over Zenoh from a live daemon. Without a C++ compiler the test
//! is skipped locally and fails under CI (`CI` set).

use rangegp_tests::child::succeeded_within;
use rangegp_tests::{Harness, TempDir};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The folder holding `librangegp_c.so` (built with this test binary: rangegp-c is a
/// dependency of the tests crate).
fn library_dir() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let deps = exe
        .parent()
        .ok_or_else(|| anyhow::anyhow!("test binary without a folder"))?;
    let found = [deps, deps.parent().unwrap_or(deps)]
        .into_iter()
        .find(|d| d.join("librangegp_c.so").exists())
        .map(Path::to_path_buf);
    found.ok_or_else(|| anyhow::anyhow!("librangegp_c.so not found beside {}", exe.display()))
}

#[test]
fn the_cpp_example_publishes_a_scan_and_reads_elevation_back() -> anyhow::Result<()> {
    let compiler = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
    if !rangegp_tests::tool_or_skip(&compiler, "the C++ example")? {
        return Ok(());
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let lib = library_dir()?;
    let tmp = TempDir::new("elevation")?;
    let exe = tmp.path().join("elevation");
    succeeded_within(
        Command::new(&compiler)
            .args(["-std=c++17", "-Wall", "-Wextra", "-Werror"])
            .arg(root.join("examples/cpp/elevation.cpp"))
            .arg("-I")
            .arg(root.join("capi/include"))
            .arg("-L")
            .arg(&lib)
            .arg("-lrangegp_c")
            // DT_RPATH, searched before LD_LIBRARY_PATH (cargo's points at target/release too, where
            // a `cargo build` of another revision may have left an older librangegp_c.so).
            .arg(format!("-Wl,--disable-new-dtags,-rpath,{}", lib.display()))
            .arg("-o")
            .arg(&exe),
        "compiling the example",
    )?;
    let h = Harness::start(|_| {})?;
    let run = succeeded_within(
        Command::new(&exe).args([&h.endpoint, &h.config.map_id, &h.config.scan_service_name()]),
        "the example",
    )?;
    let stdout = String::from_utf8_lossy(&run.stdout);
    let lines: Vec<Vec<f64>> = stdout
        .lines()
        .filter_map(|l| l.strip_prefix("elevation "))
        .map(|l| l.split_whitespace().filter_map(|v| v.parse().ok()).collect())
        .collect();
    eprintln!("{stdout}");
    assert_eq!(lines.len(), 3, "{stdout}");
    for l in &lines {
        // Flat ground at z = 0 under a sensor 1 m up.
        assert!(l[2].abs() < 0.01 && l[3] > 0.0 && l[3] < 0.05, "{stdout}");
    }
    let status = h.client.status()?;
    assert_eq!((status.scans_accepted, status.scans_rejected), (1, 0));
    Ok(())
}
