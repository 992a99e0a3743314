//! Validation of a scan copied out of shared memory. Pure functions over private copies: a scan
//! either becomes a [`ScanInput`] or is rejected with exactly one [`RejectReason`].

use super::deskew::{deskew, Twist};
use super::noise::range_noise_floor;
use crate::scan::{RayObservation, RejectReason, ScanInput};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rangegp_proto::scan::{
    ScanHeader, ScanPoint, FLAG_NO_RETURN, FLAG_RING_COLUMN_VALID, MAX_TIME_OFFSET_NS,
};
use rangegp_proto::PROTOCOL_VERSION;

/// Bounds a scan must respect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValidationLimits {
    /// Most points accepted in one scan.
    pub max_points: usize,
    /// How far a scan's stamp may lie ahead of this machine's clock, nanoseconds.
    pub max_future_ns: u64,
    /// Measure each scan's range noise floor from its returns ([`super::noise`]).
    pub learn_noise_floor: bool,
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
    if !twist_of(h).is_plausible() {
        return Err(RejectReason::InvalidMotion);
    }
    Ok(())
}

/// The header's sweep twist.
fn twist_of(h: &ScanHeader) -> Twist {
    Twist {
        linear: Vector3::new(h.vx_mps, h.vy_mps, h.vz_mps),
        angular: Vector3::new(h.wx_radps, h.wy_radps, h.wz_radps),
    }
}

/// Validates a private copy of the header and its points and builds the fitter's input.
/// Returns at or beyond the max range count as no-returns. With a non-zero twist, each return is
/// deskewed to the sensor frame at the stamp ([`deskew`]).
pub fn validate(
    h: &ScanHeader,
    points: &[ScanPoint],
    limits: &ValidationLimits,
    now_ns: u64,
) -> Result<ScanInput, RejectReason> {
    check_header(h, points.len(), limits, now_ns)?;
    let points = &points[..h.point_count as usize];
    let known_flags = FLAG_NO_RETURN | FLAG_RING_COLUMN_VALID;
    let twist = twist_of(h);
    let moving = !twist.is_zero();
    let mut rays = Vec::with_capacity(points.len());
    for p in points {
        if p.time_offset_ns > MAX_TIME_OFFSET_NS {
            return Err(RejectReason::InvalidMotion);
        }
        if p.flags & !known_flags != 0 || p.reserved != 0 {
            return Err(RejectReason::InvalidFlags);
        }
        let (inc, az) = (p.inclination_rad as f64, p.azimuth_rad as f64);
        let pi = std::f64::consts::PI + 1e-6;
        // Azimuths in [−π, π] or, as many drivers count them, in [0, 2π) (an f32 just below 2π
        // rounds to f32(2π), 1.7e-7 above it: the same slack as π's).
        if !inc.is_finite()
            || !az.is_finite()
            || !(0.0..=pi).contains(&inc)
            || !(-pi..=2.0 * pi).contains(&az)
        {
            return Err(RejectReason::InvalidAngle);
        }
        let az = if az > std::f64::consts::PI {
            az - std::f64::consts::TAU
        } else {
            az
        };
        if !p.has_return() {
            continue;
        }
        let r = p.range_m as f64;
        if !r.is_finite() || r < 0.0 {
            return Err(RejectReason::InvalidRange);
        }
        if r > 0.0 && r < h.max_range_m {
            let ray = RayObservation {
                inclination: inc,
                azimuth: az,
                range: r,
            };
            rays.push(if moving && p.time_offset_ns > 0 {
                deskew(&twist, p.time_offset_ns as f64 * 1e-9, ray)
            } else {
                ray
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
        range_noise_floor_m: if limits.learn_noise_floor {
            range_noise_floor(points, h.range_noise_per_m, h.max_range_m).unwrap_or(0.0)
        } else {
            0.0
        },
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
            learn_noise_floor: true,
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
        check(
            ScanHeader {
                wz_radps: f64::NAN,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidMotion,
        );
        check(
            ScanHeader {
                vx_mps: 150.0,
                ..good_header(10)
            },
            &pts,
            RejectReason::InvalidMotion,
        );
        let mut late = pts.clone();
        late[3].time_offset_ns = MAX_TIME_OFFSET_NS + 1;
        check(good_header(10), &late, RejectReason::InvalidMotion);
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
    fn a_turning_scan_is_deskewed_to_its_stamp_and_a_still_one_is_not() {
        let mut pts = good_points(4);
        pts[1].time_offset_ns = 100_000_000;
        let turning = ScanHeader {
            wz_radps: 0.5,
            ..good_header(4)
        };
        let scan = validate(&turning, &pts, &limits(), NOW).expect("valid");
        let still = validate(&good_header(4), &pts, &limits(), NOW).expect("valid");
        // Fired 0.1 s late while turning 0.5 rad/s to the left: 0.05 rad further left in the
        // stamp's frame.
        let turned = scan.rays[1].azimuth - still.rays[1].azimuth;
        assert!((turned - 0.05).abs() < 1e-6, "{turned}");
        assert!((scan.rays[1].range - still.rays[1].range).abs() < 1e-12);
        assert_eq!(scan.rays[0], still.rays[0], "a ray fired at the stamp stays put");
    }

    #[test]
    fn azimuths_counted_from_0_to_2pi_are_taken_as_from_minus_pi_to_pi() {
        let mut pts = good_points(4);
        pts[0].azimuth_rad = 1.5 * std::f32::consts::PI;
        pts[1].azimuth_rad = 0.25;
        // An f32 just below 2π rounds to f32(2π), a hair above 2π: taken as 0.
        pts[2].azimuth_rad = std::f32::consts::TAU;
        pts[3].azimuth_rad = 6.3;
        let scan = validate(&good_header(3), &pts, &limits(), NOW).expect("valid");
        assert!((scan.rays[0].azimuth + 0.5 * std::f64::consts::PI).abs() < 1e-6);
        assert_eq!(scan.rays[1].azimuth, 0.25f32 as f64);
        assert!(scan.rays[2].azimuth.abs() < 1e-6);
        // Past 2π is no convention: refused.
        assert_eq!(
            validate(&good_header(4), &pts, &limits(), NOW),
            Err(RejectReason::InvalidAngle)
        );
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

        /// Half the headers sound but for their random motion and count, half wild.
        fn header(rng: &mut Pcg64) -> ScanHeader {
            let f: Vec<f64> = (0..15).map(|_| float(rng)).collect();
            let motion = |v: f64, rng: &mut Pcg64| if rng.random_range(0..3) == 0 { v } else { 0.0 };
            let twist = ScanHeader {
                vx_mps: motion(f[9], rng),
                vy_mps: motion(f[10], rng),
                vz_mps: motion(f[11], rng),
                wx_radps: motion(f[12], rng),
                wy_radps: motion(f[13], rng),
                wz_radps: motion(f[14], rng),
                ..good_header(rng.random_range(0..200))
            };
            if rng.random() {
                return twist;
            }
            ScanHeader {
                protocol_version: PROTOCOL_VERSION + rng.random_range(0..2),
                sequence: rng.random(),
                stamp_ns: if rng.random() { NOW } else { rng.random() },
                px_m: f[0],
                py_m: f[1],
                pz_m: f[2],
                qx: f[3] * 1e-3,
                qy: f[4] * 1e-3,
                qz: f[5] * 1e-3,
                qw: if f[6].is_finite() { 1.0 } else { f[6] },
                max_range_m: f[7],
                range_noise_per_m: f[8] * 1e-3,
                ..twist
            }
        }

        /// Mostly plausible points, one in twenty with any bits at all.
        fn point(rng: &mut Pcg64) -> ScanPoint {
            if rng.random_range(0..20) > 0 {
                return ScanPoint {
                    range_m: rng.random_range(-1.0..40.0f32),
                    inclination_rad: rng.random_range(0.0..3.2f32),
                    azimuth_rad: rng.random_range(-3.2..3.2f32),
                    flags: rng.random_range(0..4),
                    time_offset_ns: rng.random_range(0..200_000_000),
                    ..ScanPoint::default()
                };
            }
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
                flags: rng.random_range(0..8),
                reserved: rng.random_range(0..2),
                time_offset_ns: rng.random(),
                ..ScanPoint::default()
            }
        }

        #[test]
        fn any_header_and_points_are_accepted_only_when_sound() {
            let mut accepted = 0;
            for seed in 0..CASES {
                let mut rng = Pcg64::seed_from_u64(seed);
                let h = header(&mut rng);
                let n = rng.random_range(0..200);
                let points: Vec<ScanPoint> = (0..n).map(|_| point(&mut rng)).collect();
                let Ok(scan) = validate(&h, &points, &limits(), NOW) else {
                    continue;
                };
                accepted += 1;
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
            // Not vacuous: some random scans are sound.
            assert!(accepted > 0, "no case was accepted");
        }
    }
}
