//! The relief between returns, learnt from each scan: how far the ground departs from the
//! straight line between two returns, by the distance to the nearer of them.
//!
//! A map's answer metres from its nearest datum is a smooth continuation of the data around it;
//! what the ground does in between, no return measured. A range GP cannot know it (its σ is an
//! angular one, and between two rings far out a few milliradians span metres of ground), and the
//! prequential calibration cannot teach it either: new returns land where the scans see, so they
//! test the maps mostly near their data and never on ground hidden from every scan. The terrain's
//! own returns can: for a return p with two others a and b on either side of it, the departure
//! δ = z_p − (the line from a to b at p) is the error a straight interpolation from a and b makes
//! at p's distance from them. Its mean square by that distance, the returns' noise taken out, is
//! the variance of the relief an answer that far from data has not seen: planner layers bound
//! their σ with it, and with `gp.unseen_relief` the snapshot adds it to window answers' calibrated
//! variance ([`super::scales::Relief`]). It follows the terrain: rough
//! relief gives large departures at short distances, a smooth slope none at any.

use super::data_index::DataIndex;
use super::local::LocalRangeMap;
use super::scales::{data_bin_of, data_centre_m, Relief, DATA_BINS};
use crate::gp::sphere;
use crate::scan::ScanInput;
use nalgebra::Vector3;
use std::collections::VecDeque;

/// Returns of a scan taken as the middle point p.
pub const ANCHORS_PER_SCAN: usize = 256;
/// Departures remembered per distance bin (the oldest drop out: the estimate follows the terrain).
pub const RELIEF_MEMORY: usize = 2000;
/// Departures a bin needs before its mean counts.
pub const MIN_DEPARTURES: usize = 50;
/// How far from its target (a share of the target's distance from p) a partner may lie.
const PARTNER_TOLERANCE: f64 = 0.3;

/// One measured departure: its square and the noise variance in it, m².
#[derive(Debug, Clone, Copy)]
struct Departure {
    square: f64,
    noise_var: f64,
}

/// The recent departures by distance bin and the relief they give.
#[derive(Debug, Clone, Default)]
pub struct ReliefLearner {
    bins: [VecDeque<Departure>; DATA_BINS],
}

impl ReliefLearner {
    /// Measures departures among `scan`'s returns, placed as `map` (the scan's own map, whose pose
    /// a correction may have moved since) places them, against the index of the returns it
    /// trained on: for each of up to [`ANCHORS_PER_SCAN`] returns p and each distance bin's centre
    /// c, the returns nearest p ± c·u (u a direction turning with each try), if within
    /// `PARTNER_TOLERANCE`·c of those points and on either side of p.
    pub fn observe(&mut self, scan: &ScanInput, map: &LocalRangeMap) {
        let n = scan.rays.len();
        if n == 0 {
            return;
        }
        let (pose, data) = (map.pose(), map.data());
        let stride = n.div_ceil(ANCHORS_PER_SCAN).max(1);
        let origin = pose.translation.vector;
        let offset = (scan.sequence as usize).wrapping_mul(40_503) % stride;
        for (k, ray) in scan.rays.iter().skip(offset).step_by(stride).enumerate() {
            let [x, y, z] = sphere::to_sphere(ray.inclination, ray.azimuth, 1.0);
            let dir = pose.rotation * Vector3::new(x, y, z);
            let p = origin + dir * ray.range;
            let noise_var = (scan.range_sd(ray.range) * dir.z).powi(2);
            for bin in 0..DATA_BINS {
                // The golden angle turns the direction from one try to the next.
                let angle = (k * DATA_BINS + bin) as f64 * 2.399_963_229_7 + scan.sequence as f64;
                if let Some(d) = departure(data, &p, data_centre_m(bin), angle, noise_var) {
                    let q = &mut self.bins[data_bin_of(d.0)];
                    if q.len() == RELIEF_MEMORY {
                        q.pop_front();
                    }
                    q.push_back(d.1);
                }
            }
        }
    }

    /// The relief variance by distance bin: each bin's mean square departure less its noise,
    /// never less than a nearer bin's (a bin short of [`MIN_DEPARTURES`] takes the nearer one's).
    pub fn relief(&self) -> Relief {
        self.relief_with(None).0
    }

    /// [`Self::relief`], where a bin short of [`MIN_DEPARTURES`] that `prior` learnt (restored
    /// from before a restart, with its flags) counts the prior's variance as its own; and which
    /// bins are learnt.
    pub fn relief_with(&self, prior: Option<(&Relief, &[bool; DATA_BINS])>) -> (Relief, [bool; DATA_BINS]) {
        let mut var_m2 = [0.0; DATA_BINS];
        let mut learnt = [false; DATA_BINS];
        let mut floor = 0.0f64;
        for (k, q) in self.bins.iter().enumerate() {
            if q.len() >= MIN_DEPARTURES {
                let n = q.len() as f64;
                let square = q.iter().map(|d| d.square).sum::<f64>() / n;
                let noise = q.iter().map(|d| d.noise_var).sum::<f64>() / n;
                floor = floor.max(square - noise);
                learnt[k] = true;
            } else if let Some((relief, _)) = prior.filter(|(_, flags)| flags[k]) {
                floor = floor.max(relief.var_m2[k]);
                learnt[k] = true;
            }
            var_m2[k] = floor;
        }
        (Relief { var_m2 }, learnt)
    }
}

/// The departure of `p` from the line between the returns nearest p ± c·(cos a, sin a), with the
/// horizontal distance from p to the nearer of the two: `None` when either lies farther than
/// [`PARTNER_TOLERANCE`]·c from its target or p does not lie between them.
fn departure(
    data: &DataIndex,
    p: &Vector3<f64>,
    c: f64,
    angle: f64,
    noise_var: f64,
) -> Option<(f64, Departure)> {
    let (s, co) = angle.sin_cos();
    let tolerance = PARTNER_TOLERANCE * c;
    let (a, _) = data.nearest_within(p.x - c * co, p.y - c * s, tolerance)?;
    let (b, _) = data.nearest_within(p.x + c * co, p.y + c * s, tolerance)?;
    let ab = [b[0] - a[0], b[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    if len2 <= 0.0 {
        return None;
    }
    let t = ((p.x - a[0]) * ab[0] + (p.y - a[1]) * ab[1]) / len2;
    if !(0.2..=0.8).contains(&t) {
        return None;
    }
    let line = a[2] + t * (b[2] - a[2]);
    let near = t.min(1.0 - t) * len2.sqrt();
    // The noise of p and of the line through a and b (taken as p's own).
    let noise = noise_var * (1.0 + t * t + (1.0 - t) * (1.0 - t));
    let delta = p.z - line;
    delta.is_finite().then_some((
        near,
        Departure {
            square: delta * delta,
            noise_var: noise,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::test_support::{family_terrain, params, scan_at_centre, scan_of};
    use crate::map::LocalRangeMap;
    use nalgebra::Isometry3;

    #[test]
    fn bins_short_of_departures_keep_the_priors_learnt_relief_and_fill_the_rest() {
        let prior = Relief {
            var_m2: [0.0, 1e-4, 9.0, 4e-4, 0.5, 0.5, 0.5, 0.5],
        };
        let mut flags = [false; DATA_BINS];
        flags[1] = true;
        flags[3] = true;
        let (relief, learnt) = ReliefLearner::default().relief_with(Some((&prior, &flags)));
        assert_eq!(relief.var_m2, [0.0, 1e-4, 1e-4, 4e-4, 4e-4, 4e-4, 4e-4, 4e-4]);
        assert_eq!(learnt, flags);
        let (none, nothing) = ReliefLearner::default().relief_with(None);
        assert_eq!((none, nothing), (Relief::default(), [false; DATA_BINS]));
    }

    /// The relief learnt from one scan of `terrain` (a family terrain by name).
    fn relief_on(terrain: &str) -> Relief {
        let scan = scan_at_centre(&family_terrain(terrain, 3, 60.0));
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        let mut learner = ReliefLearner::default();
        learner.observe(&scan, &map);
        learner.relief()
    }

    #[test]
    fn rough_ground_has_more_relief_than_gentle_ground_and_it_grows_with_distance() {
        let gentle = relief_on("fbm-h08-8deg");
        let rough = relief_on("fbm-h05-30deg");
        let at = |r: &Relief, d: f64| r.var_at(d).sqrt();
        assert!(
            at(&rough, 1.0) > 2.0 * at(&gentle, 1.0),
            "{rough:?} against {gentle:?}"
        );
        assert!(at(&rough, 2.0) > at(&rough, 0.2), "{rough:?}");
        assert!(at(&gentle, 1.0) > 0.0, "{gentle:?}");
        for w in rough.var_m2.windows(2) {
            assert!(w[1] >= w[0], "never less far out: {rough:?}");
        }
    }

    #[test]
    fn nothing_is_learnt_from_a_scan_without_returns() {
        let terrain = family_terrain("craters", 3, 60.0);
        let mut scan = scan_of(&terrain, Isometry3::translation(0.0, 0.0, 1.0));
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        scan.rays.clear();
        let mut learner = ReliefLearner::default();
        learner.observe(&scan, &map);
        assert_eq!(learner.relief(), Relief::default());
    }

    #[test]
    fn a_map_moved_by_a_correction_is_measured_where_it_now_lies() {
        let scan = scan_at_centre(&family_terrain("fbm-h05-30deg", 3, 60.0));
        let map = LocalRangeMap::fit(&scan, &params()).expect("fit");
        let moved = map.reanchored(Isometry3::translation(3.0, -2.0, 0.5) * scan.pose, 1);
        let (mut here, mut there) = (ReliefLearner::default(), ReliefLearner::default());
        here.observe(&scan, &map);
        there.observe(&scan, &moved);
        // A rigid move changes no departure (up to the index's f32 coordinates).
        let (a, b) = (here.relief(), there.relief());
        for (x, y) in a.var_m2.iter().zip(b.var_m2) {
            assert!((x - y).abs() <= 1e-6 + 1e-3 * x, "{a:?} against {b:?}");
        }
        assert!(a.var_m2[DATA_BINS - 1] > 0.0, "relief learnt: {a:?}");
    }
}
