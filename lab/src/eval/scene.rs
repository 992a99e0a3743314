//! The terrains the calibration and layers evaluations run on: the sim family, or one digital
//! elevation model read from a file (`--dem`), so that σ and the planner layers can be judged
//! on real geography the project never saw.

use std::borrow::Cow;
use std::path::Path;

use anyhow::{Context, Result};
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, Dem, Heightmap, TerrainSpec};

/// Smallest side a DEM terrain may have, metres: the drives wander up to 15 m from the origin
/// before turning back, and the near range bands (to 20 m) must lie on the map around them.
pub const MIN_DEM_SIDE_M: f64 = 60.0;

/// A terrain from a DEM file, ready to drive on.
#[derive(Debug, Clone)]
pub struct DemTerrain {
    /// Name in reports: the file's stem, with the relief factor when it is not 1.
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
            dem.shape().0.min(dem.shape().1),
            map.resolution(),
        );
        let stem = path.file_stem().map_or("dem".into(), |s| s.to_string_lossy());
        let name = if relief == 1.0 {
            stem.into_owned()
        } else {
            format!("{stem}-x{}", three_figures(relief))
        };
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

/// One terrain an evaluation runs on.
pub enum Scene<'a> {
    /// A member of the sim family, built from the run's seed.
    Family(TerrainSpec),
    /// The DEM given with `--dem`.
    Dem(&'a DemTerrain),
}

impl Scene<'_> {
    /// Name in reports.
    pub fn name(&self) -> &str {
        match self {
            Self::Family(spec) => &spec.name,
            Self::Dem(dem) => &dem.name,
        }
    }

    /// The terrain (a family member is built here, at the family's size).
    pub fn build(&self, seed: u64) -> Cow<'_, Heightmap> {
        match self {
            Self::Family(spec) => Cow::Owned(spec.build(seed, FAMILY_SIZE_M)),
            Self::Dem(dem) => Cow::Borrowed(&dem.map),
        }
    }
}

/// The scenes of a run: the DEM alone when one is given, else the family (only the members
/// named in `quick` when `quick` is set and `quick` is not empty).
pub fn scenes<'a>(dem: Option<&'a DemTerrain>, quick: bool, quick_names: &[&str]) -> Vec<Scene<'a>> {
    match dem {
        Some(dem) => vec![Scene::Dem(dem)],
        None => family()
            .into_iter()
            .filter(|t| !quick || quick_names.contains(&t.name.as_str()))
            .map(Scene::Family)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::demo::TempDir;

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
        let dir = TempDir::new(&format!("dem-load-{}", std::process::id()))?;
        let path = dir.0.join("ramp.asc");
        std::fs::write(&path, ramp(41, 2.0))?;
        let dem = DemTerrain::load(&path, None, None)?;
        assert_eq!(dem.name, "ramp");
        assert_eq!(dem.map.half_extent(), 40.0);
        let rise = dem.map.height(0.0, 10.0).zip(dem.map.height(0.0, 0.0));
        assert!(rise.is_some_and(|(n, c)| (n - c - 1.0).abs() < 1e-6), "{rise:?}");
        // Shrunk to 1.5 m cells with the slope kept (relief 0.75): still 1 in 10.
        let shrunk = DemTerrain::load(&path, Some(1.5), Some(0.75))?;
        assert_eq!(shrunk.name, "ramp-x0.75");
        let rise = shrunk.map.height(0.0, 10.0).zip(shrunk.map.height(0.0, 0.0));
        assert!(rise.is_some_and(|(n, c)| (n - c - 1.0).abs() < 1e-5), "{rise:?}");
        let small = DemTerrain::load(&path, Some(1.0), None).expect_err("40 m is too small");
        assert!(format!("{small:#}").contains("--dem-cell-m"), "{small:#}");
        let missing = DemTerrain::load(&dir.0.join("none.asc"), None, None).expect_err("no file");
        assert!(format!("{missing:#}").contains("none.asc"), "{missing:#}");
        Ok(())
    }

    #[test]
    fn a_relief_factor_is_named_to_three_figures() {
        let named: Vec<String> = [0.0033564255, 2.0, 12.5, 0.25, 150.0].map(three_figures).into();
        assert_eq!(named, ["0.00336", "2", "12.5", "0.25", "150"]);
    }

    #[test]
    fn a_dem_replaces_the_family_and_quick_keeps_only_the_named_members() -> Result<()> {
        let dir = TempDir::new(&format!("dem-scenes-{}", std::process::id()))?;
        let path = dir.0.join("ramp.asc");
        std::fs::write(&path, ramp(41, 2.0))?;
        let dem = DemTerrain::load(&path, None, None)?;
        let names = |s: Vec<Scene>| s.iter().map(|s| s.name().to_owned()).collect::<Vec<_>>();
        assert_eq!(names(scenes(Some(&dem), true, &["craters"])), ["ramp"]);
        assert_eq!(
            names(scenes(None, true, &["craters", "boulders"])),
            ["craters", "boulders"]
        );
        assert_eq!(scenes(None, false, &["craters"]).len(), family().len());
        Ok(())
    }
}
