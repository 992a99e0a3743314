//! Pose plausibility: a scan whose pose lies outside the map's bounds, or jumped from its
//! publisher's last accepted pose faster than the robot can move, is a localisation glitch and
//! would tear the map (the aggregate evicts around the newest sensor). A publisher that really
//! was relocalised is followed once `confirm_scans` consecutive scans agree on the new place.

use nalgebra::Vector3;
use std::collections::HashMap;

/// Limits of a plausible pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseLimits {
    /// Largest |x|, |y| and |z| of a sensor position, metres.
    pub bounds_m: f64,
    /// Fastest plausible motion between two scans of one publisher, m/s.
    pub max_speed_mps: f64,
    /// Jump allowed on top of the speed limit (localisation noise, clock jitter), metres.
    pub slack_m: f64,
    /// Consecutive mutually plausible scans that confirm a relocalisation.
    pub confirm_scans: u32,
}

/// What the gate decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseVerdict {
    /// Plausible: accept.
    Plausible,
    /// The publisher was relocalised: `confirm_scans` scans agree on a new place; accept.
    Relocated,
    /// Out of bounds or an implausible jump: reject.
    Implausible,
}

/// A position at a time.
#[derive(Debug, Clone, Copy)]
struct Fix {
    stamp_ns: u64,
    position: Vector3<f64>,
}

/// Where one publisher stands.
#[derive(Debug, Clone, Copy)]
struct Track {
    accepted: Fix,
    /// Scans that disagree with `accepted` but agree with each other, and the newest of them.
    candidate: Option<(Fix, u32)>,
}

/// Per-publisher pose bookkeeping, bounded in size.
#[derive(Debug)]
pub struct PoseGate {
    limits: PoseLimits,
    publishers: HashMap<u64, Track>,
}

/// Publishers remembered at most; beyond it the table is cleared.
const MAX_TRACKED_PUBLISHERS: usize = 4096;

impl PoseGate {
    /// A gate with `limits`.
    pub fn new(limits: PoseLimits) -> Self {
        Self {
            limits,
            publishers: HashMap::new(),
        }
    }

    /// Judges the pose of a scan of `publisher` and records it: a plausible or relocated pose
    /// becomes the publisher's accepted one; an implausible one in bounds only builds the
    /// candidate a relocation needs (the accepted pose stays).
    pub fn judge(&mut self, publisher: u64, stamp_ns: u64, position: Vector3<f64>) -> PoseVerdict {
        if !self.in_bounds(&position) {
            return PoseVerdict::Implausible;
        }
        if self.publishers.len() >= MAX_TRACKED_PUBLISHERS && !self.publishers.contains_key(&publisher) {
            self.publishers.clear();
        }
        let here = Fix { stamp_ns, position };
        let limits = self.limits;
        let accepted = Track {
            accepted: here,
            candidate: None,
        };
        let Some(track) = self.publishers.get_mut(&publisher) else {
            self.publishers.insert(publisher, accepted);
            return PoseVerdict::Plausible;
        };
        if reachable(&limits, &track.accepted, &here) {
            *track = accepted;
            return PoseVerdict::Plausible;
        }
        let agreeing = match track.candidate {
            Some((fix, n)) if reachable(&limits, &fix, &here) => n + 1,
            _ => 1,
        };
        if agreeing >= limits.confirm_scans {
            *track = accepted;
            return PoseVerdict::Relocated;
        }
        track.candidate = Some((here, agreeing));
        PoseVerdict::Implausible
    }

    /// Whether every coordinate lies within ±`bounds_m` (NaN never does).
    fn in_bounds(&self, position: &Vector3<f64>) -> bool {
        position.iter().all(|v| v.abs() <= self.limits.bounds_m)
    }
}

/// Whether a robot within `limits` can get from `from` to `to` in the time between them.
fn reachable(limits: &PoseLimits, from: &Fix, to: &Fix) -> bool {
    // A stamp older than the last accepted one earns no travel time: an old or replayed stamp
    // cannot excuse a jump.
    let dt = to.stamp_ns.saturating_sub(from.stamp_ns) as f64 * 1e-9;
    (to.position - from.position).norm() <= limits.max_speed_mps * dt + limits.slack_m
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: u64 = 1_000_000_000;

    fn gate() -> PoseGate {
        PoseGate::new(PoseLimits {
            bounds_m: 1e5,
            max_speed_mps: 10.0,
            slack_m: 1.0,
            confirm_scans: 3,
        })
    }

    fn step(g: &mut PoseGate, id: u64, t: u64, x: f64) -> PoseVerdict {
        g.judge(id, t, Vector3::new(x, 0.0, 0.5))
    }

    #[test]
    fn a_glitch_is_refused_and_the_track_goes_on() {
        let mut g = gate();
        assert_eq!(step(&mut g, 1, 0, 0.0), PoseVerdict::Plausible);
        assert_eq!(
            step(&mut g, 1, S / 10, 1.5),
            PoseVerdict::Plausible,
            "1.5 m in 0.1 s: slack"
        );
        assert_eq!(step(&mut g, 1, S / 5, 50.0), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, 3 * S / 10, 2.0), PoseVerdict::Plausible);
        assert_eq!(step(&mut g, 2, 0, 1e6), PoseVerdict::Implausible, "out of bounds");
        assert_eq!(
            step(&mut g, 2, S, 1e6),
            PoseVerdict::Implausible,
            "never confirmed"
        );
        assert_eq!(step(&mut g, 2, 2 * S, 1e6), PoseVerdict::Implausible);
        assert_eq!(
            step(&mut g, 1, 100 * S, 900.0),
            PoseVerdict::Plausible,
            "far, but time passed"
        );
        assert_eq!(
            step(&mut g, 1, 0, 950.0),
            PoseVerdict::Implausible,
            "an old stamp excuses nothing"
        );
    }

    #[test]
    fn a_relocalisation_is_followed_after_the_confirming_scans() {
        let mut g = gate();
        step(&mut g, 1, 0, 0.0);
        assert_eq!(step(&mut g, 1, S / 10, 200.0), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, S / 5, 200.5), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, 3 * S / 10, 201.0), PoseVerdict::Relocated);
        assert_eq!(step(&mut g, 1, 4 * S / 10, 201.5), PoseVerdict::Plausible);
        // Glitches that disagree with each other never confirm anything.
        assert_eq!(step(&mut g, 1, 5 * S / 10, -500.0), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, 6 * S / 10, 800.0), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, 7 * S / 10, -300.0), PoseVerdict::Implausible);
        assert_eq!(step(&mut g, 1, 8 * S / 10, 202.5), PoseVerdict::Plausible);
    }
}
