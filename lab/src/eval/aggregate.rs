//! The aggregate experiment of seed 000 (§IV, §V-B): five A* trajectories, a scan every 5 m,
//! each scan's training rays folded into the aggregates; at the end of each trajectory the
//! elevation is scored over the held-out rays of all its scans. Compared: seed 000's
//! pose-augmented GP, the project's world aggregate, and a batch elevation GP over every
//! training point of the trajectory.

use super::drive::ScaleLearner;
use super::local::{self, NUGGET_M2};
use super::progress;
use super::scores::{MeanSd, Sample, Scores};
use super::split::{split_scan, SplitScan};
use crate::plot::{Heatmap, Limits, Raster};
use anyhow::{Context, Result};
use nalgebra::{UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rangegp_service::config::Config;
use rangegp_service::gp::hyper::fit_hyperparameters;
use rangegp_service::gp::likelihood::TrainingSet;
use rangegp_service::gp::{sphere, JitterPolicy, Kernel};
use rangegp_service::map::aggregate::pose_gp::{PoseAugmentedGp, PoseGpParams};
use rangegp_service::map::aggregate::world::{WorldAggregate, WorldParams};
use rangegp_service::map::aggregate::Aggregate;
use rangegp_service::map::elevation_gp::ElevationGp;
use rangegp_service::map::local::{LocalRangeMap, MapParams};
use rangegp_service::map::prior::Prior;
use rangegp_sim::{plan_trajectories, Heightmap, ScannerPreset, Trajectory, TrajectoryParams};
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// Size of the aggregate experiment, and the daemon configuration its world aggregate maps with.
#[derive(Debug, Clone, PartialEq)]
pub struct AggregateOptions {
    /// Trajectories (seed 000: 5).
    pub trajectories: usize,
    /// Start and goal at least this far apart, metres.
    pub min_length_m: f64,
    /// Random scans the hyperparameters are tuned on (geometric mean of per-scan optima).
    pub tune_scans: usize,
    /// World seed.
    pub seed: u64,
    /// Draw the seed-000 aggregate's error map too (slow: a root-find per pixel over every ray).
    pub seed000_picture: bool,
    /// Daemon configuration of the window maps the world aggregate fuses (`--config`; the
    /// kernel is the tuned one).
    pub config: Config,
}

/// Scores of the three models on one trajectory.
#[derive(Debug, Clone, Serialize)]
pub struct TrajectoryRow {
    /// Scans along it.
    pub scans: usize,
    /// Held-out rays scored.
    pub test_rays: usize,
    /// The project's world aggregate, z at each test ray's true (x, y).
    pub world: Scores,
    /// Test rays the world aggregate had no answer for.
    pub world_unobserved: usize,
    /// Seed 000's pose-augmented GP, z of the predicted point along each test ray.
    pub seed000: Scores,
    /// Batch elevation GP over all training points.
    pub batch_elevation: Scores,
    /// Mean insert time per scan of the world aggregate (local fit excluded), ms.
    pub world_insert_ms: f64,
    /// Tiles and cells of the world aggregate at the end.
    pub world_tiles: usize,
    /// Cells of the world aggregate at the end.
    pub world_cells: usize,
}

/// The aggregate experiment's report.
#[derive(Debug, Clone, Serialize)]
pub struct AggregateReport {
    /// Per trajectory.
    pub trajectories: Vec<TrajectoryRow>,
    /// Mean over trajectories of the world aggregate's RMSE in z.
    pub world_rmse_z: MeanSd,
    /// Mean over trajectories of the pose-augmented GP's RMSE in z.
    pub seed000_rmse_z: MeanSd,
    /// Mean over trajectories of the batch elevation GP's RMSE in z.
    pub batch_elev_rmse_z: MeanSd,
    /// Pooled 95 % coverage of the world aggregate.
    pub world_coverage95: f64,
    /// Hyperparameters used: range GP (σ², ℓ), seed-000 form (σ², ℓ), elevation GP (σ², ℓ).
    pub kernels: [[f64; 2]; 3],
}

/// Per-scan optima of the paper-form range GP (range sphere, plain residual) on one scan: the
/// hyperparameters seed 000 reused for its aggregate.
fn tune_paper_form(scan: &SplitScan) -> Result<(f64, f64)> {
    let t = &scan.train;
    let prior = Prior::flat_ground(
        ScannerPreset::seed000().mount_height_m,
        &UnitQuaternion::identity(),
        t.max_range_m,
    );
    let inputs: Vec<[f64; 3]> = t
        .rays
        .iter()
        .map(|r| sphere::to_sphere(r.inclination, r.azimuth, 10.0))
        .collect();
    let targets: Vec<f64> = t
        .rays
        .iter()
        .map(|r| r.range - prior.range(&Vector3::from(sphere::to_sphere(r.inclination, r.azimuth, 1.0))))
        .collect();
    let noise: Vec<f64> = t
        .rays
        .iter()
        .map(|r| (t.range_noise_per_m * r.range).powi(2) + NUGGET_M2)
        .collect();
    let set = TrainingSet {
        inputs: &inputs,
        targets: &targets,
        noise_var: &noise,
    };
    let fit = fit_hyperparameters(&local::start_kernel(), set, local::bounds(), 100)?;
    Ok((fit.variance, fit.length_scale))
}

/// The three kernels: range GP (the daemon's form), seed-000 form, elevation GP.
fn tune(terrain: &Heightmap, opts: &AggregateOptions) -> Result<[Kernel; 3]> {
    let bar = progress::bar(opts.tune_scans as u64, "aggregate: tuning");
    let fits: Vec<_> = (0..opts.tune_scans)
        .into_par_iter()
        .map(|i| {
            let scan = local::scan_at(terrain, opts.seed, 2, i);
            let r = local::tune(&scan).and_then(|(range, elev)| Ok((range, tune_paper_form(&scan)?, elev)));
            bar.inc(1);
            r
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    Ok([
        local::geometric_kernel(fits.iter().map(|f| (f.0.variance, f.0.length_scale))),
        local::geometric_kernel(fits.iter().map(|f| f.1)),
        local::geometric_kernel(fits.iter().map(|f| (f.2.variance, f.2.length_scale))),
    ])
}

/// Folds one trajectory into the models and scores them; draws pictures when `pictures` is set.
fn run_trajectory(
    terrain: &Heightmap,
    traj: &Trajectory,
    index: usize,
    kernels: &[Kernel; 3],
    opts: &AggregateOptions,
    pictures: Option<&Path>,
) -> Result<TrajectoryRow> {
    let preset = ScannerPreset::seed000();
    let mut rng = Pcg64::seed_from_u64(opts.seed ^ 0xa66 ^ ((index as u64) << 32));
    let scans: Vec<SplitScan> = (0..traj.scans.waypoints.len())
        .map(|i| {
            split_scan(
                terrain,
                traj.scans.pose(terrain, i, preset.mount_height_m),
                &preset,
                0.2,
                i as u64,
                &mut rng,
            )
        })
        .collect();
    let params = MapParams {
        kernel: kernels[0],
        ..opts.config.map_params()
    };
    let mut world = WorldAggregate::new(WorldParams {
        kernel_variance: kernels[2].variance,
        length_scale: kernels[2].length_scale,
        ..WorldParams::default()
    });
    let mut pose_gp = PoseAugmentedGp::new(PoseGpParams {
        kernel: kernels[1],
        sphere_radius_m: 10.0,
        sensor_height_m: preset.mount_height_m,
        nugget_m2: NUGGET_M2,
        max_points: 20_000,
    });
    let bar = progress::bar(scans.len() as u64, &format!("trajectory {}", index + 1));
    let mut insert_ms = 0.0;
    let mut scales = ScaleLearner::new(&opts.config);
    for scan in &scans {
        let local = Arc::new(LocalRangeMap::fit(&scan.train, &params)?);
        scales.observe(&scan.train, Arc::clone(&local), &mut world);
        let t0 = Instant::now();
        world.insert(&scan.train, &local)?;
        insert_ms += t0.elapsed().as_secs_f64() * 1e3;
        pose_gp.insert(&scan.train, &local)?;
        bar.inc(1);
    }
    bar.finish_and_clear();

    let (mut w_samples, mut p_samples, mut unobserved) = (Vec::new(), Vec::new(), 0);
    let mut train_points = Vec::new();
    let mut train_noise = Vec::new();
    let mut test_xy = Vec::new();
    let mut test_z = Vec::new();
    for scan in &scans {
        let t = &scan.train;
        let s = t.pose.translation.vector;
        for r in &t.rays {
            let w = t.pose.rotation * rangegp_sim::sensor::direction(r.inclination, r.azimuth);
            let p = s + w * r.range;
            train_points.push([p.x, p.y, p.z]);
            train_noise.push((t.range_noise_per_m * r.range).powi(2) + NUGGET_M2);
        }
        let angles: Vec<(f64, f64)> = scan.test.iter().map(|r| (r.inclination, r.azimuth)).collect();
        let (ranges, vars) = pose_gp
            .predict_ranges(&t.pose, &angles)
            .context("pose GP needs two scans")?;
        for ((ray, r), v) in scan.test.iter().zip(ranges).zip(vars) {
            p_samples.push(Sample {
                mean: s.z + r * ray.dir[2],
                sd: (v.sqrt() * ray.dir[2].abs()).max(1e-12),
                truth: ray.point[2],
            });
            test_xy.push((ray.point[0], ray.point[1]));
            test_z.push(ray.point[2]);
        }
    }
    for (&(x, y), &z) in test_xy.iter().zip(&test_z) {
        match world.elevation(x, y) {
            Some(e) => w_samples.push(Sample {
                mean: e.z,
                sd: e.var.sqrt().max(1e-12),
                truth: z,
            }),
            None => unobserved += 1,
        }
    }
    let batch = ElevationGp::fit(&train_points, &train_noise, kernels[2], JitterPolicy::default())?;
    let (bz, bv) = batch.predict_batch(&test_xy);
    let b_samples: Vec<Sample> = bz
        .iter()
        .zip(&bv)
        .zip(&test_z)
        .map(|((&m, &v), &z)| Sample {
            mean: m,
            sd: v.sqrt().max(1e-12),
            truth: z,
        })
        .collect();
    if let Some(out) = pictures {
        draw(
            out,
            terrain,
            traj,
            &world,
            opts.seed000_picture.then_some(&pose_gp),
        )?;
    }
    Ok(TrajectoryRow {
        scans: scans.len(),
        test_rays: test_z.len(),
        world: Scores::of(&w_samples).context("world aggregate answered nothing")?,
        world_unobserved: unobserved,
        seed000: Scores::of(&p_samples).context("no test rays")?,
        batch_elevation: Scores::of(&b_samples).context("no test rays")?,
        world_insert_ms: insert_ms / scans.len().max(1) as f64,
        world_tiles: world.tiles(),
        world_cells: world.len(),
    })
}

/// Heightmap with the trajectory; the world aggregate's elevation, |error| and σ around it (and
/// the seed-000 aggregate's |error| when given), as in seed 000's Fig. 3 and Fig. 6.
fn draw(
    out: &Path,
    terrain: &Heightmap,
    traj: &Trajectory,
    world: &WorldAggregate,
    seed000: Option<&PoseAugmentedGp>,
) -> Result<()> {
    let h = terrain.half_extent();
    let path: Vec<[f64; 2]> = traj.dense.clone();
    let whole = Raster::from_fn((-h, -h), (h, h), 0.25, |x, y| terrain.height(x, y));
    let zrange = whole
        .range()
        .map_or(Limits::Robust, |(lo, hi)| Limits::Fixed(lo, hi));
    Heatmap::new("Terrain and the rover's path", "elevation (m)")
        .limits(zrange)
        .path(&path)
        .save(&out.join("heightmap.png"), &whole)?;
    let fold = |f: fn(f64, f64) -> f64, init: f64, k: usize| path.iter().map(|p| p[k]).fold(init, f);
    let lo = (
        (fold(f64::min, f64::INFINITY, 0) - 11.0).max(-h),
        (fold(f64::min, f64::INFINITY, 1) - 11.0).max(-h),
    );
    let hi = (
        (fold(f64::max, f64::NEG_INFINITY, 0) + 11.0).min(h),
        (fold(f64::max, f64::NEG_INFINITY, 1) + 11.0).min(h),
    );
    let res = 0.25;
    let z = Raster::from_fn(lo, hi, res, |x, y| world.elevation(x, y).map(|e| e.z));
    let err = Raster::from_fn(lo, hi, res, |x, y| {
        Some((world.elevation(x, y)?.z - terrain.height(x, y)?).abs())
    });
    let sd = Raster::from_fn(lo, hi, res, |x, y| world.elevation(x, y).map(|e| e.var.sqrt()));
    let pictures = [
        (
            "aggregate_elevation.png",
            "Aggregate elevation",
            "elevation (m)",
            &z,
            zrange,
            colorous::VIRIDIS,
        ),
        (
            "aggregate_abs_error.png",
            "Aggregate absolute error",
            "|error| (m)",
            &err,
            Limits::Fixed(0.0, 0.1),
            colorous::INFERNO,
        ),
        (
            "aggregate_sigma.png",
            "Aggregate σ",
            "σ (m)",
            &sd,
            Limits::Robust,
            colorous::MAGMA,
        ),
    ];
    for (file, title, unit, raster, limits, gradient) in pictures {
        Heatmap::new(title, unit)
            .limits(limits)
            .gradient(gradient)
            .path(&path)
            .save(&out.join(file), raster)?;
    }
    if let Some(p) = seed000 {
        let err = Raster::from_fn(lo, hi, 0.5, |x, y| {
            Some((p.elevation(x, y)?.z - terrain.height(x, y)?).abs())
        });
        Heatmap::new("Seed 000 pose-augmented GP: absolute error", "|error| (m)")
            .limits(Limits::Fixed(0.0, 0.3))
            .gradient(colorous::INFERNO)
            .path(&path)
            .save(&out.join("seed000_abs_error.png"), &err)?;
    }
    Ok(())
}

/// Runs the experiment; pictures of the first trajectory go to `out`.
pub fn run_aggregate(terrain: &Heightmap, opts: &AggregateOptions, out: &Path) -> Result<AggregateReport> {
    let kernels = tune(terrain, opts)?;
    let tp = TrajectoryParams {
        min_length_m: opts.min_length_m,
        ..TrajectoryParams::default()
    };
    let trajs = plan_trajectories(terrain, opts.seed ^ 0x7a, opts.trajectories, tp)
        .context("no room for trajectories on this map")?;
    let mut rows = Vec::with_capacity(trajs.len());
    for (i, t) in trajs.iter().enumerate() {
        rows.push(run_trajectory(
            terrain,
            t,
            i,
            &kernels,
            opts,
            (i == 0).then_some(out),
        )?);
    }
    let rmse = |f: fn(&TrajectoryRow) -> f64| MeanSd::of(&rows.iter().map(f).collect::<Vec<_>>());
    let covered: f64 = rows
        .iter()
        .map(|r| r.world.coverage95 * r.world.count as f64)
        .sum();
    let count: usize = rows.iter().map(|r| r.world.count).sum();
    Ok(AggregateReport {
        world_rmse_z: rmse(|r| r.world.rmse),
        seed000_rmse_z: rmse(|r| r.seed000.rmse),
        batch_elev_rmse_z: rmse(|r| r.batch_elevation.rmse),
        world_coverage95: covered / count.max(1) as f64,
        kernels: kernels.map(|k| [k.variance, k.length_scale]),
        trajectories: rows,
    })
}

/// Prints the table beside seed 000's numbers.
pub fn print_aggregate(r: &AggregateReport) {
    println!(
        "\nAggregate mapping (seed 000 §V-B): {} trajectories, a scan every 5 m",
        r.trajectories.len()
    );
    println!("  traj scans test rays   world RMSE z  cov95   seed-000 RMSE z   batch elev RMSE z   world insert ms  tiles  cells");
    for (i, t) in r.trajectories.iter().enumerate() {
        println!(
            "  {:>4} {:>5} {:>9}   {:>12.4}  {:>5.3}   {:>15.4}   {:>17.4}   {:>15.1}  {:>5}  {:>5}",
            i + 1,
            t.scans,
            t.test_rays,
            t.world.rmse,
            t.world.coverage95,
            t.seed000.rmse,
            t.batch_elevation.rmse,
            t.world_insert_ms,
            t.world_tiles,
            t.world_cells
        );
    }
    println!(
        "  mean             world {:.4} ({:.4})   seed-000 {:.4} ({:.4})   batch elevation {:.4} ({:.4})",
        r.world_rmse_z.mean,
        r.world_rmse_z.sd,
        r.seed000_rmse_z.mean,
        r.seed000_rmse_z.sd,
        r.batch_elev_rmse_z.mean,
        r.batch_elev_rmse_z.sd
    );
    println!("  paper            range-GP aggregate 0.1442, batch elevation GP 0.0096");
    println!("  world aggregate pooled 95 % coverage {:.3}", r.world_coverage95);
}
