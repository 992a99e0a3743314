//! Terrains from digital elevation model files for the lab's tools: the calibration and layers
//! evaluations (`rangegp-eval ... --dem`) and the scan generator (`rangegp scangen --dem`), so
//! that maps and σ can be judged, and a daemon driven, on real geography the project never saw.

use std::path::{Path, PathBuf};

use crate::cli::within;
use anyhow::{Context, Result};
use rangegp_sim::{Dem, Heightmap};

/// `--dem FILE [--dem-cell-m M] [--dem-relief K]`, shared by every command that takes a DEM.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct DemArgs {
    /// A digital elevation model (ESRI ASCII grid, `.asc`) to drive on instead of the simulated
    /// terrain: its central square, centred on the origin, north up (docs/EVALUATION.md "Real
    /// geography").
    #[arg(long)]
    pub dem: Option<PathBuf>,
    /// The DEM's cell size for the run, metres (default: the file's `cellsize`, taken as
    /// metres; a grid in degrees needs it).
    #[arg(long, requires = "dem", value_parser = cell_of)]
    pub dem_cell_m: Option<f64>,
    /// Factor on the DEM's heights about their mean (default 1). A landscape shrunk to a
    /// rover's scale keeps its slopes with the ratio of `--dem-cell-m` to the true cell size.
    #[arg(long, requires = "dem", value_parser = relief_of)]
    pub dem_relief: Option<f64>,
}

impl DemArgs {
    /// The terrain `--dem` names, or `None` without one.
    pub fn load(&self) -> Result<Option<DemTerrain>> {
        self.dem
            .as_deref()
            .map(|path| DemTerrain::load(path, self.dem_cell_m, self.dem_relief))
            .transpose()
    }
}

/// Parses `--dem-cell-m`: a finite cell size in [0.01, 100] m.
fn cell_of(s: &str) -> std::result::Result<f64, String> {
    within(
        s,
        |v| (0.01..=100.0).contains(&v),
        "the cell size must lie in [0.01, 100] m",
    )
}

/// Parses `--dem-relief`: a finite factor in (0, 100].
fn relief_of(s: &str) -> std::result::Result<f64, String> {
    within(
        s,
        |v| v > 0.0 && v <= 100.0,
        "the relief factor must lie in (0, 100]",
    )
}

/// Smallest side a DEM terrain may have, metres: the drives turn back 15 m from its edge, so a
/// 60 m square leaves them 15 m to wander from the centre with their 0–10 m range bands on the
/// map (farther bands are scored on the part of them that is).
pub const MIN_DEM_SIDE_M: f64 = 60.0;

/// A terrain from a DEM file, ready to drive on.
#[derive(Debug, Clone)]
pub struct DemTerrain {
    /// Name in reports: the file's stem, with the cell size and the relief factor when given.
    pub name: String,
    /// The terrain (the DEM's central square, centred on the origin).
    pub map: Heightmap,
}

impl DemTerrain {
    /// Reads `path` (an ESRI ASCII grid) with cells of `cell_m` metres (default: the file's
    /// cell size) and heights × `relief` about their mean.
    pub fn load(path: &Path, cell_m: Option<f64>, relief: Option<f64>) -> Result<Self> {
        let dem = Dem::read(path).with_context(|| format!("--dem {}", path.display()))?;
        let relief = relief.unwrap_or(1.0);
        let map = dem
            .heightmap(cell_m, relief)
            .with_context(|| format!("--dem {}", path.display()))?;
        let side = 2.0 * map.half_extent();
        anyhow::ensure!(
            side >= MIN_DEM_SIDE_M,
            "--dem {}: its central square is {} cells of {} m, {side:.1} m a side; the drives need \
             at least {MIN_DEM_SIDE_M} m (a grid in degrees or at a rover's scale needs --dem-cell-m)",
            path.display(),
            dem.shape().0.min(dem.shape().1) - 1,
            map.resolution(),
        );
        let mut name = path
            .file_stem()
            .map_or("dem".into(), |s| s.to_string_lossy())
            .into_owned();
        if let Some(cell) = cell_m {
            name.push_str(&format!("-c{}", three_figures(cell)));
        }
        if relief != 1.0 {
            name.push_str(&format!("-x{}", three_figures(relief)));
        }
        Ok(Self { name, map })
    }
}

/// `v` (positive) to three significant figures, without trailing zeros: 0.00336, 2, 12.5.
fn three_figures(v: f64) -> String {
    let decimals = (2 - v.log10().floor() as i32).max(0) as usize;
    let text = format!("{v:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::demo::TempDir;

    /// [`ramp`]`(41, 2.0)` (80 m a side) written to `ramp.asc` in a directory of its own, named
    /// after `test`; the directory goes when the returned guard drops.
    pub(crate) fn ramp_file(test: &str) -> Result<(TempDir, PathBuf)> {
        let dir = TempDir::new(&format!("{test}-{}", std::process::id()))?;
        let path = dir.0.join("ramp.asc");
        std::fs::write(&path, ramp(41, 2.0))?;
        Ok((dir, path))
    }

    /// An ESRI ASCII grid of `n` × `n` cells of `cell` on a plane rising 1 in 10 to the north.
    fn ramp(n: usize, cell: f64) -> String {
        let mut text = format!("ncols {n}\nnrows {n}\nxllcorner 0\nyllcorner 0\ncellsize {cell}\n");
        for row in 0..n {
            let z = (n - 1 - row) as f64 * cell * 0.1;
            text.push_str(&vec![format!("{z}"); n].join(" "));
            text.push('\n');
        }
        text
    }

    #[test]
    fn a_dem_file_becomes_a_named_terrain_north_up_or_is_refused_with_its_reason() -> Result<()> {
        let (dir, path) = ramp_file("dem-load")?;
        let dem = DemTerrain::load(&path, None, None)?;
        assert_eq!(dem.name, "ramp");
        assert_eq!(dem.map.half_extent(), 40.0);
        let rise = dem.map.height(0.0, 10.0).zip(dem.map.height(0.0, 0.0));
        assert!(rise.is_some_and(|(n, c)| (n - c - 1.0).abs() < 1e-6), "{rise:?}");
        // Shrunk to 1.5 m cells with the slope kept (relief 0.75): still 1 in 10.
        let shrunk = DemTerrain::load(&path, Some(1.5), Some(0.75))?;
        assert_eq!(shrunk.name, "ramp-c1.5-x0.75");
        let rise = shrunk.map.height(0.0, 10.0).zip(shrunk.map.height(0.0, 0.0));
        assert!(rise.is_some_and(|(n, c)| (n - c - 1.0).abs() < 1e-5), "{rise:?}");
        let small = DemTerrain::load(&path, Some(1.0), None).expect_err("40 m is too small");
        assert!(format!("{small:#}").contains("--dem-cell-m"), "{small:#}");
        let missing = DemTerrain::load(&dir.0.join("none.asc"), None, None).expect_err("no file");
        assert!(format!("{missing:#}").contains("none.asc"), "{missing:#}");
        Ok(())
    }

    #[test]
    fn a_scan_generator_drives_on_a_dem() -> Result<()> {
        let (_dir, path) = ramp_file("dem-scangen")?;
        let map = DemTerrain::load(&path, None, None)?.map;
        let preset = rangegp_sim::ScannerPreset::vlp16();
        let mount = preset.mount_height_m;
        let mut world = crate::scangen::ScanGenerator::on(map.clone(), 3, preset, 5, 1.0);
        for i in 0..5 {
            let scan = world.scan(i, 1_000 + i as u64);
            let at = scan.pose.translation.vector;
            let ground = map.height(at.x, at.y).expect("on the map");
            assert!((at.z - ground - mount).abs() < 1e-9, "{at:?} over {ground}");
            assert!(!scan.points.is_empty(), "scan {i} saw nothing");
        }
        Ok(())
    }

    #[test]
    fn a_relief_factor_is_named_to_three_figures() {
        let named: Vec<String> = [0.0033564255, 2.0, 12.5, 0.25, 150.0].map(three_figures).into();
        assert_eq!(named, ["0.00336", "2", "12.5", "0.25", "150"]);
    }
}
