//! The hot loops of every map query, four lanes at a time: sums and values of the exponential
//! kernel families, and the forward substitution of the posterior variance.
//!
//! On x86-64 with AVX2 and FMA (checked at run time, so one binary still runs on robot computers
//! without them) they use 256-bit intrinsics and the exp of `avx`; elsewhere `wide`'s portable
//! f64x4 (SSE2 or NEON) and plain loops. Measured (docs/ARCHITECTURE.md): a 128-input Matérn sum
//! takes about a third of the time of the portable path.

#![allow(unsafe_code)] // Allowed here, each site with its SAFETY comment; denied elsewhere.

use super::points::Points;
use wide::f64x4;

/// A unit-variance exponential-family kernel as a function of the squared distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Profile {
    /// (1 + s) e^(−s), s = c d.
    Matern32 {
        /// √3 / ℓ.
        c: f64,
    },
    /// (1 + s + s²/3) e^(−s), s = c d.
    Matern52 {
        /// √5 / ℓ.
        c: f64,
    },
    /// e^(−c d²).
    SquaredExponential {
        /// 1 / 2ℓ².
        c: f64,
    },
}

impl Profile {
    /// The value at squared distance `d2` (libm's exp).
    pub fn unit(self, d2: f64) -> f64 {
        match self {
            Profile::Matern32 { c } => {
                let s = d2.sqrt() * c;
                (1.0 + s) * (-s).exp()
            }
            Profile::Matern52 { c } => {
                let s = d2.sqrt() * c;
                (1.0 + s + s * s / 3.0) * (-s).exp()
            }
            Profile::SquaredExponential { c } => (-c * d2).exp(),
        }
    }

    /// [`Self::unit`] at four squared distances with `wide`'s exp.
    fn unit_x4(self, d2: f64x4) -> f64x4 {
        match self {
            Profile::Matern32 { c } => {
                let s = d2.sqrt() * f64x4::splat(c);
                (f64x4::ONE + s) * (-s).exp()
            }
            Profile::Matern52 { c } => {
                let s = d2.sqrt() * f64x4::splat(c);
                (f64x4::ONE + s + s * s * f64x4::splat(1.0 / 3.0)) * (-s).exp()
            }
            Profile::SquaredExponential { c } => (d2 * f64x4::splat(-c)).exp(),
        }
    }
}

/// Whether the AVX2 + FMA paths run on this CPU (std caches the detection).
fn avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Σᵢ unit(‖x − xᵢ‖²) wᵢ (panics when the lengths differ: misuse).
pub fn weighted_sum<const D: usize>(
    profile: Profile,
    x: &[f64; D],
    inputs: &Points<D>,
    weights: &[f64],
) -> f64 {
    assert_eq!(inputs.len(), weights.len(), "one weight per input");
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has AVX2 and FMA (checked just above).
        return unsafe { avx::weighted_sum(profile, x, inputs, weights) };
    }
    portable_weighted_sum(profile, x, inputs, weights)
}

/// unit(‖x − xᵢ‖²) into `out[i]` for every input (panics when the lengths differ: misuse).
pub fn values<const D: usize>(profile: Profile, x: &[f64; D], inputs: &Points<D>, out: &mut [f64]) {
    assert_eq!(inputs.len(), out.len(), "one output per input");
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has AVX2 and FMA (checked just above).
        return unsafe { avx::values(profile, x, inputs, out) };
    }
    portable_values(profile, x, inputs, out);
}

/// Solves L w = v in place for the lower factor L (n = `v.len()`, packed by columns: rows j..n of
/// column j for every j) and returns ‖w‖²: the variance the training data explains at a query
/// whose kernel column is v (panics when the lengths differ: misuse).
pub fn forward_explained(packed: &[f64], v: &mut [f64]) -> f64 {
    let n = v.len();
    assert_eq!(
        packed.len(),
        n * (n + 1) / 2,
        "a packed n × n factor for n values"
    );
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has AVX2 and FMA (checked just above).
        return unsafe { avx::forward_explained(packed, v) };
    }
    portable_forward_explained(packed, v)
}

/// Squared distances from `x` to inputs i..i+4 (i + 4 ≤ len).
fn d2_x4<const D: usize>(x: &[f64; D], inputs: &Points<D>, i: usize) -> f64x4 {
    let mut d2 = f64x4::ZERO;
    for (k, xk) in x.iter().enumerate() {
        let c = &inputs.coord(k)[i..i + 4];
        let diff = f64x4::new([c[0], c[1], c[2], c[3]]) - f64x4::splat(*xk);
        d2 += diff * diff;
    }
    d2
}

/// Squared distance from `x` to input `i`.
fn d2_at<const D: usize>(x: &[f64; D], inputs: &Points<D>, i: usize) -> f64 {
    (0..D).map(|k| (inputs.coord(k)[i] - x[k]).powi(2)).sum()
}

fn portable_weighted_sum<const D: usize>(
    profile: Profile,
    x: &[f64; D],
    inputs: &Points<D>,
    weights: &[f64],
) -> f64 {
    let n4 = weights.len() / 4 * 4;
    let mut acc = f64x4::ZERO;
    for i in (0..n4).step_by(4) {
        let w = &weights[i..i + 4];
        acc += profile.unit_x4(d2_x4(x, inputs, i)) * f64x4::new([w[0], w[1], w[2], w[3]]);
    }
    let tail: f64 = (n4..weights.len())
        .map(|i| profile.unit(d2_at(x, inputs, i)) * weights[i])
        .sum();
    acc.reduce_add() + tail
}

fn portable_values<const D: usize>(profile: Profile, x: &[f64; D], inputs: &Points<D>, out: &mut [f64]) {
    let n4 = out.len() / 4 * 4;
    for i in (0..n4).step_by(4) {
        out[i..i + 4].copy_from_slice(&profile.unit_x4(d2_x4(x, inputs, i)).to_array());
    }
    for (i, o) in out.iter_mut().enumerate().skip(n4) {
        *o = profile.unit(d2_at(x, inputs, i));
    }
}

fn portable_forward_explained(packed: &[f64], v: &mut [f64]) -> f64 {
    let n = v.len();
    let (mut explained, mut start) = (0.0, 0);
    for j in 0..n {
        let col = &packed[start..start + n - j];
        start += n - j;
        let vj = v[j] / col[0];
        explained += vj * vj;
        for (vi, lij) in v[j + 1..].iter_mut().zip(&col[1..]) {
            *vi -= lij * vj;
        }
    }
    explained
}

/// AVX2 + FMA versions. Every function requires a CPU with both (the callers check).
#[cfg(target_arch = "x86_64")]
mod avx {
    use super::{d2_at, Points, Profile};
    use std::arch::x86_64::*;

    /// Four lanes of `s[i..i + 4]`.
    ///
    /// # Safety
    /// AVX must be available; panics (never reads out of bounds) when i + 4 > len.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn load(s: &[f64], i: usize) -> __m256d {
        let lanes: &[f64; 4] = s[i..i + 4].try_into().expect("four lanes");
        _mm256_loadu_pd(lanes.as_ptr())
    }

    /// Sum of the four lanes.
    ///
    /// # Safety
    /// AVX must be available.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn sum_lanes(v: __m256d) -> f64 {
        let mut out = [0.0; 4];
        _mm256_storeu_pd(out.as_mut_ptr(), v);
        (out[0] + out[1]) + (out[2] + out[3])
    }

    /// e^x for x ≤ 0 (x below −708 is taken as −708: e^−708 ≈ 3e−308; NaN stays NaN):
    /// x = n ln 2 + r with |r| ≤ ln 2 / 2 (Cody–Waite, two-part ln 2, n rounded by the
    /// 1.5 · 2⁵² shift), a degree-13 Taylor polynomial of e^r by Horner in FMAs (truncation
    /// below 1e−17 relative), and 2ⁿ built in the exponent bits.
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn exp_nonpositive(x: __m256d) -> __m256d {
        const SHIFT: f64 = 6_755_399_441_055_744.0;
        // fdlibm's split of ln 2: the high part has trailing zero bits, so n · LN2_HI is exact.
        const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
        const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
        const TAYLOR: [f64; 14] = [
            1.0 / 6_227_020_800.0,
            1.0 / 479_001_600.0,
            1.0 / 39_916_800.0,
            1.0 / 3_628_800.0,
            1.0 / 362_880.0,
            1.0 / 40_320.0,
            1.0 / 5_040.0,
            1.0 / 720.0,
            1.0 / 120.0,
            1.0 / 24.0,
            1.0 / 6.0,
            0.5,
            1.0,
            1.0,
        ];
        let x = _mm256_max_pd(_mm256_set1_pd(-708.0), x);
        let shifted = _mm256_fmadd_pd(x, _mm256_set1_pd(std::f64::consts::LOG2_E), _mm256_set1_pd(SHIFT));
        let n = _mm256_sub_pd(shifted, _mm256_set1_pd(SHIFT));
        let r = _mm256_fnmadd_pd(n, _mm256_set1_pd(LN2_HI), x);
        let r = _mm256_fnmadd_pd(n, _mm256_set1_pd(LN2_LO), r);
        let mut p = _mm256_set1_pd(TAYLOR[0]);
        for c in &TAYLOR[1..] {
            p = _mm256_fmadd_pd(p, r, _mm256_set1_pd(*c));
        }
        // The shift left n + 2⁵¹ in the low mantissa bits: adding the bias and shifting the
        // 2⁵¹ out leaves (n + 1023) in the exponent field, i.e. 2ⁿ (n ≥ −1022 here).
        let bits = _mm256_add_epi64(_mm256_castpd_si256(shifted), _mm256_set1_epi64x(1023));
        _mm256_mul_pd(p, _mm256_castsi256_pd(_mm256_slli_epi64::<52>(bits)))
    }

    /// The profile at four squared distances.
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn unit(profile: Profile, d2: __m256d) -> __m256d {
        let one = _mm256_set1_pd(1.0);
        match profile {
            Profile::Matern32 { c } => {
                let s = _mm256_mul_pd(_mm256_sqrt_pd(d2), _mm256_set1_pd(c));
                let e = exp_nonpositive(_mm256_sub_pd(_mm256_setzero_pd(), s));
                _mm256_mul_pd(_mm256_add_pd(one, s), e)
            }
            Profile::Matern52 { c } => {
                let s = _mm256_mul_pd(_mm256_sqrt_pd(d2), _mm256_set1_pd(c));
                let e = exp_nonpositive(_mm256_sub_pd(_mm256_setzero_pd(), s));
                let poly = _mm256_fmadd_pd(
                    _mm256_mul_pd(s, s),
                    _mm256_set1_pd(1.0 / 3.0),
                    _mm256_add_pd(one, s),
                );
                _mm256_mul_pd(poly, e)
            }
            Profile::SquaredExponential { c } => exp_nonpositive(_mm256_mul_pd(d2, _mm256_set1_pd(-c))),
        }
    }

    /// Squared distances from `x` to inputs i..i + 4.
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn d2<const D: usize>(x: &[f64; D], inputs: &Points<D>, i: usize) -> __m256d {
        let mut d2 = _mm256_setzero_pd();
        for (k, xk) in x.iter().enumerate() {
            let diff = _mm256_sub_pd(load(inputs.coord(k), i), _mm256_set1_pd(*xk));
            d2 = _mm256_fmadd_pd(diff, diff, d2);
        }
        d2
    }

    /// [`super::weighted_sum`].
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn weighted_sum<const D: usize>(
        profile: Profile,
        x: &[f64; D],
        inputs: &Points<D>,
        weights: &[f64],
    ) -> f64 {
        let n4 = weights.len() / 4 * 4;
        let mut acc = _mm256_setzero_pd();
        for i in (0..n4).step_by(4) {
            acc = _mm256_fmadd_pd(unit(profile, d2(x, inputs, i)), load(weights, i), acc);
        }
        if n4 < weights.len() {
            // The last one to three inputs in one more pass of four lanes, the spare lanes
            // weighted by zero.
            let (mut d2s, mut ws) = ([0.0; 4], [0.0; 4]);
            for (l, i) in (n4..weights.len()).enumerate() {
                d2s[l] = d2_at(x, inputs, i);
                ws[l] = weights[i];
            }
            let lanes = unit(profile, _mm256_loadu_pd(d2s.as_ptr()));
            acc = _mm256_fmadd_pd(lanes, _mm256_loadu_pd(ws.as_ptr()), acc);
        }
        sum_lanes(acc)
    }

    /// [`super::values`].
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn values<const D: usize>(
        profile: Profile,
        x: &[f64; D],
        inputs: &Points<D>,
        out: &mut [f64],
    ) {
        let n4 = out.len() / 4 * 4;
        for i in (0..n4).step_by(4) {
            let lanes: &mut [f64; 4] = (&mut out[i..i + 4]).try_into().expect("four lanes");
            _mm256_storeu_pd(lanes.as_mut_ptr(), unit(profile, d2(x, inputs, i)));
        }
        for (i, o) in out.iter_mut().enumerate().skip(n4) {
            *o = profile.unit(d2_at(x, inputs, i));
        }
    }

    /// [`super::forward_explained`]: the same column axpys, compiled for AVX2 with fused
    /// multiply-adds.
    ///
    /// # Safety
    /// AVX2 and FMA must be available.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn forward_explained(packed: &[f64], v: &mut [f64]) -> f64 {
        let n = v.len();
        let (mut explained, mut start) = (0.0, 0);
        let mut j = 0;
        // Four columns at a time: the 4 × 4 triangle first, then each lower element takes the
        // four updates in column order (the same operations in the same order as one column at
        // a time, with a quarter of the loads and stores of `v`).
        while j + 4 <= n {
            let len = n - j;
            let c0 = &packed[start..start + len];
            let c1 = &packed[start + len..start + 2 * len - 1];
            let c2 = &packed[start + 2 * len - 1..start + 3 * len - 3];
            let c3 = &packed[start + 3 * len - 3..start + 4 * len - 6];
            start += 4 * len - 6;
            let w0 = v[j] / c0[0];
            v[j + 1] = (-c0[1]).mul_add(w0, v[j + 1]);
            v[j + 2] = (-c0[2]).mul_add(w0, v[j + 2]);
            v[j + 3] = (-c0[3]).mul_add(w0, v[j + 3]);
            let w1 = v[j + 1] / c1[0];
            v[j + 2] = (-c1[1]).mul_add(w1, v[j + 2]);
            v[j + 3] = (-c1[2]).mul_add(w1, v[j + 3]);
            let w2 = v[j + 2] / c2[0];
            v[j + 3] = (-c2[1]).mul_add(w2, v[j + 3]);
            let w3 = v[j + 3] / c3[0];
            explained += w0 * w0;
            explained += w1 * w1;
            explained += w2 * w2;
            explained += w3 * w3;
            let rows = v[j + 4..]
                .iter_mut()
                .zip(&c0[4..])
                .zip(&c1[3..])
                .zip(&c2[2..])
                .zip(&c3[1..]);
            for ((((vi, a), b), c), d) in rows {
                let u = (-a).mul_add(w0, *vi);
                let u = (-b).mul_add(w1, u);
                let u = (-c).mul_add(w2, u);
                *vi = (-d).mul_add(w3, u);
            }
            j += 4;
        }
        for j in j..n {
            let col = &packed[start..start + n - j];
            start += n - j;
            let vj = v[j] / col[0];
            explained += vj * vj;
            for (vi, lij) in v[j + 1..].iter_mut().zip(&col[1..]) {
                *vi = (-lij).mul_add(vj, *vi);
            }
        }
        explained
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    const PROFILES: [Profile; 3] = [
        Profile::Matern32 { c: 2.9 },
        Profile::Matern52 { c: 3.7 },
        Profile::SquaredExponential { c: 1.4 },
    ];

    fn scalar(profile: Profile, x: &[f64; 3], pts: &[[f64; 3]], w: &[f64]) -> f64 {
        pts.iter()
            .zip(w)
            .map(|(p, wi)| profile.unit((0..3).map(|k| (p[k] - x[k]).powi(2)).sum()) * wi)
            .sum()
    }

    #[test]
    fn every_path_matches_the_scalar_profile() {
        let mut rng = rand_pcg::Pcg64::new(3, 5);
        for profile in PROFILES {
            for n in [0, 1, 3, 4, 5, 128, 131] {
                let pts: Vec<[f64; 3]> = (0..n)
                    .map(|_| std::array::from_fn(|_| rng.random_range(-3.0..3.0)))
                    .collect();
                let w: Vec<f64> = (0..n).map(|_| rng.random_range(-50.0..50.0)).collect();
                let x = [0.3, -0.2, 1.1];
                let inputs = Points::new(&pts);
                let want = scalar(profile, &x, &pts, &w);
                let scale = w.iter().map(|v| v.abs()).sum::<f64>().max(1.0);
                let mut sums = vec![portable_weighted_sum(profile, &x, &inputs, &w)];
                let mut vals = vec![0.0; n];
                portable_values(profile, &x, &inputs, &mut vals);
                let mut all_vals = vec![vals.clone()];
                sums.push(weighted_sum(profile, &x, &inputs, &w));
                values(profile, &x, &inputs, &mut vals);
                all_vals.push(vals);
                for s in sums {
                    assert!(
                        (s - want).abs() <= 1e-13 * scale,
                        "{profile:?} n={n}: {s} vs {want}"
                    );
                }
                for vals in all_vals {
                    for (i, v) in vals.iter().enumerate() {
                        let exact = profile.unit((0..3).map(|k| (pts[i][k] - x[k]).powi(2)).sum());
                        assert!(
                            (v - exact).abs() <= 1e-15,
                            "{profile:?} value {i}: {v} vs {exact}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn forward_substitution_paths_agree_with_a_dense_solve() {
        // Sizes around the vector path's blocks of four columns, and one with a remainder.
        for n in [1, 3, 4, 5, 8, 37] {
            forward_substitution_agrees(n);
        }
    }

    fn forward_substitution_agrees(n: usize) {
        let mut rng = rand_pcg::Pcg64::new(9, n as u128);
        let mut cols = vec![0.0; n * n];
        for j in 0..n {
            cols[j * n + j] = rng.random_range(0.5..2.0);
            for i in j + 1..n {
                cols[j * n + i] = rng.random_range(-0.3..0.3);
            }
        }
        let v: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        // Reference: w by row-oriented substitution, then ‖w‖².
        let mut w = vec![0.0; n];
        for i in 0..n {
            let s: f64 = (0..i).map(|j| cols[j * n + i] * w[j]).sum();
            w[i] = (v[i] - s) / cols[i * n + i];
        }
        let want: f64 = w.iter().map(|x| x * x).sum();
        let packed: Vec<f64> = (0..n)
            .flat_map(|j| cols[j * n + j..(j + 1) * n].to_vec())
            .collect();
        let portable = portable_forward_explained(&packed, &mut v.clone());
        let dispatched = forward_explained(&packed, &mut v.clone());
        assert!((portable - want).abs() <= 1e-12 * want, "{portable} vs {want}");
        assert!(
            (dispatched - want).abs() <= 1e-12 * want,
            "{dispatched} vs {want}"
        );
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_exp_is_within_two_ulp_of_libm() {
        if !avx2_fma() {
            // Nothing to check: this CPU runs the portable path, which libm's exp backs.
            eprintln!("skipped: this CPU has no AVX2 + FMA, so the vector exp never runs here");
            return;
        }
        use std::arch::x86_64::*;
        let mut worst: f64 = 0.0;
        for k in 0..=200_000 {
            let x = -708.0 * k as f64 / 200_000.0;
            let mut out = [0.0; 4];
            // SAFETY: AVX2 and FMA checked above.
            unsafe {
                let v = avx::exp_nonpositive(_mm256_set_pd(x, x * 0.5, x * 1e-3, x * 1e-9));
                _mm256_storeu_pd(out.as_mut_ptr(), v);
            }
            for (got, arg) in out.iter().zip([x * 1e-9, x * 1e-3, x * 0.5, x]) {
                worst = worst.max(((got - arg.exp()) / arg.exp()).abs());
            }
        }
        assert!(worst <= 2.0 * f64::EPSILON, "worst relative error {worst:e}");
        // SAFETY: AVX2 and FMA checked above.
        let nan = unsafe {
            let mut out = [0.0; 4];
            _mm256_storeu_pd(out.as_mut_ptr(), avx::exp_nonpositive(_mm256_set1_pd(f64::NAN)));
            out[0]
        };
        assert!(nan.is_nan());
    }
}
