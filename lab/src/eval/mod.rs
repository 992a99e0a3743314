//! The seed-000 evaluation (`rangegp-eval`): Table I, the aggregate experiment and the overhang
//! scene, scored with [`scores`] and printed beside the paper's numbers.

pub mod aggregate;
pub mod bars;
pub mod calibration;
pub mod change;
pub mod drift;
mod drive;
pub mod layers;
pub mod local;
pub mod overhang;
pub mod progress;
pub mod scene;
pub mod scores;
pub mod sitemap;
pub mod split;
pub mod view;
pub mod world;

use aggregate::{print_aggregate, run_aggregate, AggregateOptions, AggregateReport};
use anyhow::Result;
use local::{print_local, run_local, LocalOptions, LocalReport};
use overhang::{print_overhang, run_overhang, OverhangOptions, OverhangReport};
use rangegp_service::config::Config;
use rangegp_sim::{CraterParams, Heightmap, ScannerPreset};
use serde::Serialize;
use std::path::PathBuf;

/// Which experiments to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Experiment {
    /// Table I: one scan at a time.
    Local,
    /// Five A* trajectories folded into the aggregates.
    Aggregate,
    /// The tunnel scene with the constant-range prior.
    Overhang,
    /// All three.
    All,
    /// σ calibration over the sim family of terrains × sensors × range bands (not in `all`):
    /// writes calibration.json.
    Calibration,
    /// Rays from poses never visited over ground only evicted scans saw (not in `all`): writes
    /// view.json.
    View,
    /// A drive of over 1 km with the daemon in this process and its site map (not in `all`):
    /// writes sitemap.json.
    Sitemap,
    /// A map that follows the world (not in `all`; built so far: motion deskew): writes
    /// world.json.
    World,
    /// Planner layers (slope, step, roughness, risk, cost) against the terrain's truth and A*
    /// over the cost layer (not in `all`): writes layers.json.
    Layers,
}

/// Command line of `rangegp-eval`.
#[derive(Debug, Clone, clap::Parser)]
#[command(
    version,
    about = "Reproduce seed 000 (Table I, the aggregate, overhangs) and score rangegp's maps"
)]
pub struct EvalOptions {
    /// Experiment to run.
    #[arg(value_enum)]
    pub experiment: Experiment,
    /// Reduced sizes for CI (a few minutes); the bars checked are the quick ones.
    #[arg(long)]
    pub quick: bool,
    /// World seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output folder for summary.json and the pictures.
    #[arg(long, default_value = "eval-out")]
    pub out: PathBuf,
    /// Daemon configuration the calibration, layers, view and world evaluations and the
    /// aggregate experiment's window maps run with (default: the embedded defaults), to compare
    /// settings on the same scenes; Table I and the overhang fit with seed 000's own settings,
    /// the site map with the defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Distance between consecutive scans of the calibration and layers drives, metres: 1 m is a
    /// rover at 10 m/s with a 10 Hz scanner, 0.1 m one at 1 m/s.
    #[arg(long, default_value_t = 1.0, value_parser = step_of)]
    pub step_m: f64,
    /// Scans the calibration and layers drives take after their last step, standing still.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u16).range(..=1000))]
    pub stop_scans: u16,
    /// Scans the calibration and layers drives take while moving (default: 20, 12 / 6 with
    /// `--quick`): with `--step-m` it sets how far the robot has come when it is scored.
    #[arg(long, value_parser = clap::value_parser!(u16).range(2..=1000))]
    pub scans: Option<u16>,
    /// Places along the calibration drive where its matrix is scored, [`calibration::END_SPACING_SCANS`]
    /// scans apart (default 1: where the drive ends after `--scans`). With N the drive goes on
    /// for N − 1 more places and each cell pools the points of all N: one place is one draw of
    /// the terrain under the robot (docs/EVALUATION.md "Calibration", step 13).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=50))]
    pub ends: u16,
    /// Height of every sensor above the ground in the calibration and layers drives, metres
    /// (default: each preset's, 0.75 m). The daemon's `gp.sensor_height_m` stays as configured:
    /// a robot whose mount the defaults do not know.
    #[arg(long, value_parser = mount_of)]
    pub mount_m: Option<f64>,
    /// How the sensors of the calibration and layers drives ride and which returns they lose.
    #[command(flatten)]
    pub sensor: crate::cli::SimSensorArgs,
    /// A DEM to run the calibration and layers evaluations on instead of the sim family.
    #[command(flatten)]
    pub dem: crate::dem::DemArgs,
}

impl EvalOptions {
    /// The daemon configuration of `--config`, else the embedded defaults.
    fn daemon_config(&self) -> Result<Config> {
        match &self.config {
            Some(path) => Ok(Config::load(path)?),
            None => Ok(Config::default()),
        }
    }
}

/// Parses `--mount-m`: a finite height in [0.2, 5] m.
fn mount_of(s: &str) -> std::result::Result<f64, String> {
    crate::cli::within(
        s,
        |v| (0.2..=5.0).contains(&v),
        "the mount height must lie in [0.2, 5] m",
    )
}

/// Parses `--step-m`: a finite step in (0, 5] m.
fn step_of(s: &str) -> std::result::Result<f64, String> {
    crate::cli::within(s, |v| v > 0.0 && v <= 5.0, "the step must lie in (0, 5] m")
}

/// What `summary.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// Quick (CI) or full sizes.
    pub quick: bool,
    /// World seed.
    pub seed: u64,
    /// Table I.
    pub local: Option<LocalSummary>,
    /// The aggregate experiment.
    pub aggregate: Option<AggregateSummary>,
    /// The overhang scene.
    pub overhang: Option<OverhangSummary>,
    /// Bars missed, one line each (empty: all met).
    pub failures: Vec<String>,
}

/// The local experiment's headline numbers and its full report.
#[derive(Debug, Clone, Serialize)]
pub struct LocalSummary {
    /// Range GP mean per-scan RMSE in z, metres.
    pub range_rmse_z: f64,
    /// Elevation GP mean per-scan RMSE in z, metres.
    pub elev_rmse_z: f64,
    /// Range GP 95 % coverage of z.
    pub coverage95: f64,
    /// Range GP NLPD of z.
    pub nlpd: f64,
    /// Range GP AUSE of z, metres.
    pub ause: f64,
    /// Everything measured.
    pub report: LocalReport,
}

/// The aggregate experiment's headline numbers and its full report.
#[derive(Debug, Clone, Serialize)]
pub struct AggregateSummary {
    /// The project's world aggregate: mean over trajectories of the RMSE in z, metres.
    pub rmse_z: f64,
    /// Seed 000's pose-augmented GP, same, metres.
    pub seed000_rmse_z: f64,
    /// Batch elevation GP, same, metres.
    pub batch_elev_rmse_z: f64,
    /// World aggregate pooled 95 % coverage.
    pub coverage95: f64,
    /// Everything measured.
    pub report: AggregateReport,
}

/// The overhang experiment's headline numbers and its full report.
#[derive(Debug, Clone, Serialize)]
pub struct OverhangSummary {
    /// Range GP (the project's form: inverse range) RMSE of the range along held-out rays, metres.
    pub ray_rmse: f64,
    /// Range GP in seed 000's form (range), same rays, metres.
    pub seed000_ray_rmse: f64,
    /// Elevation GP RMSE of the range along the same rays, metres.
    pub elevation_gp_ray_rmse: f64,
    /// Everything measured.
    pub report: OverhangReport,
}

/// Runs the selected experiments, prints their tables, writes summary.json.
pub fn run(opts: &EvalOptions) -> Result<Summary> {
    anyhow::ensure!(
        opts.dem.dem.is_none() || matches!(opts.experiment, Experiment::Calibration | Experiment::Layers),
        "--dem applies to the calibration and layers evaluations only"
    );
    if opts.experiment == Experiment::Calibration {
        return run_calibration_experiment(opts);
    }
    if opts.experiment == Experiment::View {
        return run_view_experiment(opts);
    }
    if opts.experiment == Experiment::World {
        let report = world::run_world(&FamilyOptions::of(opts)?)?;
        world::print_world(&report);
        let failures = report.failures.clone();
        return write_report(opts, "world.json", &report, failures);
    }
    if opts.experiment == Experiment::Layers {
        let report = layers::run_layers(&FamilyOptions::of(opts)?, &opts.out)?;
        layers::print_layers(&report);
        let failures = report.failures.clone();
        return write_report(opts, "layers.json", &report, failures);
    }
    if opts.experiment == Experiment::Sitemap {
        let report = sitemap::run_sitemap(&sitemap::SitemapOptions {
            quick: opts.quick,
            seed: opts.seed,
        })?;
        sitemap::print_sitemap(&report);
        let failures = report.failures.clone();
        return write_report(opts, "sitemap.json", &report, failures);
    }
    let want = |e: Experiment| opts.experiment == e || opts.experiment == Experiment::All;
    eprintln!("terrain: 100 m × 100 m at 5 cm, seed {} …", opts.seed);
    let terrain = Heightmap::cratered(opts.seed, &CraterParams::default());
    let mut summary = Summary {
        quick: opts.quick,
        seed: opts.seed,
        local: None,
        aggregate: None,
        overhang: None,
        failures: Vec::new(),
    };
    if want(Experiment::Local) {
        let n = if opts.quick { 20 } else { 100 };
        let report = run_local(
            &terrain,
            &LocalOptions {
                tune_scans: n,
                test_scans: n,
                seed: opts.seed,
            },
        )?;
        print_local(&report);
        summary.local = Some(LocalSummary {
            range_rmse_z: report.range.rmse_z_per_scan.mean,
            elev_rmse_z: report.elevation.rmse_z_per_scan.mean,
            coverage95: report.range.z.coverage95,
            nlpd: report.range.z.nlpd,
            ause: report.range.z.ause,
            report,
        });
    }
    std::fs::create_dir_all(&opts.out)?;
    if want(Experiment::Aggregate) {
        let report = run_aggregate(
            &terrain,
            &AggregateOptions {
                trajectories: if opts.quick { 2 } else { 5 },
                min_length_m: if opts.quick { 30.0 } else { 50.0 },
                tune_scans: if opts.quick { 10 } else { 30 },
                seed: opts.seed,
                seed000_picture: !opts.quick,
                config: opts.daemon_config()?,
            },
            &opts.out,
        )?;
        print_aggregate(&report);
        summary.aggregate = Some(AggregateSummary {
            rmse_z: report.world_rmse_z.mean,
            seed000_rmse_z: report.seed000_rmse_z.mean,
            batch_elev_rmse_z: report.batch_elev_rmse_z.mean,
            coverage95: report.world_coverage95,
            report,
        });
    }
    if want(Experiment::Overhang) {
        let report = run_overhang(
            &OverhangOptions {
                tune_scans: if opts.quick { 3 } else { 50 },
                test_scans: if opts.quick { 3 } else { 20 },
                seed: opts.seed,
            },
            &opts.out,
        )?;
        print_overhang(&report);
        summary.overhang = Some(OverhangSummary {
            ray_rmse: report.inverse_range.ray.rmse,
            seed000_ray_rmse: report.range.ray.rmse,
            elevation_gp_ray_rmse: report.elevation_gp_ray.rmse,
            report,
        });
    }
    summary.failures = bars::failures(&summary);
    if summary.failures.is_empty() {
        println!("\nAll {} bars met.", if opts.quick { "quick" } else { "full" });
    } else {
        println!("\nBars missed:");
        for f in &summary.failures {
            println!("  {f}");
        }
    }
    std::fs::write(
        opts.out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    Ok(summary)
}

/// How an evaluation over the sim family runs: its sizes, seed and the daemon configuration it
/// maps with (calibration, view and world).
#[derive(Debug, Clone)]
pub struct FamilyOptions {
    /// Reduced sizes (CI).
    pub quick: bool,
    /// World seed.
    pub seed: u64,
    /// The daemon configuration whose map, calibration and aggregate settings are used.
    pub config: Config,
    /// Distance between consecutive scans of the calibration and layers drives, metres.
    pub step_m: f64,
    /// Scans those drives take after their last step, standing still.
    pub stop_scans: usize,
    /// Scans those drives take while moving (`None`: each drive's own default).
    pub scans: Option<usize>,
    /// Places along the calibration drive where the matrix is scored (`--ends`).
    pub ends: usize,
    /// Sensor height above the ground in those drives, metres (`None`: each preset's own).
    pub mount_m: Option<f64>,
    /// Side of the chassis the sensor tilts with in those drives, metres (`None`: level).
    pub chassis_m: Option<f64>,
    /// Range at which those drives' sensors just detect a surface met squarely (`None`: every
    /// ray within range returns).
    pub weak_returns_m: Option<f64>,
    /// The DEM the calibration and layers evaluations run on instead of the family (`--dem`).
    pub dem: Option<crate::dem::DemTerrain>,
}

impl FamilyOptions {
    /// The CI form: quick sizes, seed 0, the embedded defaults.
    pub fn quick() -> Self {
        Self {
            quick: true,
            seed: 0,
            config: Config::default(),
            step_m: 1.0,
            stop_scans: 0,
            scans: None,
            ends: 1,
            mount_m: None,
            chassis_m: None,
            weak_returns_m: None,
            dem: None,
        }
    }

    /// The terrains of a calibration or layers run: the DEM, else the family (with `--quick`,
    /// the members named in `quick_names`).
    pub fn scenes(&self, quick_names: &[&str]) -> Vec<scene::Scene<'_>> {
        scene::scenes(self.dem.as_ref(), self.quick, quick_names)
    }

    /// `preset` mounted at `--mount-m` and losing weak returns beyond `--weak-returns-m`, when
    /// given.
    pub fn mounted(&self, preset: ScannerPreset) -> ScannerPreset {
        ScannerPreset {
            mount_height_m: self.mount_m.unwrap_or(preset.mount_height_m),
            weak_return_range_m: self.weak_returns_m.or(preset.weak_return_range_m),
            ..preset
        }
    }

    /// Scans a drive takes while moving: `--scans`, else `full` (`quick` with `--quick`).
    pub fn drive_scans(&self, full: usize, quick: usize) -> usize {
        self.scans.unwrap_or(if self.quick { quick } else { full })
    }

    /// From the command line (`--config`, else the embedded defaults).
    fn of(opts: &EvalOptions) -> Result<Self> {
        Ok(Self {
            quick: opts.quick,
            seed: opts.seed,
            config: opts.daemon_config()?,
            step_m: opts.step_m,
            stop_scans: usize::from(opts.stop_scans),
            scans: opts.scans.map(usize::from),
            ends: usize::from(opts.ends),
            mount_m: opts.mount_m,
            chassis_m: opts.sensor.chassis_m,
            weak_returns_m: opts.sensor.weak_returns_m,
            dem: opts.dem.load()?,
        })
    }
}

/// `rangegp-eval view`: rays over evicted ground, printed and written to view.json.
fn run_view_experiment(opts: &EvalOptions) -> Result<Summary> {
    let report = view::run_view(&FamilyOptions::of(opts)?)?;
    view::print_view(&report);
    let failures = report.failures.clone();
    write_report(opts, "view.json", &report, failures)
}

/// `rangegp-eval calibration`: the σ matrix, printed and written to calibration.json.
fn run_calibration_experiment(opts: &EvalOptions) -> Result<Summary> {
    let report = calibration::run_calibration(&FamilyOptions::of(opts)?)?;
    calibration::print_calibration(&report);
    for file in calibration::write_reliability_pictures(&report, &opts.out)? {
        println!("  reliability diagram: {}", file.display());
    }
    if report.failures.is_empty() {
        println!("\nEvery cell with n ≥ {} calibrated.", calibration::MIN_CELL_N);
    }
    let failures = report.failures.clone();
    write_report(opts, "calibration.json", &report, failures)
}

/// Writes an experiment's own report as `<out>/<file>`, prints the bars it missed, and returns
/// them as the run's summary (the experiments outside `all` have no place in summary.json).
fn write_report(
    opts: &EvalOptions,
    file: &str,
    report: &impl Serialize,
    failures: Vec<String>,
) -> Result<Summary> {
    std::fs::create_dir_all(&opts.out)?;
    let path = opts.out.join(file);
    std::fs::write(&path, serde_json::to_string_pretty(report)?)?;
    for f in &failures {
        println!("  bar missed: {f}");
    }
    println!("\n  written: {}", path.display());
    Ok(Summary {
        quick: opts.quick,
        seed: opts.seed,
        local: None,
        aggregate: None,
        overhang: None,
        failures,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn scans_set_the_drives_length_and_a_single_scan_is_refused() {
        let parse =
            |args: &[&str]| EvalOptions::try_parse_from(["rangegp-eval", "layers"].iter().chain(args));
        let opts = parse(&["--scans", "60"]).expect("parsed");
        assert_eq!(opts.scans, Some(60));
        let family = FamilyOptions::of(&opts).expect("defaults");
        assert_eq!(family.drive_scans(20, 12), 60);
        let quick = FamilyOptions::quick();
        assert_eq!((quick.drive_scans(20, 12), quick.drive_scans(20, 6)), (12, 6));
        let full = FamilyOptions::of(&parse(&[]).expect("parsed")).expect("defaults");
        assert_eq!(full.drive_scans(20, 12), 20);
        assert!(
            parse(&["--scans", "1"]).is_err(),
            "a drive of one scan has no step"
        );
    }

    #[test]
    fn ends_default_to_one_place_and_none_is_refused() {
        let parse =
            |args: &[&str]| EvalOptions::try_parse_from(["rangegp-eval", "calibration"].iter().chain(args));
        let of = |args: &[&str]| FamilyOptions::of(&parse(args).expect("parsed")).expect("defaults");
        assert_eq!(
            (
                of(&[]).ends,
                of(&["--ends", "5"]).ends,
                FamilyOptions::quick().ends
            ),
            (1, 5, 1)
        );
        assert!(parse(&["--ends", "0"]).is_err(), "no place to score");
    }

    #[test]
    fn a_dem_is_taken_by_calibration_and_layers_only_and_its_scales_need_it() {
        let parse = |args: &[&str]| EvalOptions::try_parse_from(["rangegp-eval"].iter().chain(args));
        let opts = parse(&[
            "layers",
            "--dem",
            "x.asc",
            "--dem-cell-m",
            "0.25",
            "--dem-relief",
            "0.5",
        ])
        .expect("parsed");
        assert_eq!(
            (opts.dem.dem_cell_m, opts.dem.dem_relief),
            (Some(0.25), Some(0.5))
        );
        assert!(
            parse(&["calibration", "--dem-cell-m", "0.25"]).is_err(),
            "a cell size alone"
        );
        assert!(
            parse(&["calibration", "--dem-relief", "2"]).is_err(),
            "a relief alone"
        );
        for bad in ["0", "-1", "nan", "1000"] {
            for flag in ["--dem-relief", "--dem-cell-m"] {
                let refused = parse(&["layers", "--dem", "x.asc", &format!("{flag}={bad}")]);
                let kind = refused.map(|_| ()).map_err(|e| e.kind());
                assert_eq!(kind, Err(clap::error::ErrorKind::ValueValidation), "{flag}={bad}");
            }
        }
        let world = parse(&["world", "--dem", "x.asc"]).expect("parsed");
        let refused = run(&world).expect_err("world runs on its own scenes");
        assert!(refused.to_string().contains("--dem"), "{refused}");
        let missing = FamilyOptions::of(&opts).expect_err("no such file");
        assert!(format!("{missing:#}").contains("x.asc"), "{missing:#}");
    }

    #[test]
    fn a_mount_height_moves_every_sensor_and_an_absurd_one_is_refused() {
        let parse =
            |args: &[&str]| EvalOptions::try_parse_from(["rangegp-eval", "calibration"].iter().chain(args));
        let family = FamilyOptions::of(&parse(&["--mount-m", "1.5"]).expect("parsed")).expect("defaults");
        let vlp16 = ScannerPreset::vlp16();
        assert_eq!(family.mounted(vlp16.clone()).mount_height_m, 1.5);
        assert_eq!(FamilyOptions::quick().mounted(vlp16.clone()), vlp16);
        for bad in ["0", "-1", "9", "nan"] {
            assert!(parse(&["--mount-m", bad]).is_err(), "{bad} m accepted");
        }
    }
}
