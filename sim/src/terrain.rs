//! Heightmap terrain: lunar-style cratered ground, bilinear ground truth, exact ray casting.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Parameters of the cratered heightmap (defaults written out in docs/ARCHITECTURE.md).
#[derive(Debug, Clone, PartialEq)]
pub struct CraterParams {
    /// Side of the square map, metres.
    pub size_m: f64,
    /// Cell size, metres.
    pub resolution_m: f64,
    /// Smallest crater diameter, metres.
    pub d_min_m: f64,
    /// Largest crater diameter, metres.
    pub d_max_m: f64,
    /// Exponent b of the cumulative size–frequency law N(≥D) ∝ D^(−b).
    pub sfd_exponent: f64,
    /// Craters with D ≥ 1 m per square metre.
    pub density_per_m2_at_1m: f64,
    /// Bowl depth over diameter (fresh simple craters: about 0.2).
    pub depth_ratio: f64,
    /// Rim height over diameter.
    pub rim_ratio: f64,
    /// Amplitude of the fractal roughness at its coarsest octave, metres.
    pub roughness_m: f64,
}

impl CraterParams {
    /// The default parameters on a map of `size_m` metres.
    pub fn sized(size_m: f64) -> Self {
        Self {
            size_m,
            ..Self::default()
        }
    }
}

impl Default for CraterParams {
    fn default() -> Self {
        Self {
            size_m: 100.0,
            resolution_m: 0.05,
            d_min_m: 0.5,
            d_max_m: 20.0,
            sfd_exponent: 2.0,
            density_per_m2_at_1m: 0.01,
            depth_ratio: 0.2,
            rim_ratio: 0.04,
            roughness_m: 0.04,
        }
    }
}

/// A square grid of height samples with bilinear interpolation between them.
///
/// Sample (i, j) sits at (origin_x + i·res, origin_y + j·res); the map is centred on (0, 0).
#[derive(Debug, Clone)]
pub struct Heightmap {
    origin: [f64; 2],
    resolution: f64,
    n: usize,
    z: Vec<f32>,
    max_slope: f64,
}

impl Heightmap {
    /// A flat map at height `z` (useful in tests where the answer must be exact).
    pub fn flat(size_m: f64, resolution_m: f64, z: f64) -> Self {
        let n = (size_m / resolution_m).round() as usize + 1;
        Self::from_samples(size_m, resolution_m, vec![z as f32; n * n])
    }

    /// Generates the seeded cratered terrain.
    pub fn cratered(seed: u64, p: &CraterParams) -> Self {
        let n = (p.size_m / p.resolution_m).round() as usize + 1;
        let half = p.size_m / 2.0;
        let mut rng = Pcg64::seed_from_u64(seed);
        let mut z = fractal_roughness(&mut rng, n, p.resolution_m, p.roughness_m);
        let area = p.size_m * p.size_m;
        let cum = |d: f64| p.density_per_m2_at_1m * d.powf(-p.sfd_exponent);
        let count = ((cum(p.d_min_m) - cum(p.d_max_m)) * area).round() as usize;
        let (a, b) = (p.d_min_m.powf(-p.sfd_exponent), p.d_max_m.powf(-p.sfd_exponent));
        for _ in 0..count {
            let u: f64 = rng.random();
            let d = (a - u * (a - b)).powf(-1.0 / p.sfd_exponent);
            let cx = rng.random_range(-half..half);
            let cy = rng.random_range(-half..half);
            stamp_crater(&mut z, n, p.resolution_m, half, [cx, cy], d, p);
        }
        Self::from_samples(p.size_m, p.resolution_m, z)
    }

    /// A map of side `size_m` from row-major samples spaced `resolution` apart (panics when
    /// their count is not ((size / resolution) + 1)²: caller's misuse).
    pub fn from_grid(size_m: f64, resolution: f64, z: Vec<f64>) -> Self {
        Self::from_samples(size_m, resolution, z.into_iter().map(|v| v as f32).collect())
    }

    /// The same map with an object standing on it: the ground inside the axis-aligned box
    /// centred at (x, y) with half sides `half_m` raised by `height_m` (a boulder or a vehicle
    /// with vertical faces, at the map's resolution).
    pub fn with_box(&self, x: f64, y: f64, half_m: [f64; 2], height_m: f64) -> Self {
        let mut z = self.z.clone();
        for j in 0..self.n {
            for i in 0..self.n {
                let (px, py) = (
                    self.origin[0] + i as f64 * self.resolution,
                    self.origin[1] + j as f64 * self.resolution,
                );
                if (px - x).abs() <= half_m[0] && (py - y).abs() <= half_m[1] {
                    z[j * self.n + i] += height_m as f32;
                }
            }
        }
        Self::from_samples((self.n - 1) as f64 * self.resolution, self.resolution, z)
    }

    /// The height samples, row-major (y rows of x samples).
    pub fn samples(&self) -> &[f32] {
        &self.z
    }

    fn from_samples(size_m: f64, resolution: f64, z: Vec<f32>) -> Self {
        let n = (size_m / resolution).round() as usize + 1;
        assert_eq!(z.len(), n * n, "heightmap sample count");
        let mut max_slope: f64 = 0.0;
        for j in 0..n {
            for i in 0..n {
                let h = z[j * n + i] as f64;
                if i + 1 < n {
                    max_slope = max_slope.max((z[j * n + i + 1] as f64 - h).abs() / resolution);
                }
                if j + 1 < n {
                    max_slope = max_slope.max((z[(j + 1) * n + i] as f64 - h).abs() / resolution);
                }
            }
        }
        Self {
            origin: [-size_m / 2.0, -size_m / 2.0],
            resolution,
            n,
            z,
            // Bilinear patches can be steeper along a diagonal than along the axes.
            max_slope: max_slope * std::f64::consts::SQRT_2,
        }
    }

    /// Half the side length, metres: the map spans [−half, half]² around the origin.
    pub fn half_extent(&self) -> f64 {
        (self.n - 1) as f64 * self.resolution / 2.0
    }

    /// Cell size, metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Mean height of all samples, metres.
    pub fn mean_height(&self) -> f64 {
        self.z.iter().map(|&v| v as f64).sum::<f64>() / self.z.len() as f64
    }

    /// Ground-truth height at (x, y) by bilinear interpolation, or `None` outside the map.
    pub fn height(&self, x: f64, y: f64) -> Option<f64> {
        let gx = (x - self.origin[0]) / self.resolution;
        let gy = (y - self.origin[1]) / self.resolution;
        let last = (self.n - 1) as f64;
        if !(0.0..=last).contains(&gx) || !(0.0..=last).contains(&gy) {
            return None;
        }
        let i = (gx.floor() as usize).min(self.n - 2);
        let j = (gy.floor() as usize).min(self.n - 2);
        let (fx, fy) = (gx - i as f64, gy - j as f64);
        let at = |i: usize, j: usize| self.z[j * self.n + i] as f64;
        let bottom = at(i, j) * (1.0 - fx) + at(i + 1, j) * fx;
        let top = at(i, j + 1) * (1.0 - fx) + at(i + 1, j + 1) * fx;
        Some(bottom * (1.0 - fy) + top * fy)
    }

    /// Distance along the unit ray `dir` from `origin` to the first surface hit within
    /// `max_range`, or `None` (no hit, or the ray leaves the map first).
    ///
    /// Steps are bounded by the map's Lipschitz constant, so no crossing is skipped; the crossing
    /// is then bisected to 1e-7 m, so the result agrees with [`Heightmap::height`].
    pub fn cast(&self, origin: Vector3<f64>, dir: Vector3<f64>, max_range: f64) -> Option<f64> {
        let gap_at = |t: f64| -> Option<f64> {
            let p = origin + dir * t;
            self.height(p.x, p.y).map(|h| p.z - h)
        };
        let rate = dir.z.abs() + self.max_slope * dir.x.hypot(dir.y) + 1e-9;
        let mut t = 0.0;
        let mut gap = gap_at(t)?;
        if gap <= 0.0 {
            return None;
        }
        let min_step = self.resolution * 1e-3;
        while t < max_range {
            let step = (gap / rate).max(min_step);
            let t_next = (t + step).min(max_range);
            let g_next = gap_at(t_next)?;
            if g_next <= 0.0 {
                let (mut lo, mut hi) = (t, t_next);
                while hi - lo > 1e-7 {
                    let mid = 0.5 * (lo + hi);
                    match gap_at(mid) {
                        Some(g) if g > 0.0 => lo = mid,
                        _ => hi = mid,
                    }
                }
                return Some(0.5 * (lo + hi));
            }
            t = t_next;
            gap = g_next;
        }
        None
    }
}

fn stamp_crater(z: &mut [f32], n: usize, res: f64, half: f64, c: [f64; 2], d: f64, p: &CraterParams) {
    let r = d / 2.0;
    let depth = p.depth_ratio * d;
    let rim = p.rim_ratio * d;
    let reach = 2.5 * r;
    let to_index = |v: f64| ((v + half) / res).round();
    let i0 = to_index(c[0] - reach).max(0.0) as usize;
    let i1 = (to_index(c[0] + reach).max(0.0) as usize).min(n - 1);
    let j0 = to_index(c[1] - reach).max(0.0) as usize;
    let j1 = (to_index(c[1] + reach).max(0.0) as usize).min(n - 1);
    for j in j0..=j1 {
        let y = j as f64 * res - half;
        for i in i0..=i1 {
            let x = i as f64 * res - half;
            let q = (x - c[0]).hypot(y - c[1]) / r;
            let dz = if q < 1.0 {
                // Parabolic bowl from the floor (rim − depth) up to the rim crest.
                rim - depth * (1.0 - q * q)
            } else if q < 2.5 {
                // Ejecta blanket: rim height decaying as q^-3, faded to zero at the footprint edge.
                rim * q.powi(-3) * (1.0 - (q - 1.0) / 1.5)
            } else {
                0.0
            };
            z[j * n + i] += dz as f32;
        }
    }
}

/// Sum of three octaves of smooth value noise (wavelengths 8, 2 and 0.5 m).
fn fractal_roughness(rng: &mut Pcg64, n: usize, res: f64, amplitude: f64) -> Vec<f32> {
    let mut z = vec![0.0f32; n * n];
    for (wavelength, amp) in [(8.0, amplitude), (2.0, amplitude * 0.35), (0.5, amplitude * 0.1)] {
        value_noise(rng, n, res, wavelength, |k, v| z[k] += (amp * v) as f32);
    }
    z
}

/// One octave of smooth value noise of `wavelength` on an `n` × `n` grid of spacing `res`:
/// calls `add(k, v)` with v in [−1, 1] for every sample k, row-major.
pub(crate) fn value_noise(
    rng: &mut Pcg64,
    n: usize,
    res: f64,
    wavelength: f64,
    mut add: impl FnMut(usize, f64),
) {
    let cells = ((n - 1) as f64 * res / wavelength).ceil() as usize + 2;
    let lattice: Vec<f64> = (0..cells * cells).map(|_| rng.random_range(-1.0..1.0)).collect();
    for j in 0..n {
        let gy = j as f64 * res / wavelength;
        let (jy, fy) = (gy.floor() as usize, smooth(gy.fract()));
        for i in 0..n {
            let gx = i as f64 * res / wavelength;
            let (ix, fx) = (gx.floor() as usize, smooth(gx.fract()));
            let at = |a: usize, b: usize| lattice[b * cells + a];
            let v0 = at(ix, jy) * (1.0 - fx) + at(ix + 1, jy) * fx;
            let v1 = at(ix, jy + 1) * (1.0 - fx) + at(ix + 1, jy + 1) * fx;
            add(j * n + i, v0 * (1.0 - fy) + v1 * fy);
        }
    }
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Heightmap {
        let p = CraterParams::sized(30.0);
        Heightmap::cratered(7, &p)
    }

    #[test]
    fn same_seed_same_terrain() {
        let (a, b) = (small(), small());
        assert_eq!(a.z, b.z);
        let p = CraterParams::sized(30.0);
        assert_ne!(a.z, Heightmap::cratered(8, &p).z);
    }

    #[test]
    fn bilinear_height_hits_samples_and_is_none_outside() {
        let m = small();
        let r = m.resolution();
        let h = m.half_extent();
        let z00 = m.z[0] as f64;
        assert!((m.height(-h, -h).expect("inside") - z00).abs() < 1e-12);
        let mid = m.height(-h + 0.5 * r, -h).expect("inside");
        assert!((mid - 0.5 * (m.z[0] as f64 + m.z[1] as f64)).abs() < 1e-6);
        assert!(m.height(h + 0.01, 0.0).is_none());
    }

    #[test]
    fn cast_lands_on_the_interpolated_surface() {
        let m = small();
        let mut rng = Pcg64::seed_from_u64(3);
        let mut hits = 0;
        for _ in 0..300 {
            let origin = Vector3::new(
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
                m.height(0.0, 0.0).expect("inside") + 2.0,
            );
            let dir = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..-0.05),
            )
            .normalize();
            if origin.z <= m.height(origin.x, origin.y).expect("inside") {
                continue;
            }
            if let Some(t) = m.cast(origin, dir, 12.0) {
                let p = origin + dir * t;
                let g = m.height(p.x, p.y).expect("inside");
                assert!((p.z - g).abs() < 1e-5, "hit {t} off the surface by {}", p.z - g);
                hits += 1;
            }
        }
        assert!(hits > 200, "only {hits} hits");
    }

    #[test]
    fn flat_ground_cast_is_closed_form() {
        let m = Heightmap::flat(40.0, 0.05, 0.0);
        let dir = Vector3::new(1.0, 0.0, -0.1).normalize();
        let t = m.cast(Vector3::new(0.0, 0.0, 0.75), dir, 20.0).expect("hit");
        assert!((t - 0.75 / (-dir.z)).abs() < 1e-6);
    }

    #[test]
    fn a_box_raises_the_ground_inside_it_only() {
        let flat = Heightmap::flat(20.0, 0.1, 0.2);
        let with = flat.with_box(1.0, -2.0, [0.5, 0.3], 0.6);
        assert_eq!(with.height(1.0, -2.0), Some(0.8f32 as f64));
        assert_eq!(with.height(1.4, -1.8), Some(0.8f32 as f64));
        assert_eq!(with.height(1.7, -2.0), Some(0.2f32 as f64));
        assert_eq!(with.height(-3.0, 4.0), flat.height(-3.0, 4.0));
    }
}
