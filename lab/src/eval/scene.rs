//! The terrains the calibration and layers evaluations run on: the sim family, or one digital
//! elevation model read from a file (`--dem`), so that σ and the planner layers can be judged
//! on real geography the project never saw.

use std::borrow::Cow;

use crate::dem::DemTerrain;
use rangegp_sim::family::FAMILY_SIZE_M;
use rangegp_sim::{family, Heightmap, TerrainSpec};

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
/// named in `quick_names` when `quick` is set).
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
    use crate::dem::tests::ramp_file;
    use anyhow::Result;

    #[test]
    fn a_dem_replaces_the_family_and_quick_keeps_only_the_named_members() -> Result<()> {
        let (_dir, path) = ramp_file("dem-scenes")?;
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
