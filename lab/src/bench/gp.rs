//! `rangegp-bench gp`: the GP engine's speed on this machine, with numpy / scikit-learn peers
//! measured in the same run when a Python with them is available. Medians, not single runs.

use crate::scangen::to_message;
use anyhow::{Context, Result};
use faer::Mat;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rangegp_service::config::Config;
use rangegp_service::gp::{factor_with_jitter, sphere, ExactGp, JitterPolicy, Kernel};
use rangegp_service::ingest::validate::{validate, ValidationLimits};
use rangegp_service::map::local::{embedding_of, hyper_sample, LocalRangeMap, MapParams};
use rangegp_service::scan::ScanInput;
use rangegp_sim::{simulate_scan, CraterParams, Heightmap, Path, ScannerPreset};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

/// Rays per call in the batched prediction measurement (a planner's batch or a grid block).
const PREDICT_BATCH: usize = 4096;
/// Options of `rangegp-bench gp`.
#[derive(Debug, Clone, clap::Args)]
pub struct GpBenchOptions {
    /// Timed repeats per measurement (medians are reported).
    #[arg(long, default_value_t = 7)]
    pub repeats: usize,
    /// Output folder for gp.json.
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
    /// Python with numpy and scikit-learn for the peers (default: python3 on PATH).
    #[arg(long, default_value = "python3")]
    pub python: PathBuf,
}

/// Fit-time distribution of one sensor.
#[derive(Debug, Clone, Serialize)]
pub struct FitTiming {
    /// Returned rays per scan (mean).
    pub rays: f64,
    /// Local experts per scan (mean).
    pub tiles: f64,
    /// Median, milliseconds.
    pub p50_ms: f64,
    /// 90th percentile, milliseconds.
    pub p90_ms: f64,
}

/// Everything `gp.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct GpReport {
    /// Median fit time of a seed-000 scan, ms.
    pub seed000_fit_p50_ms: f64,
    /// Median fit time of a VLP-16 scan, ms.
    pub vlp16_fit_p50_ms: f64,
    /// Median fit time of an OS1-64 (64 × 1024) scan, ms.
    pub os1_64_fit_p50_ms: f64,
    /// Per-sensor details.
    pub fits: BTreeMap<String, FitTiming>,
    /// faer Cholesky GFLOP/s (one thread) by n.
    pub chol_gflops: BTreeMap<String, f64>,
    /// numpy / OpenBLAS Cholesky GFLOP/s (one thread) by n, when numpy is present.
    pub openblas_gflops: Option<BTreeMap<String, f64>>,
    /// faer / OpenBLAS by n.
    pub chol_ratio: Option<BTreeMap<String, f64>>,
    /// Mean + variance predictions per second on one core (tiled seed-000 map, batches of 4096
    /// rays: the path of batched queries and grids).
    pub predict_points_per_s_per_core: f64,
    /// The same, one ray per call (the latency path of single-point queries).
    pub predict_single_points_per_s_per_core: f64,
    /// Exact GP, equal size: rangegp fit + batched predict, seconds.
    pub exact_fit_predict_s: f64,
    /// scikit-learn fit + predict(return_std) on the same data, seconds.
    pub sklearn_fit_predict_s: Option<f64>,
    /// scikit-learn (exact GP) time / rangegp engine (tiled experts, the daemon's model) time,
    /// same training rays and queries.
    pub sklearn_fit_predict_speedup: Option<f64>,
    /// Tiled experts (the daemon's model) fit + predict on the same data, seconds.
    pub tiled_fit_predict_s: f64,
    /// scikit-learn time / rangegp exact GP time: the same O(n³) + O(m n²) work on both sides.
    pub sklearn_exact_vs_exact_speedup: Option<f64>,
    /// Training rays and queries of the scikit-learn comparison.
    pub sklearn_problem: [usize; 2],
    /// numpy and scikit-learn versions used.
    pub peer_versions: Option<String>,
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn p90(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * 0.9).round() as usize]
}

fn time<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let out = f();
    (out, t.elapsed().as_secs_f64())
}

/// Scans of `preset` along a wander path on the default cratered terrain, validated exactly as
/// the daemon validates them.
pub(crate) fn scans(
    terrain: &Heightmap,
    preset: &ScannerPreset,
    count: usize,
    seed: u64,
) -> Result<Vec<ScanInput>> {
    let path = Path::wander(seed, terrain, count, 4.0, 0.3);
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..count)
        .map(|i| {
            let pose = path.pose(terrain, i, preset.mount_height_m);
            let rays = simulate_scan(terrain, &pose, preset, &mut rng);
            let (mut header, points) = to_message(preset, &pose, &rays, 0);
            header.sequence = i as u64;
            let limits = ValidationLimits {
                max_points: 1 << 20,
                max_future_ns: u64::MAX,
                learn_noise_floor: true,
            };
            validate(&header, &points, &limits, 0)
                .map_err(|r| anyhow::anyhow!("simulated scan rejected: {}", r.as_str()))
        })
        .collect()
}

/// One fit as the daemon does it: tiled experts plus one online hyperparameter step.
fn fit_like_the_daemon(
    scan: &ScanInput,
    params: &MapParams,
    config: &Config,
) -> Result<(LocalRangeMap, f64)> {
    let mut online = config.online_hyperparameters();
    let (map, secs) = time(|| -> Result<LocalRangeMap> {
        let map = LocalRangeMap::fit(scan, params)?;
        let sample = hyper_sample(scan, params, config.gp.online.subset_rays);
        online.update(sample.as_training_set())?;
        Ok(map)
    });
    Ok((map?, secs))
}

/// Runs the GP benchmark and writes `gp.json`.
pub fn run_gp(opts: &GpBenchOptions) -> Result<GpReport> {
    let repeats = opts.repeats.max(3);
    std::fs::create_dir_all(&opts.out)?;
    let config = Config::default();
    let params = config.map_params();
    eprintln!("[1/4] terrain 100 m × 100 m at 5 cm …");
    let terrain = Heightmap::cratered(0, &CraterParams::default());

    eprintln!("[2/4] Cholesky, one thread …");
    let mut rng = Pcg64::seed_from_u64(7);
    let sizes = [128usize, 256, 512, 1024, 2048];
    let mut chol_gflops = BTreeMap::new();
    for &n in &sizes {
        let pts: Vec<[f64; 3]> = (0..n)
            .map(|_| sphere::to_sphere(rng.random_range(1.4..1.9), rng.random_range(-3.1..3.1), 10.0))
            .collect();
        let k = Kernel::matern32(2.3, 1.2);
        let m = Mat::from_fn(n, n, |i, j| {
            k.between(&pts[i], &pts[j]) + if i == j { 1e-2 } else { 0.0 }
        });
        let reps = (2048 / n).clamp(3, 16).max(repeats);
        let mut t: Vec<f64> = (0..reps)
            .map(|_| time(|| factor_with_jitter(&m, JitterPolicy::default()).map(|_| ())).1)
            .collect();
        let g = (n as f64).powi(3) / 3.0 / median(&mut t) / 1e9;
        eprintln!("      n = {n:>4}: {g:6.1} GFLOP/s");
        chol_gflops.insert(n.to_string(), g);
    }

    eprintln!(
        "[3/4] full-scan fits (tiles + Cholesky + hyperparameter step, {} threads) …",
        rayon::current_num_threads()
    );
    let mut fits = BTreeMap::new();
    let presets = [
        ScannerPreset::seed000(),
        ScannerPreset::vlp16(),
        ScannerPreset::os1_64(1024),
    ];
    let mut seed_map = None;
    for preset in &presets {
        let inputs = scans(&terrain, preset, 5, 11)?;
        let mut times = Vec::new();
        let mut tiles = 0.0;
        for _ in 0..repeats.div_ceil(inputs.len()).max(2) {
            for scan in &inputs {
                let (map, secs) = fit_like_the_daemon(scan, &params, &config)?;
                tiles += map.tiles() as f64;
                times.push(secs * 1e3);
                if preset.name == "seed000" {
                    seed_map.get_or_insert(map);
                }
            }
        }
        let rays = inputs.iter().map(|s| s.rays.len()).sum::<usize>() as f64 / inputs.len() as f64;
        let t = FitTiming {
            rays,
            tiles: tiles / times.len() as f64,
            p50_ms: median(&mut times),
            p90_ms: p90(&mut times),
        };
        eprintln!(
            "      {:<8} {:>7.0} rays {:>5.0} tiles: p50 {:7.1} ms, p90 {:7.1} ms",
            preset.name, t.rays, t.tiles, t.p50_ms, t.p90_ms
        );
        fits.insert(preset.name.to_string(), t);
    }

    eprintln!("[4/4] prediction throughput and peers …");
    let map = seed_map.context("no seed-000 map")?;
    let angles: Vec<(f64, f64)> = (0..20_000)
        .map(|_| (rng.random_range(1.58..1.82), rng.random_range(-1.5..1.5)))
        .collect();
    let mut rates: Vec<f64> = (0..repeats)
        .map(|_| {
            let (sum, secs) = time(|| {
                angles
                    .iter()
                    .map(|&(t, p)| map.predict_range(t, p).1)
                    .sum::<f64>()
            });
            std::hint::black_box(sum);
            angles.len() as f64 / secs
        })
        .collect();
    let predict_single_rate = median(&mut rates);
    let mut rates: Vec<f64> = (0..repeats)
        .map(|_| {
            let (sum, secs) = time(|| {
                angles
                    .chunks(PREDICT_BATCH)
                    .flat_map(|batch| map.predict_ranges(batch))
                    .map(|(_, v)| v)
                    .sum::<f64>()
            });
            std::hint::black_box(sum);
            angles.len() as f64 / secs
        })
        .collect();
    let predict_rate = median(&mut rates);

    // The scikit-learn problem: one seed-000 scan, all returns, exact GP; 4096 queries.
    let scan = &scans(&terrain, &presets[0], 1, 99)?[0];
    let sample = hyper_sample(scan, &params, usize::MAX);
    let embedding = embedding_of(scan, &params);
    let queries: Vec<[f64; 3]> = angles
        .iter()
        .take(4096)
        .map(|&(t, p)| embedding.point(t, p))
        .collect();
    let mut exact_t: Vec<f64> = (0..repeats)
        .map(|_| {
            time(|| {
                let gp = ExactGp::fit(
                    params.kernel,
                    sample.inputs.clone(),
                    &sample.targets,
                    &sample.noise_var,
                    params.jitter,
                );
                gp.map(|gp| gp.predict_batch(&queries))
            })
            .1
        })
        .collect();
    let exact_s = median(&mut exact_t);
    let tiled_rays: Vec<rangegp_service::map::tiles::TrainingRay> = sample
        .inputs
        .iter()
        .zip(&sample.targets)
        .zip(&sample.noise_var)
        .map(|((x, &r), &v)| {
            let (inclination, azimuth) = sphere::angles_of(*x);
            rangegp_service::map::tiles::TrainingRay {
                inclination,
                azimuth,
                residual: r,
                noise_var: v,
            }
        })
        .collect();
    let mut tiled_t: Vec<f64> = (0..repeats)
        .map(|_| {
            time(|| {
                let gp = rangegp_service::map::tiles::TiledGp::fit(
                    &tiled_rays,
                    params.kernel,
                    embedding,
                    params.tiling,
                    params.jitter,
                );
                gp.map(|gp| {
                    angles
                        .iter()
                        .take(4096)
                        .map(|&(t, p)| gp.mean_variance(t, p).1)
                        .sum::<f64>()
                })
            })
            .1
        })
        .collect();
    let tiled_s = median(&mut tiled_t);
    let peers = run_peers(
        opts,
        &sizes,
        &sample.inputs,
        &sample.targets,
        &sample.noise_var,
        &queries,
        &params,
        repeats,
    );
    let (openblas, sk_s, versions) = match peers {
        Ok(p) => p,
        Err(e) => {
            eprintln!("      peers unavailable ({e}); reporting rangegp alone");
            (None, None, None)
        }
    };
    let chol_ratio = openblas.as_ref().map(|o: &BTreeMap<String, f64>| {
        chol_gflops
            .iter()
            .filter_map(|(n, g)| o.get(n).map(|b| (n.clone(), g / b)))
            .collect()
    });
    let report = GpReport {
        seed000_fit_p50_ms: fits["seed000"].p50_ms,
        vlp16_fit_p50_ms: fits["vlp16"].p50_ms,
        os1_64_fit_p50_ms: fits["os1-64"].p50_ms,
        fits,
        chol_gflops,
        openblas_gflops: openblas,
        chol_ratio,
        predict_points_per_s_per_core: predict_rate,
        predict_single_points_per_s_per_core: predict_single_rate,
        exact_fit_predict_s: exact_s,
        sklearn_fit_predict_s: sk_s,
        sklearn_fit_predict_speedup: sk_s.map(|s| s / tiled_s),
        tiled_fit_predict_s: tiled_s,
        sklearn_exact_vs_exact_speedup: sk_s.map(|s| s / exact_s),
        sklearn_problem: [sample.inputs.len(), queries.len()],
        peer_versions: versions,
    };
    std::fs::write(opts.out.join("gp.json"), serde_json::to_string_pretty(&report)?)?;
    Ok(report)
}

type Peers = (Option<BTreeMap<String, f64>>, Option<f64>, Option<String>);

#[allow(clippy::too_many_arguments)]
fn run_peers(
    opts: &GpBenchOptions,
    sizes: &[usize],
    x: &[[f64; 3]],
    y: &[f64],
    noise: &[f64],
    queries: &[[f64; 3]],
    params: &MapParams,
    repeats: usize,
) -> Result<Peers> {
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../bench/peers/peers.py");
    let spec = serde_json::json!({
        "chol_sizes": sizes, "train_x": x, "train_y": y, "noise_var": noise, "query_x": queries,
        "variance": params.kernel.variance, "length_scale": params.kernel.length_scale, "repeats": repeats,
    });
    let file = opts.out.join("peers-input.json");
    std::fs::write(&file, serde_json::to_vec(&spec)?)?;
    let out = Command::new(&opts.python)
        .arg(&script)
        .arg(&file)
        .env("OPENBLAS_NUM_THREADS", "1")
        .env("OMP_NUM_THREADS", "1")
        .output()
        .with_context(|| format!("running {}", opts.python.display()))?;
    std::fs::remove_file(&file).ok();
    anyhow::ensure!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
            .lines()
            .last()
            .unwrap_or("failed")
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    let openblas = serde_json::from_value(v["openblas_gflops"].clone())?;
    let sk = v["sklearn_fit_s"]
        .as_f64()
        .zip(v["sklearn_predict_s"].as_f64())
        .map(|(a, b)| a + b);
    let versions = format!(
        "numpy {}, scikit-learn {}",
        v["numpy"].as_str().unwrap_or("?"),
        v["sklearn"].as_str().unwrap_or("?")
    );
    Ok((Some(openblas), sk, Some(versions)))
}

/// Prints the benchmark table.
pub fn print_gp(r: &GpReport) {
    println!("\nrangegp GP engine benchmark (this machine, medians)");
    println!("  Cholesky GFLOP/s, one thread     n:  faer   OpenBLAS   ratio");
    let mut sizes: Vec<(&String, &f64)> = r.chol_gflops.iter().collect();
    sizes.sort_by_key(|(n, _)| n.parse::<usize>().unwrap_or(usize::MAX));
    for (n, g) in sizes {
        let b = r.openblas_gflops.as_ref().and_then(|o| o.get(n)).copied();
        match b {
            Some(b) => println!(
                "                               {n:>6}: {g:6.1}   {b:6.1}   {:5.2}",
                g / b
            ),
            None => println!("                               {n:>6}: {g:6.1}      —"),
        }
    }
    for (name, t) in &r.fits {
        println!(
            "  full-scan fit {name:<8} {:>7.0} rays, {:>4.0} tiles: p50 {:7.1} ms  p90 {:7.1} ms",
            t.rays, t.tiles, t.p50_ms, t.p90_ms
        );
    }
    println!(
        "  prediction (mean + variance)     {:>10.0} points/s/core in batches of {PREDICT_BATCH}, {:.0} one at a time",
        r.predict_points_per_s_per_core, r.predict_single_points_per_s_per_core
    );
    let [n, m] = r.sklearn_problem;
    println!(
        "  fit + predict, {n} rays, {m} queries: rangegp exact {:.3} s, tiled {:.3} s",
        r.exact_fit_predict_s, r.tiled_fit_predict_s
    );
    match (
        r.sklearn_fit_predict_s,
        r.sklearn_exact_vs_exact_speedup,
        r.sklearn_fit_predict_speedup,
    ) {
        (Some(s), Some(x), Some(t)) => println!(
            "  scikit-learn (exact) {s:.3} s: ×{x:.1} vs rangegp exact, ×{t:.1} vs rangegp tiled ({})",
            r.peer_versions.as_deref().unwrap_or("")
        ),
        _ => println!("  scikit-learn: not available (pass --python with numpy and scikit-learn)"),
    }
}
