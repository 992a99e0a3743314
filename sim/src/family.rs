//! The evaluation family of terrains: besides the crater field, fractal relief (fBm) at several
//! Hurst exponents and amplitudes, a boulder field with steps and near-vertical faces, and
//! ramps with terraces. Each is seeded and large enough for a sensor's full range, so that map
//! quality and σ calibration are judged on terrain the defaults were never tuned on.

use crate::terrain::{value_noise, CraterParams, Heightmap};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// How a family member's heights are made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TerrainKind {
    /// The crater field of seed 000 (the terrain the defaults were tuned on).
    Craters,
    /// Fractional Brownian relief: octaves of value noise whose amplitude grows as
    /// wavelength^`hurst`, scaled so that the 95th percentile of the slope is `p95_slope_deg`.
    Fractal {
        /// Hurst exponent in (0, 1): 0.5 rough, 0.8 smooth and rolling.
        hurst: f64,
        /// 95th percentile of the slope angle, degrees.
        p95_slope_deg: f64,
    },
    /// Gentle relief strewn with flat-topped boulders 10–50 cm high, whose sides are steps
    /// one grid cell wide (near-vertical faces).
    Boulders,
    /// A ramp rising in x by terraces: treads of 3 m, risers of 0.3 m at 45°, with gentle relief.
    Terraces,
}

/// One member of the family.
#[derive(Debug, Clone, PartialEq)]
pub struct TerrainSpec {
    /// Stable short name (reports, file names).
    pub name: String,
    /// How it is made.
    pub kind: TerrainKind,
}

/// Side of the family's square terrains, metres: an OS1-64's 120 m range from the centre.
pub const FAMILY_SIZE_M: f64 = 260.0;
/// Grid spacing of the family's terrains, metres.
pub const FAMILY_RESOLUTION_M: f64 = 0.1;

/// The documented family: craters, fractal relief at three slopes (8°, 16°, 30° at the 95th
/// percentile) and two Hurst exponents, boulders, terraces.
pub fn family() -> Vec<TerrainSpec> {
    let mut specs = vec![TerrainSpec {
        name: "craters".into(),
        kind: TerrainKind::Craters,
    }];
    for (hurst, tag) in [(0.5, "h05"), (0.8, "h08")] {
        for slope in [8.0, 16.0, 30.0] {
            specs.push(TerrainSpec {
                name: format!("fbm-{tag}-{slope:.0}deg"),
                kind: TerrainKind::Fractal {
                    hurst,
                    p95_slope_deg: slope,
                },
            });
        }
    }
    specs.push(TerrainSpec {
        name: "boulders".into(),
        kind: TerrainKind::Boulders,
    });
    specs.push(TerrainSpec {
        name: "terraces".into(),
        kind: TerrainKind::Terraces,
    });
    specs
}

impl TerrainSpec {
    /// The terrain of side `size_m` from `seed`.
    pub fn build(&self, seed: u64, size_m: f64) -> Heightmap {
        let res = FAMILY_RESOLUTION_M;
        let n = (size_m / res).round() as usize + 1;
        let mut rng = Pcg64::seed_from_u64(seed ^ 0xfa417);
        match self.kind {
            TerrainKind::Craters => Heightmap::cratered(seed, &CraterParams::sized(size_m)),
            TerrainKind::Fractal { hurst, p95_slope_deg } => {
                let mut z = fbm(&mut rng, n, res, hurst);
                let scale = p95_slope_deg.to_radians().tan() / p95_slope(&z, n, res).max(1e-9);
                z.iter_mut().for_each(|v| *v *= scale);
                Heightmap::from_grid(size_m, res, z)
            }
            TerrainKind::Boulders => {
                let mut z = fbm(&mut rng, n, res, 0.8);
                let scale = 5f64.to_radians().tan() / p95_slope(&z, n, res).max(1e-9);
                z.iter_mut().for_each(|v| *v *= scale);
                let half = size_m / 2.0;
                let count = (size_m * size_m / 40.0) as usize;
                for _ in 0..count {
                    let c = [rng.random_range(-half..half), rng.random_range(-half..half)];
                    let radius = rng.random_range(0.3..1.2);
                    let height = rng.random_range(0.1..0.5);
                    stamp_boulder(&mut z, n, res, half, c, radius, height);
                }
                Heightmap::from_grid(size_m, res, z)
            }
            TerrainKind::Terraces => {
                let mut z = fbm(&mut rng, n, res, 0.8);
                let scale = 3f64.to_radians().tan() / p95_slope(&z, n, res).max(1e-9);
                let half = size_m / 2.0;
                for j in 0..n {
                    for i in 0..n {
                        let x = i as f64 * res - half;
                        z[j * n + i] = z[j * n + i] * scale + terrace(x);
                    }
                }
                Heightmap::from_grid(size_m, res, z)
            }
        }
    }
}

/// Height of the terraced ramp at `x`: 3 m treads, 0.3 m risers at 45°.
fn terrace(x: f64) -> f64 {
    let (tread, rise) = (3.0, 0.3);
    let k = (x / tread).floor();
    let within = x - k * tread;
    k * rise + (within - (tread - rise)).clamp(0.0, rise)
}

/// Raises a flat-topped boulder of `radius` and `height` centred at `c` (its side one cell wide).
fn stamp_boulder(z: &mut [f64], n: usize, res: f64, half: f64, c: [f64; 2], radius: f64, height: f64) {
    let to_index = |v: f64| ((v + half) / res).round().clamp(0.0, (n - 1) as f64) as usize;
    let (i0, i1) = (to_index(c[0] - radius), to_index(c[0] + radius));
    let (j0, j1) = (to_index(c[1] - radius), to_index(c[1] + radius));
    let base = z[to_index(c[1]) * n + to_index(c[0])];
    for j in j0..=j1 {
        for i in i0..=i1 {
            let (x, y) = (i as f64 * res - half, j as f64 * res - half);
            if (x - c[0]).hypot(y - c[1]) <= radius {
                let top = base + height;
                z[j * n + i] = z[j * n + i].max(top);
            }
        }
    }
}

/// Zero-mean fBm on an `n` × `n` grid of spacing `res`: value-noise octaves from 64 m down to
/// two cells, amplitude ∝ wavelength^`hurst`.
fn fbm(rng: &mut Pcg64, n: usize, res: f64, hurst: f64) -> Vec<f64> {
    let mut z = vec![0.0; n * n];
    let mut wavelength = 64.0;
    while wavelength >= 2.0 * res {
        let amp = wavelength.powf(hurst);
        value_noise(rng, n, res, wavelength, |k, v| z[k] += amp * v);
        wavelength /= 2.0;
    }
    let mean = z.iter().sum::<f64>() / z.len() as f64;
    z.iter_mut().for_each(|v| *v -= mean);
    z
}

/// 95th percentile of the gradient magnitude (rise over run) of a grid, from central differences
/// on a subsample of the samples.
pub fn p95_slope(z: &[f64], n: usize, res: f64) -> f64 {
    let step = (n / 400).max(1);
    let mut slopes = Vec::new();
    for j in (1..n - 1).step_by(step) {
        for i in (1..n - 1).step_by(step) {
            let gx = (z[j * n + i + 1] - z[j * n + i - 1]) / (2.0 * res);
            let gy = (z[(j + 1) * n + i] - z[(j - 1) * n + i]) / (2.0 * res);
            slopes.push(gx.hypot(gy));
        }
    }
    if slopes.is_empty() {
        return 0.0;
    }
    slopes.sort_by(f64::total_cmp);
    slopes[(slopes.len() - 1) * 95 / 100]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_family_is_seeded_and_its_slopes_are_the_documented_ones() {
        for spec in family() {
            let a = spec.build(3, 40.0);
            assert_eq!(
                a.samples(),
                spec.build(3, 40.0).samples(),
                "{}: same seed, same terrain",
                spec.name
            );
            assert!(a.samples().iter().all(|v| v.is_finite()), "{}", spec.name);
            if let TerrainKind::Fractal { p95_slope_deg, .. } = spec.kind {
                let n = (40.0 / FAMILY_RESOLUTION_M).round() as usize + 1;
                let z: Vec<f64> = a.samples().iter().map(|&v| v as f64).collect();
                let got = p95_slope(&z, n, FAMILY_RESOLUTION_M).atan().to_degrees();
                assert!(
                    (got - p95_slope_deg).abs() < 0.5,
                    "{}: p95 slope {got}°",
                    spec.name
                );
            }
        }
    }

    #[test]
    fn boulders_have_steps_and_terraces_rise() {
        let b = TerrainSpec {
            name: "boulders".into(),
            kind: TerrainKind::Boulders,
        }
        .build(1, 40.0);
        let n = (40.0 / FAMILY_RESOLUTION_M).round() as usize + 1;
        let z = b.samples();
        let steepest = (0..n * (n - 1))
            .filter(|k| k % n != n - 1)
            .map(|k| (z[k + 1] - z[k]).abs())
            .fold(0f32, f32::max);
        assert!(steepest > 0.1, "a step of at least 10 cm in one cell: {steepest}");
        assert!((terrace(6.0) - terrace(0.0) - 0.6).abs() < 1e-9);
        assert!((terrace(2.85) - 0.15).abs() < 1e-9, "half-way up the first riser");
    }
}
