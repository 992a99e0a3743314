//! Durable checkpoints of the world aggregate (docs/OPERATIONS.md "Checkpoints").
//!
//! - [`format`](mod@format): the file layout — magic, format version, identity hash, length, bincode
//!   payload, xxh3 checksum — and its one encode / decode pair.
//! - [`store`]: generations on disk, written atomically (temp file, fsync, rename, fsync of the
//!   directory), the newest valid one restored.
//! - [`writer`]: the thread that writes the published aggregate when it changed.
//! - [`pages`]: the site map: tiles beyond the radius, one file each, back when the robot is.
//!
//! A checkpoint holds what the daemon needs to resume its map: the aggregate's cells (tiles are
//! refitted from them) and how each was seen, the scans it folded in, the online kernel
//! hyperparameters and the learnt σ scales. The window of local maps is not kept: it is rebuilt
//! by the next scans within a second.

pub mod format;
pub mod format3;
pub mod format4;
pub mod format5;
pub mod pages;
pub mod store;
pub mod writer;

use crate::map::aggregate::world::{
    record_in_domain, WorldAggregate, WorldParams, WorldState, HISTORY_LEN, VIEWS_KEPT,
};
use crate::map::aggregate::AggregateError;
use crate::map::scales::SigmaScales;
use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use format::{decode, encode, FormatError};
pub use pages::{PageError, PageReader, PageStore};
pub use store::{Restored, Store, StoreError};

/// What one checkpoint holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// When it was taken, nanoseconds since the Unix epoch.
    pub created_unix_ns: u64,
    /// Kernel variance the fitter used, m² (restored when online learning is on).
    pub kernel_variance: f64,
    /// Kernel length scale the fitter used (restored when online learning is on).
    pub length_scale: f64,
    /// The aggregate.
    pub world: WorldState,
    /// The σ scales the calibrator had learnt (`None`: none kept, as in format 5 and before):
    /// a restarted daemon answers with them, and they stand for each part the calibrator has
    /// not relearnt since ([`Calibrator::with_prior`](crate::map::calibration::Calibrator::with_prior)).
    pub scales: Option<SigmaScales>,
}

/// A checkpoint of format 5 or older: the same header fields, and the aggregate's state as that
/// format kept it (`W`), read on upgrade ([`format::decode`]); it holds no σ scales.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OldCheckpoint<W> {
    /// When it was taken, nanoseconds since the Unix epoch.
    pub created_unix_ns: u64,
    /// Kernel variance the fitter used, m².
    pub kernel_variance: f64,
    /// Kernel length scale the fitter used.
    pub length_scale: f64,
    /// The aggregate.
    pub world: W,
}

impl<W: Into<WorldState>> From<OldCheckpoint<W>> for Checkpoint {
    fn from(c: OldCheckpoint<W>) -> Self {
        Self {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: c.world.into(),
            scales: None,
        }
    }
}

/// Why a decoded checkpoint cannot be restored.
#[derive(Debug, Error, PartialEq)]
pub enum RestoreError {
    /// The file cannot be read (permissions, I/O error, removed meanwhile).
    #[error("unreadable: {0}")]
    Unreadable(std::io::ErrorKind),
    /// The file itself is damaged or from elsewhere.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The aggregate settings differ from this daemon's.
    #[error("aggregate settings differ from the configured ones")]
    ParamsDiffer,
    /// A value is out of its domain (a cell with a non-finite height, say).
    #[error("invalid content: {0}")]
    Invalid(&'static str),
    /// The aggregate's tiles could not be refitted from its cells.
    #[error("tiles cannot be refitted: {0}")]
    Refit(#[from] AggregateError),
}

/// What the identity hashes in the slot of `max_gap_m`: the value every file before step 25
/// was written under. The gap is an answer-time setting ([`WorldParams::same_cells_as`]); the
/// slot keeps that value so that those files stay this map's.
const IDENTITY_MAX_GAP_M: f64 = 0.75;

/// The identity a checkpoint must match to be restored: the map id and the aggregate settings
/// the cells depend on (a checkpoint of another map, or of cells of another size, is foreign).
pub fn identity(map_id: &str, params: &WorldParams) -> u64 {
    let mut text = String::from(map_id);
    for v in [
        params.cell_m,
        params.kernel_variance,
        params.length_scale,
        params.nugget_m2,
        params.max_cell_sd_m,
        IDENTITY_MAX_GAP_M,
        params.max_reach_m,
    ] {
        text.push_str(&format!("|{:016x}", v.to_bits()));
    }
    text.push_str(&format!("|{}|{}", params.tile_cells, params.margin_cells));
    xxhash_rust::xxh3::xxh3_64(text.as_bytes())
}

impl Checkpoint {
    /// Checks every value and rebuilds the aggregate (refitting its tiles), answering under
    /// `params` (whose answer-time settings may differ from the checkpoint's).
    pub fn restore(&self, params: &WorldParams) -> Result<WorldAggregate, RestoreError> {
        let w = &self.world;
        if !w.params.same_cells_as(params) {
            return Err(RestoreError::ParamsDiffer);
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.kernel_variance) || !positive(self.length_scale) {
            return Err(RestoreError::Invalid("kernel hyperparameters must be positive"));
        }
        let cells_ok = w
            .cells
            .iter()
            .all(|(_, c)| c.z.is_finite() && positive(c.var) && c.scans > 0);
        if !cells_ok {
            return Err(RestoreError::Invalid(
                "a cell has a non-finite height or variance",
            ));
        }
        if w.cells.windows(2).any(|p| p[0].0 >= p[1].0) {
            return Err(RestoreError::Invalid("cells are not sorted and unique"));
        }
        if w.history.len() > HISTORY_LEN || w.history.len() as u64 > w.inserts {
            return Err(RestoreError::Invalid("scan history longer than its bound"));
        }
        let weights_ok = w
            .history
            .iter()
            .flat_map(|r| r.departure_weights)
            .all(|v| v.is_finite() && v >= 0.0);
        if !weights_ok {
            return Err(RestoreError::Invalid(
                "a scan's departure weight is negative or not finite",
            ));
        }
        if w.views.len() > VIEWS_KEPT || w.views.iter().flatten().any(|v| !v.is_finite()) {
            return Err(RestoreError::Invalid(
                "more recent sensor positions than kept, or one not finite",
            ));
        }
        if w.seen.windows(2).any(|p| p[0].0 >= p[1].0) {
            return Err(RestoreError::Invalid(
                "seen-from records are not sorted and unique",
            ));
        }
        if !w.seen.iter().all(|&(_, record)| record_in_domain(record)) {
            return Err(RestoreError::Invalid(
                "a cell's seen-from distance or grazing is out of its domain",
            ));
        }
        Ok(WorldAggregate::from_state(WorldState {
            params: *params,
            ..w.clone()
        })?)
    }

    /// Drops σ scales that are not ones a calibrator could have learnt
    /// ([`calibration::check`](crate::map::calibration::check)), logging why: the map is kept
    /// and the scales are relearnt from the next scans.
    pub fn drop_invalid_scales(&mut self) {
        if let Some(Err(reason)) = self.scales.as_ref().map(crate::map::calibration::check) {
            tracing::warn!(
                reason,
                "checkpointed σ scales dropped; they are relearnt from the next scans"
            );
            self.scales = None;
        }
    }
}

/// Opens the checkpoint directory of `config` and restores the newest valid generation, logging
/// every file passed over and why. A directory that cannot be opened is logged and counted as a
/// failure: the daemon then runs without checkpoints rather than not at all.
pub fn resume(
    dir: Option<&std::path::Path>,
    keep: usize,
    map_id: &str,
    params: &WorldParams,
    metrics: &crate::metrics::Metrics,
) -> (Option<Store>, Option<Restored>) {
    use std::sync::atomic::Ordering::Relaxed;
    let Some(dir) = dir else {
        return (None, None);
    };
    let store = match Store::open(dir, keep) {
        Ok(store) => store,
        Err(e) => {
            metrics.checkpoint_failures.fetch_add(1, Relaxed);
            tracing::error!(error = %e, "checkpoints disabled: the aggregate will not survive a restart");
            return (None, None);
        }
    };
    let restored = match store.restore(identity(map_id, params), params) {
        Ok((restored, rejected)) => {
            for (file, reason) in &rejected {
                metrics.checkpoints_rejected.fetch_add(1, Relaxed);
                tracing::warn!(file = %file.display(), %reason, "checkpoint rejected; trying the previous generation");
            }
            restored
        }
        Err(e) => {
            metrics.checkpoint_failures.fetch_add(1, Relaxed);
            tracing::error!(error = %e, "cannot list checkpoints; starting with an empty aggregate");
            None
        }
    };
    match &restored {
        Some(r) => tracing::info!(
            generation = r.generation,
            cells = r.world.cells().len(),
            tiles = r.world.tiles(),
            inserts = r.world.inserts(),
            newest_sequence = r.world.newest_scan().map(|s| s.sequence),
            "aggregate restored from checkpoint"
        ),
        None => {
            tracing::info!(dir = %store.dir().display(), "no usable checkpoint; starting with an empty aggregate")
        }
    }
    (Some(store), restored)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::map::aggregate::world::{Cell, ScanRef, SQUARE};
    use crate::map::aggregate::Aggregate;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    /// A small checkpoint: a 2 m × 2 m patch of sloped ground.
    pub(crate) fn sample() -> Checkpoint {
        let params = WorldParams::default();
        let cells = (0..8)
            .flat_map(|i| (0..8).map(move |j| (i, j)))
            .map(|(i, j)| {
                let z = 0.02 * i as f64 - 0.01 * j as f64;
                (
                    (i, j),
                    Cell {
                        z,
                        var: 1e-4,
                        scans: 1,
                    },
                )
            })
            .collect();
        let history = vec![ScanRef {
            publisher_id: 3,
            sequence: 9,
            stamp_ns: 1,
            insert: 0,
            reach_m: 10.0,
            departure_weights: [0.0, 0.0, 1.0 / 64.0, 0.25, 1.0, 1.0, 0.0],
        }];
        Checkpoint {
            created_unix_ns: 42,
            kernel_variance: 5e-4,
            length_scale: 0.97,
            world: WorldState {
                params,
                cells,
                inserts: 1,
                history,
                views: vec![[0.5, -1.0]],
                seen: vec![((0, 0), [3.5, 0.4]), ((0, 1), [12.0, 1.0]), ((5, 2), [7.25, 0.8])],
            },
            scales: Some(SigmaScales {
                departure: [0.0, 1.0 / 64.0, 0.25, 0.25, 1.0, 0.0, 0.0],
                tails: crate::map::scales::TailShape { dof: 3.0, scale: 0.8 },
                correlation: crate::map::scales::ErrorCorrelation { length_m: 0.3 },
                ..SigmaScales::default()
            }),
        }
    }

    fn id() -> u64 {
        identity("m", &WorldParams::default())
    }

    #[test]
    fn a_checkpoint_round_trips_and_restores() {
        let c = sample();
        let bytes = encode(&c, id()).expect("encode");
        let back = decode(&bytes, id()).expect("decode");
        assert_eq!(back, c);
        let world = back.restore(&WorldParams::default()).expect("restore");
        assert_eq!(world.inserts(), 1);
        assert!(world.elevation(1.0, 1.0).is_some());
        // How its cells were seen comes back with them.
        assert_eq!(world.state().seen, c.world.seen);
        let seen = world.seen_at(0.125, 0.125, 99.0);
        assert_eq!((seen.distance_m, seen.grazing), (3.5, f64::from(0.4f32)));
    }

    #[test]
    fn a_checkpoint_written_under_another_gap_or_change_detection_is_this_maps() {
        let today = WorldParams::default();
        let before = WorldParams {
            max_gap_m: 0.75,
            ..today
        };
        assert_eq!(identity("m", &before), id(), "the gap is no part of the identity");
        let mut c = sample();
        c.world.params = before;
        let bytes = encode(&c, identity("m", &before)).expect("encode");
        let world = decode(&bytes, id())
            .expect("decode")
            .restore(&today)
            .expect("restore");
        assert_eq!(world.params().max_gap_m, today.max_gap_m);
        // A point 0.6 m beyond the last row of cells (centres at y = 1.875): answered under the
        // old gap, not under today's.
        let (x, y) = (0.125, 1.875 + 0.6);
        let old = c.restore(&before).expect("restore under the old gap");
        assert!(old.elevation(x, y).is_some());
        assert!(world.elevation(x, y).is_none());
        // Change detection turned on across a restart keeps the map too; another cell size
        // does not.
        let detecting = WorldParams {
            change_detection: true,
            ..today
        };
        assert_eq!(identity("m", &detecting), id());
        assert!(c.restore(&detecting).is_ok_and(|w| w.params().change_detection));
        let coarser = WorldParams { cell_m: 0.5, ..today };
        assert_eq!(c.restore(&coarser).err(), Some(RestoreError::ParamsDiffer));
    }

    #[test]
    fn a_format_5_checkpoint_is_read_with_no_seen_records_and_no_scales() {
        let c = sample();
        let old = format5::CheckpointV5 {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: format5::WorldStateV5 {
                params: c.world.params,
                cells: c.world.cells.clone(),
                inserts: c.world.inserts,
                history: c.world.history.clone(),
                views: c.world.views.clone(),
            },
        };
        let bytes = format::encode_framed(format::MAGIC, format5::VERSION, &old, id()).expect("encode");
        let back = decode(&bytes, id()).expect("a format-5 checkpoint decodes");
        let expected = Checkpoint {
            world: WorldState {
                seen: Vec::new(),
                ..c.world.clone()
            },
            scales: None,
            ..c
        };
        assert_eq!(back, expected);
        let world = back.restore(&WorldParams::default()).expect("restore");
        let seen = world.seen_at(0.125, 0.125, 99.0);
        assert_eq!((seen.distance_m, seen.grazing), (99.0, SQUARE));
    }

    /// `c`'s history as formats 3 and 4 kept it, and as they are read: with weights 0.
    fn history_v4(c: &Checkpoint) -> (Vec<format4::ScanRefV4>, Vec<ScanRef>) {
        let old: Vec<format4::ScanRefV4> = c
            .world
            .history
            .iter()
            .map(|r| format4::ScanRefV4 {
                publisher_id: r.publisher_id,
                sequence: r.sequence,
                stamp_ns: r.stamp_ns,
                insert: r.insert,
                reach_m: r.reach_m,
            })
            .collect();
        let read = old.iter().map(|&r| ScanRef::from(r)).collect();
        (old, read)
    }

    #[test]
    fn a_format_4_checkpoint_is_read_with_its_scans_fused_with_weights_0() {
        let c = sample();
        let (history, read) = history_v4(&c);
        assert!(c.world.history[0].departure_weights.iter().any(|&w| w > 0.0));
        let old = format4::CheckpointV4 {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: format4::WorldStateV4 {
                params: c.world.params,
                cells: c.world.cells.clone(),
                inserts: c.world.inserts,
                history,
                views: c.world.views.clone(),
            },
        };
        let bytes = format::encode_framed(format::MAGIC, format4::VERSION, &old, id()).expect("encode");
        let back = decode(&bytes, id()).expect("a format-4 checkpoint decodes");
        assert!(read
            .iter()
            .all(|r| r.departure_weights == [0.0; crate::map::scales::BINS]));
        let expected = Checkpoint {
            world: WorldState {
                history: read,
                seen: Vec::new(),
                ..c.world
            },
            scales: None,
            ..c
        };
        assert_eq!(back, expected);
        assert!(back.restore(&WorldParams::default()).is_ok());
    }

    #[test]
    fn a_format_3_checkpoint_is_read_with_no_recent_views() {
        let c = sample();
        let (history, read) = history_v4(&c);
        let old = format3::CheckpointV3 {
            created_unix_ns: c.created_unix_ns,
            kernel_variance: c.kernel_variance,
            length_scale: c.length_scale,
            world: format3::WorldStateV3 {
                params: c.world.params,
                cells: c.world.cells.clone(),
                inserts: c.world.inserts,
                history,
            },
        };
        let bytes = format::encode_framed(format::MAGIC, format3::VERSION, &old, id()).expect("encode");
        let back = decode(&bytes, id()).expect("a format-3 checkpoint decodes");
        let without_views = Checkpoint {
            world: WorldState {
                views: Vec::new(),
                history: read,
                seen: Vec::new(),
                ..c.world
            },
            scales: None,
            ..c
        };
        assert_eq!(back, without_views);
        assert!(back.restore(&WorldParams::default()).is_ok());
        let other = format::encode_framed(format::MAGIC, 2, &old, id()).expect("encode");
        assert_eq!(
            decode(&other, id()).err(),
            Some(FormatError::Version {
                found: 2,
                reads: format::FORMAT_VERSION
            })
        );
    }

    #[test]
    fn each_kind_of_damage_has_its_reason() {
        let bytes = encode(&sample(), id()).expect("encode");
        let with = |f: &dyn Fn(&mut Vec<u8>)| {
            let mut b = bytes.clone();
            f(&mut b);
            decode(&b, id()).err()
        };
        assert_eq!(with(&|b| b.truncate(20)), Some(FormatError::TooShort(20)));
        assert_eq!(with(&|b| b[0] ^= 1), Some(FormatError::BadMagic));
        assert_eq!(
            with(&|b| b[8] = 9),
            Some(FormatError::Version {
                found: 9,
                reads: format::FORMAT_VERSION
            })
        );
        assert!(matches!(with(&|b| b[12] ^= 1), Some(FormatError::Foreign { .. })));
        assert!(matches!(with(&|b| b.push(0)), Some(FormatError::Length { .. })));
        let mid = bytes.len() / 2;
        assert_eq!(with(&|b| b[mid] ^= 0x10), Some(FormatError::Checksum));
        assert!(matches!(
            decode(&bytes, identity("other map", &WorldParams::default())),
            Err(FormatError::Foreign { .. })
        ));
    }

    #[test]
    fn content_out_of_its_domain_is_refused() {
        let params = WorldParams::default();
        let mut c = sample();
        c.world.cells[3].1.z = f64::NAN;
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        let mut c = sample();
        c.world.cells.swap(0, 1);
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        let mut c = sample();
        c.length_scale = -1.0;
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        let mut c = sample();
        c.world.views[0][1] = f64::INFINITY;
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        let mut c = sample();
        c.world.views = vec![[0.0, 0.0]; VIEWS_KEPT + 1];
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        let mut c = sample();
        c.world.seen.swap(0, 1);
        assert!(matches!(c.restore(&params), Err(RestoreError::Invalid(_))));
        for bad in [[-1.0, 0.5], [f32::NAN, 0.5], [3.0, 1.5], [3.0, f32::INFINITY]] {
            let mut c = sample();
            c.world.seen[1].1 = bad;
            assert!(
                matches!(c.restore(&params), Err(RestoreError::Invalid(_))),
                "{bad:?}"
            );
        }
        // Scales out of their domain are dropped; the map is kept.
        let mut c = sample();
        c.scales
            .as_mut()
            .expect("the sample has scales")
            .correlation
            .length_m = 0.0;
        assert!(c.restore(&params).is_ok());
        c.drop_invalid_scales();
        assert_eq!(c.scales, None);
        let mut c = sample();
        c.drop_invalid_scales();
        assert_eq!(c.scales, sample().scales, "valid scales are kept");
        assert!(sample().restore(&params).is_ok());
        let other = WorldParams {
            cell_m: 0.5,
            ..params
        };
        assert_eq!(sample().restore(&other).err(), Some(RestoreError::ParamsDiffer));
    }

    /// Seeded random cases (the failing seed is in the message).
    const CASES: u64 = 512;

    #[test]
    fn arbitrary_bytes_never_decode_or_panic() {
        for seed in 0..CASES {
            let mut rng = Pcg64::seed_from_u64(seed);
            let bytes: Vec<u8> = (0..rng.random_range(0..512)).map(|_| rng.random()).collect();
            assert!(decode(&bytes, id()).is_err(), "seed {seed}");
        }
    }

    #[test]
    fn any_damage_to_a_valid_file_is_caught() {
        let bytes = encode(&sample(), id()).expect("encode");
        for seed in 0..CASES {
            let mut rng = Pcg64::seed_from_u64(seed);
            let mut damaged = bytes.clone();
            if rng.random() {
                damaged.truncate(rng.random_range(0..bytes.len()));
            } else {
                damaged[rng.random_range(0..bytes.len())] ^= rng.random_range(1..=255u8);
            }
            assert!(decode(&damaged, id()).is_err(), "seed {seed}");
        }
    }

    #[test]
    fn decoded_payloads_never_panic_restore() {
        let corner = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
        ];
        for seed in 0..CASES {
            let mut rng = Pcg64::seed_from_u64(seed);
            let mut float = || match rng.random_range(0..3) {
                0 => corner[rng.random_range(0..corner.len())],
                1 => rng.random_range(-1e3..1e3),
                _ => f64::from_bits(rng.random()),
            };
            let (z, var) = (float(), float());
            let scans = if rng.random() { 0 } else { rng.random() };
            let mut c = sample();
            c.world.cells[5].1 = Cell { z, var, scans };
            let back = decode(&encode(&c, id()).expect("encode"), id()).expect("decode");
            let ok = z.is_finite() && var.is_finite() && var > 0.0 && scans > 0;
            if !ok {
                assert!(back.restore(&WorldParams::default()).is_err(), "seed {seed}");
            }
        }
    }
}
