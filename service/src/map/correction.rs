//! Pose corrections: which scans a correction names and where they move, and the log through
//! which every thread brings a map up to the corrections queries see.
//!
//! Each map carries the number of corrections its pose reflects (its generation); the snapshot
//! carries the number its aggregate reflects. A thread that publishes maps brings them up to
//! the snapshot's generation first, so a query never sees window maps and an aggregate that
//! disagree about a correction.

use super::aggregate::ledger::ScanRaster;
use super::aggregate::world::ScanRef;
use super::LocalRangeMap;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use rangegp_proto::msg::{CorrectionRequest, PoseCorrection, Rigid};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::Instant;
use thiserror::Error;

/// A correction request that cannot be applied (nothing is changed).
#[derive(Debug, Clone, Error, PartialEq)]
pub enum InvalidCorrection {
    /// The request names no correction.
    #[error("the request holds no correction")]
    Empty,
    /// A translation or rotation component is not finite.
    #[error("correction {index}: a pose component is not finite")]
    NotFinite {
        /// Position in the request.
        index: usize,
    },
    /// A rotation is not a unit quaternion (its norm is off by more than 1e-3).
    #[error("correction {index}: rotation quaternion has norm {norm}, not 1")]
    NotUnit {
        /// Position in the request.
        index: usize,
        /// Its norm.
        norm: f64,
    },
    /// A stamp range ends before it begins.
    #[error("correction {index}: until_stamp_ns {until} is before from_stamp_ns {from}")]
    EmptyRange {
        /// Position in the request.
        index: usize,
        /// First stamp.
        from: u64,
        /// Last stamp.
        until: u64,
    },
}

/// Who a scan is, as a correction names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ScanId {
    /// Publisher id.
    pub publisher_id: u64,
    /// Sequence number.
    pub sequence: u64,
    /// Acquisition time, ns.
    pub stamp_ns: u64,
}

impl From<&LocalRangeMap> for ScanId {
    fn from(m: &LocalRangeMap) -> Self {
        Self {
            publisher_id: m.publisher_id,
            sequence: m.sequence,
            stamp_ns: m.stamp_ns,
        }
    }
}

impl From<&ScanRaster> for ScanId {
    fn from(r: &ScanRaster) -> Self {
        Self {
            publisher_id: r.publisher_id,
            sequence: r.sequence,
            stamp_ns: r.stamp_ns,
        }
    }
}

impl From<&ScanRef> for ScanId {
    fn from(r: &ScanRef) -> Self {
        Self {
            publisher_id: r.publisher_id,
            sequence: r.sequence,
            stamp_ns: r.stamp_ns,
        }
    }
}

/// A transform over a stamp range (validated).
#[derive(Debug, Clone, Copy, PartialEq)]
struct RangeTransform {
    order: usize,
    publisher_id: Option<u64>,
    from_stamp_ns: u64,
    until_stamp_ns: u64,
    transform: Isometry3<f64>,
}

/// A pose with its place in the request.
type OrderedPose = (usize, Isometry3<f64>);

/// A validated correction request, ready to be asked about any scan.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Correction {
    /// Per (publisher, sequence): (order in the request, corrected pose).
    poses: HashMap<(u64, u64), Vec<OrderedPose>>,
    ranges: Vec<RangeTransform>,
}

/// Largest deviation of a rotation quaternion's norm from 1 that is normalised, not refused.
const UNIT_TOLERANCE: f64 = 1e-3;

/// The isometry of a wire transform, checked.
pub fn rigid(r: &Rigid, index: usize) -> Result<Isometry3<f64>, InvalidCorrection> {
    let [x, y, z, w] = r.rotation_xyzw;
    if !r
        .translation_m
        .iter()
        .chain(&r.rotation_xyzw)
        .all(|v| v.is_finite())
    {
        return Err(InvalidCorrection::NotFinite { index });
    }
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    if (norm - 1.0).abs() > UNIT_TOLERANCE {
        return Err(InvalidCorrection::NotUnit { index, norm });
    }
    let [tx, ty, tz] = r.translation_m;
    Ok(Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(q),
    ))
}

impl Correction {
    /// Validates a request.
    pub fn from_request(req: &CorrectionRequest) -> Result<Self, InvalidCorrection> {
        if req.corrections.is_empty() {
            return Err(InvalidCorrection::Empty);
        }
        let mut c = Self::default();
        for (index, item) in req.corrections.iter().enumerate() {
            match item {
                PoseCorrection::Scan {
                    publisher_id,
                    sequence,
                    pose,
                } => c
                    .poses
                    .entry((*publisher_id, *sequence))
                    .or_default()
                    .push((index, rigid(pose, index)?)),
                PoseCorrection::Transform {
                    publisher_id,
                    from_stamp_ns,
                    until_stamp_ns,
                    transform,
                } => {
                    if until_stamp_ns < from_stamp_ns {
                        return Err(InvalidCorrection::EmptyRange {
                            index,
                            from: *from_stamp_ns,
                            until: *until_stamp_ns,
                        });
                    }
                    c.ranges.push(RangeTransform {
                        order: index,
                        publisher_id: *publisher_id,
                        from_stamp_ns: *from_stamp_ns,
                        until_stamp_ns: *until_stamp_ns,
                        transform: rigid(transform, index)?,
                    });
                }
            }
        }
        Ok(c)
    }

    /// The corrected pose of scan `id` now at `pose`, or `None` when no correction names it.
    pub fn apply(&self, id: ScanId, pose: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        let mut steps: Vec<(usize, Step)> = self
            .ranges
            .iter()
            .filter(|r| {
                r.publisher_id.is_none_or(|p| p == id.publisher_id)
                    && (r.from_stamp_ns..=r.until_stamp_ns).contains(&id.stamp_ns)
            })
            .map(|r| (r.order, Step::By(r.transform)))
            .collect();
        if let Some(poses) = self.poses.get(&(id.publisher_id, id.sequence)) {
            steps.extend(poses.iter().map(|&(order, p)| (order, Step::To(p))));
        }
        if steps.is_empty() {
            return None;
        }
        steps.sort_by_key(|&(order, _)| order);
        Some(steps.iter().fold(*pose, |p, (_, step)| match step {
            Step::To(to) => *to,
            Step::By(by) => by * p,
        }))
    }

    /// Whether the correction names scan `id`.
    pub fn names(&self, id: ScanId) -> bool {
        self.apply(id, &Isometry3::identity()).is_some()
    }

    /// How many of `maps` the correction names.
    pub fn maps_named(&self, maps: &[Arc<LocalRangeMap>]) -> usize {
        maps.iter().filter(|m| self.names(m.as_ref().into())).count()
    }
}

/// One step of a correction.
#[derive(Debug, Clone, Copy)]
enum Step {
    To(Isometry3<f64>),
    By(Isometry3<f64>),
}

/// Corrections kept for maps still on their way to the window or the aggregate.
pub const KEPT_CORRECTIONS: usize = 64;

/// The corrections applied so far, numbered from 1.
#[derive(Debug, Default)]
pub struct CorrectionLog {
    generation: u64,
    entries: VecDeque<(u64, Instant, Arc<Correction>)>,
}

impl CorrectionLog {
    /// Records a correction; returns its generation.
    pub fn push(&mut self, correction: Arc<Correction>, issued: Instant) -> u64 {
        self.generation += 1;
        if self.entries.len() == KEPT_CORRECTIONS {
            self.entries.pop_front();
        }
        self.entries.push_back((self.generation, issued, correction));
        self.generation
    }

    /// Turns correction `generation` into one that names no scan (it could not be applied).
    pub fn void(&mut self, generation: u64) {
        if let Some(entry) = self.entries.iter_mut().find(|(g, _, _)| *g == generation) {
            entry.2 = Arc::new(Correction::default());
        }
    }

    /// Corrections recorded.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// The corrections issued by `at`: a scan received then was sent with their poses.
    pub fn generation_at(&self, at: Instant) -> u64 {
        self.entries
            .iter()
            .rev()
            .find(|(_, issued, _)| *issued <= at)
            .map_or(
                self.generation - self.entries.len().min(self.generation as usize) as u64,
                |(g, _, _)| *g,
            )
    }

    /// `map` with the corrections after its generation up to `to` applied (itself when none
    /// names it, only marked).
    pub fn bring_up(&self, map: &Arc<LocalRangeMap>, to: u64) -> Arc<LocalRangeMap> {
        if map.generation() >= to {
            return Arc::clone(map);
        }
        let id = ScanId::from(map.as_ref());
        let pose = self
            .entries
            .iter()
            .filter(|(g, _, _)| *g > map.generation() && *g <= to)
            .fold(None, |pose: Option<Isometry3<f64>>, (_, _, c)| {
                let now = pose.unwrap_or(*map.pose());
                c.apply(id, &now).or(pose)
            });
        Arc::new(match pose {
            Some(p) => map.reanchored(p, to),
            None => LocalRangeMap::clone(map).with_generation(to),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn wire(t: [f64; 3], yaw: f64) -> Rigid {
        let q = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        Rigid {
            translation_m: t,
            rotation_xyzw: [q.i, q.j, q.k, q.w],
        }
    }

    fn id(publisher_id: u64, sequence: u64, stamp_ns: u64) -> ScanId {
        ScanId {
            publisher_id,
            sequence,
            stamp_ns,
        }
    }

    #[test]
    fn corrections_apply_in_request_order_to_the_scans_they_name() {
        let req = CorrectionRequest {
            version: rangegp_proto::PROTOCOL_VERSION,
            corrections: vec![
                PoseCorrection::Scan {
                    publisher_id: 1,
                    sequence: 5,
                    pose: wire([10.0, 0.0, 1.0], 0.0),
                },
                PoseCorrection::Transform {
                    publisher_id: Some(1),
                    from_stamp_ns: 100,
                    until_stamp_ns: u64::MAX,
                    transform: wire([0.0, 1.0, 0.0], std::f64::consts::FRAC_PI_2),
                },
            ],
        };
        let c = Correction::from_request(&req).expect("valid");
        let start = Isometry3::translation(1.0, 0.0, 0.0);
        // Named by both: set to (10, 0, 1), then turned 90° about z and moved 1 m along y.
        let p = c.apply(id(1, 5, 200), &start).expect("named");
        assert!((p.translation.vector - Vector3::new(0.0, 11.0, 1.0)).norm() < 1e-12);
        // Only the transform: (1, 0, 0) → (0, 2, 0).
        let p = c.apply(id(1, 6, 300), &start).expect("named");
        assert!((p.translation.vector - Vector3::new(0.0, 2.0, 0.0)).norm() < 1e-12);
        // Before the range, another publisher: untouched.
        assert!(c.apply(id(1, 4, 50), &start).is_none());
        assert!(c.apply(id(2, 6, 300), &start).is_none());
    }

    #[test]
    fn bad_requests_are_refused_with_the_item_at_fault() {
        let bad = |item: PoseCorrection| {
            Correction::from_request(&CorrectionRequest {
                version: 7,
                corrections: vec![item],
            })
        };
        let mut q = wire([0.0; 3], 0.0);
        q.rotation_xyzw = [0.0, 0.0, 0.0, 2.0];
        assert!(matches!(
            bad(PoseCorrection::Scan {
                publisher_id: 1,
                sequence: 1,
                pose: q
            }),
            Err(InvalidCorrection::NotUnit { index: 0, .. })
        ));
        let mut nan = wire([0.0; 3], 0.0);
        nan.translation_m[1] = f64::NAN;
        assert_eq!(
            bad(PoseCorrection::Transform {
                publisher_id: None,
                from_stamp_ns: 0,
                until_stamp_ns: 1,
                transform: nan
            }),
            Err(InvalidCorrection::NotFinite { index: 0 })
        );
        assert!(matches!(
            bad(PoseCorrection::Transform {
                publisher_id: None,
                from_stamp_ns: 5,
                until_stamp_ns: 1,
                transform: wire([0.0; 3], 0.0)
            }),
            Err(InvalidCorrection::EmptyRange { .. })
        ));
        assert_eq!(
            Correction::from_request(&CorrectionRequest {
                version: 7,
                corrections: vec![]
            }),
            Err(InvalidCorrection::Empty)
        );
    }

    #[test]
    fn the_log_says_which_corrections_a_scan_was_sent_after() {
        let mut log = CorrectionLog::default();
        let t0 = Instant::now();
        assert_eq!(log.generation_at(t0), 0);
        let g = log.push(Arc::new(Correction::default()), t0);
        assert_eq!((g, log.generation()), (1, 1));
        assert_eq!(log.generation_at(t0), 1);
        let before = t0
            .checked_sub(std::time::Duration::from_millis(1))
            .expect("clock");
        assert_eq!(log.generation_at(before), 0);
    }
}
