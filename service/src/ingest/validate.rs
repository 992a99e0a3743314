//! Validation of a scan copied out of shared memory. Pure functions over private copies: a scan
//! either becomes a [`ScanInput`] or is rejected with exactly one [`RejectReason`].

use crate::scan::{RayObservation, RejectReason, ScanInput};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use rangegp_proto::scan::{ScanHeader, ScanPoint, FLAG_NO_RETURN, FLAG_RING_COLUMN_VALID};
use rangegp_proto::PROTOCOL_VERSION;

/// Bounds a scan must respect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValidationLimits {
    /// Most points accepted in one scan.
    pub max_points: usize,
    /// How far a scan's stamp may lie ahead of this machine's clock, nanoseconds.
    pub max_future_ns: u64,
}

/// Largest sensor max range accepted, metres.
const MAX_SENSOR_RANGE_M: f64 = 1000.0;
/// Largest range-noise coefficient accepted (σ/r).
const MAX_NOISE_PER_M: f64 = 0.1;

/// Checks the header alone (before any point is copied); `now_ns` is this machine's clock,
/// nanoseconds since the Unix epoch.
pub fn check_header(
    h: &ScanHeader,
    slice_len: usize,
    limits: &ValidationLimits,
    now_ns: u64,
) -> Result<(), RejectReason> {
    if h.protocol_version != PROTOCOL_VERSION {
        return Err(RejectReason::UnsupportedVersion);
    }
    let count = h.point_count as usize;
    if count == 0 {
        return Err(RejectReason::EmptyScan);
    }
    if count > limits.max_points {
        return Err(RejectReason::TooManyPoints);
    }
    if count > slice_len {
        return Err(RejectReason::Truncated);
    }
    let pose = [h.px_m, h.py_m, h.pz_m, h.qx, h.qy, h.qz, h.qw];
    if pose.iter().any(|v| !v.is_finite()) {
        return Err(RejectReason::InvalidPose);
    }
    let norm = (h.qx * h.qx + h.qy * h.qy + h.qz * h.qz + h.qw * h.qw).sqrt();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(RejectReason::NonUnitQuaternion);
    }
    let range_ok = h.max_range_m.is_finite() && h.max_range_m > 0.0 && h.max_range_m <= MAX_SENSOR_RANGE_M;
    let noise_ok = h.range_noise_per_m.is_finite() && (0.0..=MAX_NOISE_PER_M).contains(&h.range_noise_per_m);
    if !range_ok || !noise_ok {
        return Err(RejectReason::InvalidSensorModel);
    }
    if h.stamp_ns > now_ns.saturating_add(limits.max_future_ns) {
        return Err(RejectReason::FutureTimestamp);
    }
    Ok(())
}

/// Validates a private copy of the header and its points and builds the fitter's input.
/// Returns at or beyond the max range count as no-returns.
pub fn validate(
    h: &ScanHeader,
    points: &[ScanPoint],
    limits: &ValidationLimits,
    now_ns: u64,
) -> Result<ScanInput, RejectReason> {
    check_header(h, points.len(), limits, now_ns)?;
    let points = &points[..h.point_count as usize];
    let known_flags = FLAG_NO_RETURN | FLAG_RING_COLUMN_VALID;
    let mut rays = Vec::with_capacity(points.len());
    for p in points {
        if p.flags & !known_flags != 0 || p.reserved != 0 {
            return Err(RejectReason::InvalidFlags);
        }
        let (inc, az) = (p.inclination_rad as f64, p.azimuth_rad as f64);
        let pi = std::f64::consts::PI + 1e-6;
        if !inc.is_finite() || !az.is_finite() || !(0.0..=pi).contains(&inc) || az.abs() > pi {
            return Err(RejectReason::InvalidAngle);
        }
        if !p.has_return() {
            continue;
        }
        let r = p.range_m as f64;
        if !r.is_finite() || r < 0.0 {
            return Err(RejectReason::InvalidRange);
        }
        if r > 0.0 && r < h.max_range_m {
            rays.push(RayObservation {
                inclination: inc,
                azimuth: az,
                range: r,
            });
        }
    }
    if rays.is_empty() {
        return Err(RejectReason::NoReturns);
    }
    let rotation = UnitQuaternion::new_normalize(Quaternion::new(h.qw, h.qx, h.qy, h.qz));
    Ok(ScanInput {
        publisher_id: h.publisher_id,
        sequence: h.sequence,
        stamp_ns: h.stamp_ns,
        pose: Isometry3::from_parts(Translation3::new(h.px_m, h.py_m, h.pz_m), rotation),
        max_range_m: h.max_range_m,
        range_noise_per_m: h.range_noise_per_m,
        rays,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn good_header(count: u32) -> ScanHeader {
        ScanHeader {
            point_count: count,
            publisher_id: 7,
            sequence: 1,
            pz_m: 0.75,
            max_range_m: 10.0,
            range_noise_per_m: 0.0075 / 29.0,
            ..ScanHeader::default()
        }
    }

    pub(crate) fn good_points(count: usize) -> Vec<ScanPoint> {
        (0..count)
            .map(|i| ScanPoint {
                range_m: 3.0,
                inclination_rad: 1.75,
                azimuth_rad: -0.5 + i as f32 * 0.01,
                ..ScanPoint::default()
            })
            .collect()
    }

    fn limits() -> ValidationLimits {
        ValidationLimits {
            max_points: 100,
            max_future_ns: 1_000_000_000,
        }
    }

    /// The clock the tests validate against: 100 s after the epoch.
    const NOW: u64 = 100_000_000_000;

    #[test]
    fn a_good_scan_passes_and_max_range_returns_are_dropped() {
        let mut pts = good_points(10);
        pts[3].range_m = 10.0;
        pts[4].flags = FLAG_NO_RETURN;
        pts[4].range_m = f32::NAN;
        let scan = validate(&good_header(10), &pts, &limits(), NOW).expect("valid");
        assert_eq!(scan.rays.len(), 8);
    }

    #[test]
    fn each_defect_has_its_own_reason() {
        let pts = good_points(10);
        let check = |h: ScanHeader, p: &[ScanPoint], want: RejectReason| {
            assert_eq!(validate(&h, p, &limits(), NOW).err(), Some(want));
        };
        check(
            ScanHeader {
                protocol_version: 99,
                ..good_header(10)
            },
            &pts,
            RejectReason::UnsupportedVersion,
        );
        check(good_header(0), &pts, RejectReason::EmptyScan);
        check(good_header(101), &good_points(101), RejectReason::TooManyPoints);
        check(good_header(11), &pts, RejectReason::Truncated);
        check(
            ScanHeader {
                px_m: f64::NAN,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidPose,
        );
        check(
            ScanHeader {
                qw: f64::INFINITY,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidPose,
        );
        check(
            ScanHeader {
                qw: 0.9,
                ..good_header(10)
            },
            &pts,
            RejectReason::NonUnitQuaternion,
        );
        check(
            ScanHeader {
                max_range_m: 0.0,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidSensorModel,
        );
        check(
            ScanHeader {
                range_noise_per_m: -1.0,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidSensorModel,
        );
        check(
            ScanHeader {
                stamp_ns: NOW + 1_000_000_001,
                ..good_header(10)
            },
            &pts,
            RejectReason::FutureTimestamp,
        );
        let mut bad = pts.clone();
        bad[2].range_m = f32::NAN;
        check(good_header(10), &bad, RejectReason::InvalidRange);
        bad[2].range_m = -1.0;
        check(good_header(10), &bad, RejectReason::InvalidRange);
        let mut bad = pts.clone();
        bad[0].inclination_rad = 4.0;
        check(good_header(10), &bad, RejectReason::InvalidAngle);
        let mut bad = pts.clone();
        bad[0].flags = 0x80;
        check(good_header(10), &bad, RejectReason::InvalidFlags);
        let none: Vec<ScanPoint> = pts
            .iter()
            .map(|p| ScanPoint {
                flags: FLAG_NO_RETURN,
                ..*p
            })
            .collect();
        check(good_header(10), &none, RejectReason::NoReturns);
    }

    #[test]
    fn reason_names_are_unique() {
        let mut names: Vec<_> = RejectReason::ALL.iter().map(|r| r.as_str()).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), RejectReason::ALL.len());
        for (i, r) in RejectReason::ALL.iter().enumerate() {
            assert_eq!(*r as usize, i, "ALL must follow declaration order");
        }
    }

    /// Seeded random cases (the failing seed is in the message): every corner float, any count.
    mod properties {
        use super::*;
        use rand::{Rng, SeedableRng};
        use rand_pcg::Pcg64;

        const CASES: u64 = 512;

        fn float(rng: &mut Pcg64) -> f64 {
            match rng.random_range(0..6) {
                0 => 0.0,
                1 => 1.0,
                2 => f64::NAN,
                3 => f64::INFINITY,
                4 => rng.random_range(-1e3..1e3),
                _ => f64::from_bits(rng.random()),
            }
        }

        fn header(rng: &mut Pcg64) -> ScanHeader {
            let f: Vec<f64> = (0..9).map(|_| float(rng)).collect();
            ScanHeader {
                protocol_version: rng.random_range(0..4),
                point_count: rng.random_range(0..200),
                publisher_id: 1,
                sequence: rng.random(),
                stamp_ns: rng.random(),
                px_m: f[0],
                py_m: f[1],
                pz_m: f[2],
                qx: f[3] * 1e-3,
                qy: f[4] * 1e-3,
                qz: f[5] * 1e-3,
                qw: if f[6].is_finite() { 1.0 } else { f[6] },
                max_range_m: f[7],
                range_noise_per_m: f[8] * 1e-3,
            }
        }

        fn point(rng: &mut Pcg64) -> ScanPoint {
            let mut float = || match rng.random_range(0..3) {
                0 => f32::NAN,
                1 => rng.random_range(-4.0..40.0f32),
                _ => f32::from_bits(rng.random()),
            };
            let (range_m, inclination_rad, azimuth_rad) = (float(), float(), float());
            ScanPoint {
                range_m,
                inclination_rad,
                azimuth_rad,
                flags: rng.random_range(0..4),
                reserved: rng.random_range(0..2),
                ..ScanPoint::default()
            }
        }

        #[test]
        fn any_header_and_points_are_accepted_only_when_sound() {
            for seed in 0..CASES {
                let mut rng = Pcg64::seed_from_u64(seed);
                let h = header(&mut rng);
                let n = rng.random_range(0..200);
                let points: Vec<ScanPoint> = (0..n).map(|_| point(&mut rng)).collect();
                let Ok(scan) = validate(&h, &points, &limits(), NOW) else {
                    continue;
                };
                let case = format!("seed {seed}: {h:?}");
                assert!(h.point_count as usize <= points.len().min(100), "{case}");
                assert!(h.stamp_ns <= NOW + 1_000_000_000, "{case}");
                assert!(scan.max_range_m.is_finite() && scan.max_range_m > 0.0, "{case}");
                assert!(
                    scan.pose.translation.vector.iter().all(|v| v.is_finite()),
                    "{case}"
                );
                assert!(!scan.rays.is_empty(), "{case}");
                for r in &scan.rays {
                    assert!(
                        r.range.is_finite() && r.range > 0.0 && r.range < scan.max_range_m,
                        "{case}"
                    );
                    assert!(r.inclination.is_finite() && r.azimuth.is_finite(), "{case}");
                }
            }
        }
    }
}
