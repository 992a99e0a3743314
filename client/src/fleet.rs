//! Fleet queries: one elevation request to every map under `rangegp/*` at once (robots and site
//! daemons), answered within a deadline, fused per point by inverse variance with the maps that
//! answered it (docs/FLEET.md).

use crate::client::{Client, ClientError};
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::fleet::{RobotCell, SourcesReply, SourcesRequest};
use rangegp_proto::keys::QueryKind;
use rangegp_proto::msg::{ElevationItem, ElevationReply, ElevationRequest};
use rangegp_proto::PROTOCOL_VERSION;
use std::time::Duration;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::Wait;

/// One point's answer fused over the maps that gave a height there.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedElevation {
    /// Inverse-variance mean, metres.
    pub z_m: f64,
    /// Its variance, m² (the maps' errors taken as independent).
    pub z_var_m2: f64,
    /// The maps whose answers it fuses (their ids).
    pub maps: Vec<String>,
}

/// What every map answered to one fleet elevation request.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FleetElevation {
    /// Each answering map's id and items (one per point), in id order.
    pub maps: Vec<(String, Vec<ElevationItem>)>,
    /// Per point, the fusion of the maps that answered it with a height (`None`: none did).
    pub fused: Vec<Option<FusedElevation>>,
    /// Maps that answered with an error or with a reply that does not decode: id and reason.
    pub failed: Vec<(String, String)>,
}

impl Client {
    /// Whose cells stand behind this map's answers at `points`: per point, each robot's own
    /// cell there (a site daemon lists every robot's; a robot, its own).
    pub fn sources(&self, points: &[[f64; 2]]) -> Result<Vec<Vec<RobotCell>>, ClientError> {
        let req = SourcesRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
        };
        let rep: SourcesReply = self.call(&self.keys().query(QueryKind::Sources), &req)?;
        if rep.items.len() != points.len() {
            return Err(ClientError::BatchMismatch {
                sent: points.len(),
                got: rep.items.len(),
            });
        }
        Ok(rep.items)
    }

    /// Asks every map under `rangegp/*` (but the ids in `exclude`, such as a site daemon whose
    /// answers already fuse the robots') for the elevation at `points`, waiting at most
    /// `deadline`; maps that have not answered by then are left out.
    pub fn fleet_elevation(
        &self,
        points: &[[f64; 2]],
        deadline: Duration,
        exclude: &[&str],
    ) -> Result<FleetElevation, ClientError> {
        let encoding = Encoding::Bincode;
        let req = ElevationRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
        };
        let payload = codec::encode(encoding, &req)?;
        let key = format!("rangegp/*/query/{}", QueryKind::Elevation.as_str());
        let replies = self
            .session()
            .get(key)
            .payload(payload)
            .encoding(rangegp_transport::zenoh_encoding(encoding))
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(deadline)
            .wait()
            .map_err(|source| ClientError::Transport {
                action: "send the fleet query",
                source,
            })?;
        let mut answer = FleetElevation::default();
        while let Ok(reply) = replies.recv() {
            match reply.result() {
                Ok(sample) => {
                    let map = sample
                        .key_expr()
                        .as_str()
                        .split('/')
                        .nth(1)
                        .unwrap_or("")
                        .to_owned();
                    if exclude.contains(&map.as_str()) {
                        continue;
                    }
                    let bytes = sample.payload().to_bytes();
                    match codec::decode::<ElevationReply>(encoding, &bytes) {
                        Ok(rep) if rep.items.len() == points.len() => answer.maps.push((map, rep.items)),
                        Ok(rep) => answer.failed.push((
                            map,
                            format!("{} items for {} points", rep.items.len(), points.len()),
                        )),
                        Err(e) => answer.failed.push((map, e.to_string())),
                    }
                }
                Err(err) => answer.failed.push((
                    String::new(),
                    String::from_utf8_lossy(&err.payload().to_bytes()).into_owned(),
                )),
            }
        }
        answer.maps.sort_by(|a, b| a.0.cmp(&b.0));
        answer.fused = (0..points.len()).map(|i| fuse(&answer.maps, i)).collect();
        Ok(answer)
    }
}

/// Point `i` fused over `maps` by inverse variance.
fn fuse(maps: &[(String, Vec<ElevationItem>)], i: usize) -> Option<FusedElevation> {
    let (mut precision, mut weighted, mut names) = (0.0, 0.0, Vec::new());
    for (map, items) in maps {
        let item = &items[i];
        if let (Some(z), Some(var)) = (item.z_m, item.z_var_m2) {
            if var > 0.0 && var.is_finite() && z.is_finite() {
                precision += 1.0 / var;
                weighted += z / var;
                names.push(map.clone());
            }
        }
    }
    (precision > 0.0).then(|| FusedElevation {
        z_m: weighted / precision,
        z_var_m2: 1.0 / precision,
        maps: names,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rangegp_proto::msg::{Provenance, Source};

    fn item(z: Option<f64>, var: f64) -> ElevationItem {
        ElevationItem {
            z_m: z,
            z_var_m2: z.map(|_| var),
            point_sigma_m: None,
            source: Source::Aggregate,
            provenance: Provenance::Observed,
            refusal: None,
        }
    }

    #[test]
    fn answers_fuse_by_inverse_variance_naming_the_maps_that_gave_them() {
        let maps = vec![
            ("a".to_owned(), vec![item(Some(1.0), 1.0), item(None, 0.0)]),
            ("b".to_owned(), vec![item(Some(2.0), 3.0), item(None, 0.0)]),
        ];
        let f = fuse(&maps, 0).expect("two answers");
        assert!((f.z_m - 1.25).abs() < 1e-12 && (f.z_var_m2 - 0.75).abs() < 1e-12);
        assert_eq!(f.maps, ["a", "b"]);
        assert_eq!(fuse(&maps, 1), None);
    }
}
