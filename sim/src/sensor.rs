//! LiDAR presets and scan simulation against any [`Surface`].

use crate::scene::Surface;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;

/// A spinning LiDAR: ring inclinations × column azimuths, with its range limit and noise.
#[derive(Debug, Clone, PartialEq)]
pub struct ScannerPreset {
    /// Short name (`seed000`, `vlp16`, `os1-64`).
    pub name: &'static str,
    /// Polar angle of each ring from the sensor's +z axis, radians (π/2 is horizontal).
    pub inclinations_rad: Vec<f64>,
    /// Azimuth of each column, radians.
    pub azimuths_rad: Vec<f64>,
    /// Maximum range, metres; rays reaching it give no return.
    pub max_range_m: f64,
    /// Range noise standard deviation per metre of range.
    pub range_noise_per_m: f64,
    /// Range noise standard deviation at any range, metres: with the per-metre part, σ(r) =
    /// √(floor² + (per_m · r)²). Real devices have one (a VLP-16 about 3 cm); a scan header has no
    /// field for it, so a driver cannot tell the daemon ([`ScannerPreset::with_device_noise`]).
    pub range_noise_floor_m: f64,
    /// Height of the sensor above the ground, metres.
    pub mount_height_m: f64,
    /// Range at which a return from a surface met squarely is just detected, metres (`None`:
    /// every ray that meets a surface within `max_range_m` returns). The returned power falls as
    /// cos(incidence) / r², so a surface met at incidence α returns to this range × √cos α:
    /// grazed ground far out gives nothing back, as on a real device
    /// ([`ScannerPreset::with_weak_returns`]).
    pub weak_return_range_m: Option<f64>,
}

/// Seed-000 / VLP-16 noise: σ = 0.75 cm at 29 m, linear in range.
pub const SEED000_NOISE_PER_M: f64 = 0.0075 / 29.0;
/// A Velodyne VLP-16's range noise at any range, metres (its datasheet's typical accuracy,
/// ±3 cm).
pub const VLP16_NOISE_FLOOR_M: f64 = 0.03;
/// An Ouster OS1-64's range noise floor, metres: with the per-metre part 1.5 cm near, 3.5 cm at
/// 120 m (its datasheet's precision, 1.5–5 cm by range and reflectivity).
pub const OS1_NOISE_FLOOR_M: f64 = 0.015;

fn linspace(from: f64, to: f64, count: usize) -> Vec<f64> {
    if count == 1 {
        return vec![from];
    }
    (0..count)
        .map(|i| from + (to - from) * i as f64 / (count - 1) as f64)
        .collect()
}

fn elevations_to_inclinations(elevations_deg: Vec<f64>) -> Vec<f64> {
    elevations_deg
        .into_iter()
        .map(|e| (90.0 - e).to_radians())
        .collect()
}

impl ScannerPreset {
    /// The scanner of seed 000 §IV: elevations −15°..0° by 1°, azimuths −90°..90° by 2°, 10 m,
    /// 0.75 m above the ground.
    pub fn seed000() -> Self {
        Self {
            name: "seed000",
            inclinations_rad: elevations_to_inclinations(linspace(-15.0, 0.0, 16)),
            azimuths_rad: linspace(-90f64.to_radians(), 90f64.to_radians(), 91),
            max_range_m: 10.0,
            range_noise_per_m: SEED000_NOISE_PER_M,
            range_noise_floor_m: 0.0,
            mount_height_m: 0.75,
            weak_return_range_m: None,
        }
    }

    /// Velodyne VLP-16: 16 rings over ±15°, 0.2° azimuth steps (1800 columns), 100 m.
    pub fn vlp16() -> Self {
        Self {
            name: "vlp16",
            inclinations_rad: elevations_to_inclinations(linspace(-15.0, 15.0, 16)),
            azimuths_rad: full_turn(1800),
            max_range_m: 100.0,
            range_noise_per_m: SEED000_NOISE_PER_M,
            range_noise_floor_m: 0.0,
            mount_height_m: 0.75,
            weak_return_range_m: None,
        }
    }

    /// Ouster OS1-64: 64 rings over ±22.5°, `columns` azimuth steps (1024 or 2048), 120 m.
    pub fn os1_64(columns: usize) -> Self {
        Self {
            name: "os1-64",
            inclinations_rad: elevations_to_inclinations(linspace(-22.5, 22.5, 64)),
            azimuths_rad: full_turn(columns),
            max_range_m: 120.0,
            range_noise_per_m: SEED000_NOISE_PER_M,
            range_noise_floor_m: 0.0,
            mount_height_m: 0.75,
            weak_return_range_m: None,
        }
    }

    /// Looks a preset up by name (`seed000`, `vlp16`, `os1-64`).
    pub fn by_name(name: &str) -> Option<Self> {
        match name {
            "seed000" => Some(Self::seed000()),
            "vlp16" => Some(Self::vlp16()),
            "os1-64" => Some(Self::os1_64(1024)),
            _ => None,
        }
    }

    /// This preset with its device's own range noise: a floor that holds at every range
    /// ([`VLP16_NOISE_FLOOR_M`], [`OS1_NOISE_FLOOR_M`]) besides the per-metre part, which alone
    /// is what its scan headers tell the daemon. Seed 000's scanner keeps the paper's model (no
    /// floor).
    pub fn with_device_noise(self) -> Self {
        let range_noise_floor_m = match self.name {
            "vlp16" => VLP16_NOISE_FLOOR_M,
            "os1-64" => OS1_NOISE_FLOOR_M,
            _ => 0.0,
        };
        Self {
            range_noise_floor_m,
            ..self
        }
    }

    /// This preset losing the returns too weak to detect: a surface met squarely returns up to
    /// `range_m`, one met at incidence α up to `range_m` √cos α
    /// ([`ScannerPreset::weak_return_range_m`]).
    ///
    /// # Panics
    /// If `range_m` is not positive and finite (a caller's misuse).
    pub fn with_weak_returns(self, range_m: f64) -> Self {
        assert!(
            range_m.is_finite() && range_m > 0.0,
            "weak-return range {range_m} m"
        );
        Self {
            weak_return_range_m: Some(range_m),
            ..self
        }
    }

    /// Whether a hit at range `r_m` whose surface normal `normal` gives (against the unit ray
    /// `dir`; `None`: met squarely; asked only when returns can be weak) is strong enough to return
    /// ([`ScannerPreset::weak_return_range_m`]): what the scanner sees, for evaluations that
    /// tell seen ground from unseen.
    pub fn detects(
        &self,
        r_m: f64,
        dir: &Vector3<f64>,
        normal: impl FnOnce() -> Option<Vector3<f64>>,
    ) -> bool {
        self.weak_return_range_m.is_none_or(|range| {
            let cos = normal().map_or(1.0, |n| n.dot(dir).abs());
            r_m <= range * cos.sqrt()
        })
    }

    /// Range noise standard deviation at range `r_m`, metres.
    pub fn range_noise_sd(&self, r_m: f64) -> f64 {
        self.range_noise_floor_m.hypot(self.range_noise_per_m * r_m)
    }

    /// Rays per scan.
    pub fn ray_count(&self) -> usize {
        self.inclinations_rad.len() * self.azimuths_rad.len()
    }
}

fn full_turn(columns: usize) -> Vec<f64> {
    let step = std::f64::consts::TAU / columns as f64;
    (0..columns)
        .map(|c| -std::f64::consts::PI + step * c as f64)
        .collect()
}

/// Unit direction in the sensor frame of a ray at inclination θ (polar, from +z) and azimuth φ.
pub fn direction(inclination: f64, azimuth: f64) -> Vector3<f64> {
    Vector3::new(
        inclination.sin() * azimuth.cos(),
        inclination.sin() * azimuth.sin(),
        inclination.cos(),
    )
}

/// One simulated ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimRay {
    /// Ring index.
    pub ring: u16,
    /// Column index.
    pub column: u16,
    /// Polar angle from the sensor's +z axis, radians.
    pub inclination_rad: f64,
    /// Azimuth in the sensor frame, radians.
    pub azimuth_rad: f64,
    /// Exact range to the surface, or `None` for no return within max range.
    pub true_range_m: Option<f64>,
    /// Range with sensor noise added (`None` for no return).
    pub measured_range_m: Option<f64>,
    /// When the ray fired, seconds after the scan's stamp (0 for a scan taken at one instant).
    pub time_offset_s: f64,
}

/// How a rotating lidar moves while it sweeps: its columns fire one after another over
/// `sweep_s`, while the sensor moves with a constant twist in its own frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SweepMotion {
    /// Time from the first column to the last, seconds.
    pub sweep_s: f64,
    /// Linear velocity in the sensor frame, m/s.
    pub linear_mps: Vector3<f64>,
    /// Angular velocity in the sensor frame, rad/s.
    pub angular_radps: Vector3<f64>,
}

impl SweepMotion {
    /// The sensor's pose `t` seconds into the sweep, relative to its pose at the stamp: the twist
    /// integrated as 256 small steps in the moving frame (first order per step, so within
    /// |v|·|ω|·t² / 512 of the exact motion; independent of the daemon's closed-form exponential,
    /// so a test of one checks the other).
    pub fn displacement(&self, t: f64) -> Isometry3<f64> {
        const STEPS: usize = 256;
        let dt = t / STEPS as f64;
        let step = Isometry3::from_parts(
            Translation3::from(self.linear_mps * dt),
            UnitQuaternion::from_scaled_axis(self.angular_radps * dt),
        );
        (0..STEPS).fold(Isometry3::identity(), |pose, _| pose * step)
    }
}

/// Casts a rotating lidar's sweep from `pose` (its pose at the stamp): column c of n fires at
/// `sweep_s · c / (n − 1)`, from where the sensor is by then ([`SweepMotion::displacement`]).
/// Angles are the sensor's own at firing time, as a driver reports them; noise as in
/// [`simulate_scan`].
pub fn simulate_sweep<S: Surface + ?Sized, R: Rng>(
    surface: &S,
    pose: &Isometry3<f64>,
    preset: &ScannerPreset,
    motion: &SweepMotion,
    rng: &mut R,
) -> Vec<SimRay> {
    let columns = preset.azimuths_rad.len();
    let times: Vec<f64> = (0..columns)
        .map(|c| motion.sweep_s * c as f64 / (columns.max(2) - 1) as f64)
        .collect();
    let poses: Vec<Isometry3<f64>> = times.iter().map(|&t| pose * motion.displacement(t)).collect();
    let mut rays = Vec::with_capacity(preset.ray_count());
    for (ring, &inc) in preset.inclinations_rad.iter().enumerate() {
        for (column, &az) in preset.azimuths_rad.iter().enumerate() {
            let at = &poses[column];
            let mut ray = cast_one(surface, at, preset, ring, column, inc, az, rng);
            ray.time_offset_s = times[column];
            rays.push(ray);
        }
    }
    rays
}

/// One ray of `preset` from `pose`, with noise.
#[allow(clippy::too_many_arguments)]
fn cast_one<S: Surface + ?Sized, R: Rng>(
    surface: &S,
    pose: &Isometry3<f64>,
    preset: &ScannerPreset,
    ring: usize,
    column: usize,
    inc: f64,
    az: f64,
    rng: &mut R,
) -> SimRay {
    let dir = pose.rotation * direction(inc, az);
    let origin = pose.translation.vector;
    let true_range = surface
        .cast(origin, dir, preset.max_range_m)
        .filter(|&r| r < preset.max_range_m)
        .filter(|&r| preset.detects(r, &dir, || surface.normal(origin + dir * r)));
    let measured = true_range.map(|r| r + preset.range_noise_sd(r) * standard_normal(rng));
    SimRay {
        ring: ring as u16,
        column: column as u16,
        inclination_rad: inc,
        azimuth_rad: az,
        true_range_m: true_range,
        measured_range_m: measured,
        time_offset_s: 0.0,
    }
}

/// Casts every ray of `preset` from `pose` (sensor frame in the map frame) and adds range noise
/// of σ [`ScannerPreset::range_noise_sd`] drawn from `rng`.
pub fn simulate_scan<S: Surface + ?Sized, R: Rng>(
    surface: &S,
    pose: &Isometry3<f64>,
    preset: &ScannerPreset,
    rng: &mut R,
) -> Vec<SimRay> {
    let mut rays = Vec::with_capacity(preset.ray_count());
    for (ring, &inc) in preset.inclinations_rad.iter().enumerate() {
        for (column, &az) in preset.azimuths_rad.iter().enumerate() {
            rays.push(cast_one(surface, pose, preset, ring, column, inc, az, rng));
        }
    }
    rays
}

/// One standard-normal draw (Box–Muller; two uniforms in, one normal out).
pub fn standard_normal<R: Rng>(rng: &mut R) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::terrain::Heightmap;
    use nalgebra::{Translation3, UnitQuaternion};
    use rand::SeedableRng;
    use rand_pcg::Pcg64;

    #[test]
    fn seed000_preset_matches_the_paper() {
        let p = ScannerPreset::seed000();
        assert_eq!(p.inclinations_rad.len(), 16);
        assert_eq!(p.azimuths_rad.len(), 91);
        assert!((p.inclinations_rad[0].to_degrees() - 105.0).abs() < 1e-9);
        assert!((p.inclinations_rad[15].to_degrees() - 90.0).abs() < 1e-9);
        assert!((p.azimuths_rad[1] - p.azimuths_rad[0] - 2f64.to_radians()).abs() < 1e-12);
        assert_eq!(ScannerPreset::vlp16().ray_count(), 16 * 1800);
        assert_eq!(ScannerPreset::os1_64(1024).ray_count(), 64 * 1024);
    }

    #[test]
    fn flat_ground_scan_has_closed_form_ranges_and_drops_max_range() {
        let terrain = Heightmap::flat(40.0, 0.05, 0.0);
        let preset = ScannerPreset::seed000();
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.75),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        );
        let rays = simulate_scan(&terrain, &pose, &preset, &mut Pcg64::seed_from_u64(1));
        for r in &rays {
            let below = r.inclination_rad - std::f64::consts::FRAC_PI_2;
            let expect = 0.75 / below.sin();
            match r.true_range_m {
                Some(t) => assert!((t - expect).abs() < 1e-5, "{t} vs {expect}"),
                None => assert!(below <= 0.0 || expect >= 10.0 - 1e-6),
            }
        }
        let returned = rays.iter().filter(|r| r.true_range_m.is_some()).count();
        assert!(returned > 600 && returned < rays.len());
    }

    #[test]
    fn weak_returns_lose_grazed_ground_far_out_and_keep_it_near() {
        // Flat ground 0.75 m below: a ring b below the horizon meets it at 0.75 / sin b and at
        // incidence 90° − b, so it returns while 0.75 / sin b ≤ 100 √(sin b).
        let terrain = Heightmap::flat(200.0, 0.1, 0.0);
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.75), UnitQuaternion::identity());
        let preset = ScannerPreset::vlp16().with_weak_returns(100.0);
        let rays = simulate_scan(&terrain, &pose, &preset, &mut Pcg64::seed_from_u64(2));
        let (mut kept, mut lost) = (0, 0);
        for r in rays
            .iter()
            .filter(|r| r.inclination_rad > std::f64::consts::FRAC_PI_2)
        {
            let below = r.inclination_rad - std::f64::consts::FRAC_PI_2;
            let strong = 0.75 / below.sin() <= 100.0 * below.sin().sqrt();
            assert_eq!(
                r.true_range_m.is_some(),
                strong,
                "ring {:.1}° below",
                below.to_degrees()
            );
            if strong {
                kept += 1;
            } else {
                lost += 1;
            }
        }
        // The −1° ring (43 m out) is lost, the seven below it (within 14.3 m) kept.
        assert_eq!((kept, lost), (7 * 1800, 1800));
        let every = simulate_scan(
            &terrain,
            &pose,
            &ScannerPreset::vlp16(),
            &mut Pcg64::seed_from_u64(2),
        );
        assert_eq!(
            every.iter().filter(|r| r.true_range_m.is_some()).count(),
            8 * 1800
        );
    }

    #[test]
    fn noise_has_the_configured_scale() {
        let mut rng = Pcg64::seed_from_u64(9);
        let n = 20_000;
        let draws: Vec<f64> = (0..n).map(|_| standard_normal(&mut rng)).collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let var = draws.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.04, "{mean} {var}");
    }

    #[test]
    fn device_noise_has_its_floor_at_short_range_and_seed000_keeps_the_papers_model() {
        let terrain = Heightmap::flat(60.0, 0.05, 0.0);
        let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.75), UnitQuaternion::identity());
        let preset = ScannerPreset::vlp16().with_device_noise();
        let rays = simulate_scan(&terrain, &pose, &preset, &mut Pcg64::seed_from_u64(3));
        let errors: Vec<f64> = rays
            .iter()
            .filter_map(|r| Some(r.measured_range_m? - r.true_range_m?))
            .collect();
        let sd = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
        assert!(errors.len() > 10_000, "{} returns", errors.len());
        assert!((sd - VLP16_NOISE_FLOOR_M).abs() < 0.002, "σ {sd}");
        assert_eq!(
            ScannerPreset::seed000().with_device_noise(),
            ScannerPreset::seed000()
        );
        let os1 = ScannerPreset::os1_64(1024).with_device_noise();
        assert!((os1.range_noise_sd(0.0) - 0.015).abs() < 1e-12);
        assert!(os1.range_noise_sd(120.0) > 0.03 && os1.range_noise_sd(120.0) < 0.036);
    }
}
