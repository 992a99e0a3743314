//! Pictures of daemon replies, as `rangegp query grid --png` and `rangegp query view --png`
//! draw them: one picture per layer, each with axes, units and a colour bar.

use crate::plot::{Heatmap, Limits, Raster};
use anyhow::Result;
use rangegp_proto::msg::{Camera, GridReply, Layer, ViewReply, ViewRequest};
use std::path::{Path, PathBuf};

/// Elevation to `file`, σ beside it (`<stem>_sigma.png`), each derived layer as
/// `<stem>_<layer>.png`; unobserved cells grey.
pub fn grid(rep: &GridReply, file: &Path) -> Result<()> {
    let elevation = Raster::from_grid(rep, &rep.elevation_m, |z| z);
    Heatmap::new("Elevation", "elevation (m)").save(file, &elevation)?;
    let sigma = Raster::from_grid(rep, &rep.variance_m2, f64::sqrt);
    Heatmap::new("σ of the elevation", "σ (m)")
        .gradient(colorous::MAGMA)
        .save(&sigma_beside(file), &sigma)?;
    let robot = &rep.robot;
    for layer in &rep.layers {
        let (title, unit, convert, limits, gradient): (String, &str, fn(f64) -> f64, Limits, _) =
            match layer.layer {
                Layer::Slope => (
                    "Slope over the footprint".into(),
                    "slope (°)",
                    f64::to_degrees,
                    Limits::Robust,
                    colorous::VIRIDIS,
                ),
                Layer::SlopeSigma => (
                    "σ of the slope".into(),
                    "σ (°)",
                    f64::to_degrees,
                    Limits::Robust,
                    colorous::MAGMA,
                ),
                Layer::Aspect => (
                    "Aspect (downhill, from +x)".into(),
                    "aspect (°)",
                    f64::to_degrees,
                    Limits::Fixed(-180.0, 180.0),
                    colorous::SINEBOW,
                ),
                Layer::Roughness => (
                    "Roughness (RMS off the footprint's plane)".into(),
                    "roughness (m)",
                    identity,
                    Limits::Robust,
                    colorous::VIRIDIS,
                ),
                Layer::RoughnessSigma => (
                    "σ of the roughness".into(),
                    "σ (m)",
                    identity,
                    Limits::Robust,
                    colorous::MAGMA,
                ),
                Layer::Step => (
                    "Step across the footprint".into(),
                    "step (m)",
                    identity,
                    Limits::Robust,
                    colorous::VIRIDIS,
                ),
                Layer::StepSigma => (
                    "σ of the step".into(),
                    "σ (m)",
                    identity,
                    Limits::Robust,
                    colorous::MAGMA,
                ),
                Layer::SlopeRisk => (
                    format!("P(slope > {}°)", robot.max_slope_deg),
                    "probability",
                    identity,
                    Limits::Fixed(0.0, 1.0),
                    colorous::INFERNO,
                ),
                Layer::StepRisk => (
                    format!("P(step > {} m)", robot.max_step_m),
                    "probability",
                    identity,
                    Limits::Fixed(0.0, 1.0),
                    colorous::INFERNO,
                ),
                Layer::UnknownRisk => (
                    "Share of the footprint unknown".into(),
                    "share",
                    identity,
                    Limits::Fixed(0.0, 1.0),
                    colorous::INFERNO,
                ),
                Layer::Risk => (
                    "P(slope or step over the limit)".into(),
                    "probability",
                    identity,
                    Limits::Fixed(0.0, 1.0),
                    colorous::INFERNO,
                ),
                Layer::TraversalCost | Layer::Cost => (
                    "Traversal cost (risk and unknown)".into(),
                    "cost",
                    identity,
                    Limits::Fixed(0.0, 1.0),
                    colorous::INFERNO,
                ),
            };
        let raster = Raster::from_grid(rep, &layer.values, convert);
        Heatmap::new(title, unit)
            .limits(limits)
            .gradient(gradient)
            .save(&beside(file, layer.layer.as_str()), &raster)?;
    }
    if !rep.costmap.is_empty() {
        let cost: Vec<Option<f32>> = rep
            .costmap
            .iter()
            .map(|&c| (c >= 0).then_some(f32::from(c)))
            .collect();
        Heatmap::new(
            format!(
                "Costmap (100 lethal at risk ≥ {}; grey unknown)",
                robot.lethal_risk
            ),
            "cost (0-100)",
        )
        .limits(Limits::Fixed(0.0, 100.0))
        .gradient(colorous::INFERNO)
        .save(&beside(file, "cost"), &Raster::from_grid(rep, &cost, identity))?;
    }
    Ok(())
}

/// The value unchanged (a layer drawn in its own unit).
fn identity(v: f64) -> f64 {
    v
}

/// `<stem>_sigma.png` beside `file`: where the σ picture of `file`'s layer goes.
fn sigma_beside(file: &Path) -> PathBuf {
    beside(file, "sigma")
}

/// `<stem>_<tag>.png` beside `file`.
fn beside(file: &Path, tag: &str) -> PathBuf {
    let stem = file.file_stem().and_then(|s| s.to_str()).unwrap_or("layer");
    file.with_file_name(format!("{stem}_{tag}.png"))
}

/// The range image of a lidar view to `file` and its σ beside it, over azimuth and elevation
/// in degrees (each 0.5° cell takes the nearest pixel).
pub fn view(rep: &ViewReply, req: &ViewRequest, file: &Path) -> Result<()> {
    let Camera::Lidar {
        ring_elevations_rad, ..
    } = &req.camera
    else {
        anyhow::bail!("only lidar views are drawn");
    };
    let elevations: Vec<f64> = ring_elevations_rad.iter().map(|e| e.to_degrees()).collect();
    let (lo, hi) = elevations
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &e| {
            (a.min(e), b.max(e))
        });
    let pixel = |az: f64, el: f64, layer: &[Option<f32>]| {
        let row = elevations
            .iter()
            .enumerate()
            .min_by(|a, b| (a.1 - el).abs().total_cmp(&(b.1 - el).abs()))?
            .0;
        let col = ((az / 360.0 * f64::from(rep.cols)).round() as usize) % rep.cols.max(1) as usize;
        layer[row * rep.cols as usize + col].map(f64::from)
    };
    let res = 0.5;
    let layers = [
        (
            file.to_path_buf(),
            "Range as the sensor would see the map",
            "range (m)",
            &rep.range_m,
            colorous::VIRIDIS,
        ),
        (
            sigma_beside(file),
            "σ of the range",
            "σ (m)",
            &rep.sigma_m,
            colorous::MAGMA,
        ),
    ];
    for (path, title, unit, layer, gradient) in layers {
        let raster = Raster::from_fn((0.0, lo - res), (360.0, hi + res), res, |az, el| {
            pixel(az, el, layer)
        });
        Heatmap::new(title, unit)
            .axes("azimuth (°, left of ahead)", "elevation (°)")
            .gradient(gradient)
            .save(&path, &raster)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rangegp_proto::msg::{GridLayer, Provenance, RobotModel};
    use rangegp_proto::PROTOCOL_VERSION;

    #[test]
    fn a_grid_of_every_layer_gives_one_picture_per_layer_and_the_costmap() {
        let (cols, rows) = (6u32, 4u32);
        let n = (cols * rows) as usize;
        let ramp = |k: usize| Some(k as f32 / n as f32);
        let values: Vec<Option<f32>> = (0..n).map(|k| if k == 3 { None } else { ramp(k) }).collect();
        let layers: Vec<Layer> = Layer::ALL.into_iter().filter(|l| *l != Layer::Cost).collect();
        let reply = GridReply {
            version: PROTOCOL_VERSION,
            origin_m: [0.05, 0.05],
            resolution_m: 0.1,
            cols,
            rows,
            elevation_m: values.clone(),
            variance_m2: values.clone(),
            provenance: vec![Provenance::Observed; n],
            layers: layers
                .iter()
                .map(|&layer| GridLayer {
                    layer,
                    values: values.clone(),
                })
                .collect(),
            costmap: (0..n).map(|k| if k == 5 { -1 } else { (k * 4) as i8 }).collect(),
            robot: RobotModel {
                footprint_radius_m: 0.3,
                max_slope_deg: 20.0,
                max_step_m: 0.2,
                lethal_risk: 0.5,
            },
        };
        let dir = std::env::temp_dir().join(format!("rangegp-pictures-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let file = dir.join("grid.png");
        grid(&reply, &file).expect("drawn");
        let mut want = vec![
            "grid.png".to_owned(),
            "grid_sigma.png".into(),
            "grid_cost.png".into(),
        ];
        want.extend(layers.iter().map(|l| format!("grid_{}.png", l.as_str())));
        for name in &want {
            let bytes = std::fs::read(dir.join(name)).unwrap_or_default();
            assert!(bytes.starts_with(b"\x89PNG"), "{name} is not a PNG");
        }
        let drawn = std::fs::read_dir(&dir).expect("listed").count();
        assert_eq!(drawn, want.len(), "one picture per layer, no more");
        std::fs::remove_dir_all(&dir).expect("removed");
    }
}
