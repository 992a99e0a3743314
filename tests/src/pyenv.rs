//! The Python side of the interop tests: a virtual environment under `target/pyenv` with the
//! pinned packages from PyPI (Cyclone DDS 11.0.1, eclipse-zenoh 1.10.2, iceoryx2 0.10.0,
//! mcap-ros2-support 0.5.5, numpy, pytest) and this repository's `python/` package, made once per
//! test binary and kept between runs while the list is unchanged. Without python3 the tests are
//! skipped locally and fail under CI (`CI` set).

use crate::child::succeeded_within;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

/// The packages, pinned where the interop depends on a version.
const PACKAGES: [&str; 8] = [
    "cyclonedds==11.0.1",
    "eclipse-zenoh==1.10.2",
    "iceoryx2==0.10.0",
    "mcap-ros2-support==0.5.5",
    "numpy>=1.22",
    "pytest>=7",
    "setuptools>=68",
    "wheel",
];

/// The environment, made once per run of this test binary (`None`: no python3 outside CI).
static VENV: Mutex<Option<Option<PathBuf>>> = Mutex::new(None);

/// The venv's python with the pinned packages and this repository's `rangegp` package installed
/// (the package from a copy under `target/`: a build writes `build/` and `*.egg-info` beside its
/// sources, and the working tree stays clean).
pub fn venv_python() -> anyhow::Result<Option<PathBuf>> {
    let mut made = VENV.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(python) = made.as_ref() {
        return Ok(python.clone());
    }
    let python = make_venv()?;
    if let Some(python) = &python {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let copy = root.join("target/pyenv/rangegp-src");
        if copy.exists() {
            std::fs::remove_dir_all(&copy)?;
        }
        copy_tree(&root.join("python"), &copy)?;
        succeeded_within(
            Command::new(python)
                .args([
                    "-m",
                    "pip",
                    "install",
                    "--quiet",
                    "--no-deps",
                    "--no-build-isolation",
                ])
                .arg(&copy),
            "pip install ./python",
        )?;
    }
    *made = Some(python.clone());
    Ok(python)
}

/// Copies the directory `from` to `to`, leaving out what a build or a test run left there.
fn copy_tree(from: &Path, to: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let name = entry.file_name();
        let skip = ["build", "__pycache__", ".pytest_cache"]
            .iter()
            .any(|n| name == *n)
            || name.to_string_lossy().ends_with(".egg-info");
        if skip {
            continue;
        }
        if entry.file_type()?.is_dir() {
            copy_tree(&entry.path(), &to.join(&name))?;
        } else {
            std::fs::copy(entry.path(), to.join(&name))?;
        }
    }
    Ok(())
}

/// The venv under `target/pyenv` with [`PACKAGES`] (kept between runs while the list is
/// unchanged), or `None` without python3 outside CI.
fn make_venv() -> anyhow::Result<Option<PathBuf>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let venv = root.join("target/pyenv");
    let python = venv.join("bin/python");
    let marker = venv.join(".rangegp-ready");
    // The marker lists the packages installed: a changed list installs again.
    if std::fs::read_to_string(&marker).is_ok_and(|m| m == PACKAGES.join("\n")) {
        return Ok(Some(python));
    }
    if !crate::tool_or_skip("python3", "the Python interop tests")? {
        return Ok(None);
    }
    succeeded_within(
        Command::new("python3").args(["-m", "venv"]).arg(&venv),
        "python3 -m venv",
    )?;
    succeeded_within(
        Command::new(&python)
            .args(["-m", "pip", "install", "--quiet"])
            .args(PACKAGES),
        "pip install of the pinned packages",
    )?;
    std::fs::write(&marker, PACKAGES.join("\n"))?;
    Ok(Some(python))
}
