//! Checkpoint generations in one directory: `aggregate-<generation>.ckpt`, newest restored first.
//!
//! A write goes to a hidden temp file, is fsynced, renamed over its final name and the directory
//! is fsynced, so a crash at any instant leaves either the old set of files or the new one. The
//! newest `keep` generations stay; a generation that fails to load is logged and the next older
//! one is tried.

use super::{decode, Checkpoint, RestoreError};
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use thiserror::Error;
use tracing::warn;

/// A checkpoint operation on disk failed.
#[derive(Debug, Error)]
pub enum StoreError {
    /// The directory cannot be created or listed.
    #[error("checkpoint directory {dir}: {source}")]
    Dir {
        /// Directory.
        dir: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Writing, syncing or renaming a file failed (disk full, read-only, I/O error).
    #[error("writing checkpoint {path}: {source}")]
    Write {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

/// The directory of checkpoint generations.
#[derive(Debug, Clone)]
pub struct Store {
    dir: PathBuf,
    keep: usize,
}

/// A checkpoint restored from disk.
#[derive(Debug)]
pub struct Restored {
    /// Its generation.
    pub generation: u64,
    /// What it held.
    pub checkpoint: Checkpoint,
    /// The aggregate rebuilt from it.
    pub world: WorldAggregate,
}

/// A checkpoint file passed over at restore, and why.
pub type Rejected = (PathBuf, RestoreError);

const PREFIX: &str = "aggregate-";
const SUFFIX: &str = ".ckpt";

impl Store {
    /// Opens (creating) `dir`, keeping the newest `keep` generations (panics if `keep` < 1) and
    /// removing temp files a crash left behind.
    pub fn open(dir: &Path, keep: usize) -> Result<Self, StoreError> {
        assert!(keep >= 1, "keep at least one checkpoint generation");
        let dir_err = |source| StoreError::Dir {
            dir: dir.to_owned(),
            source,
        };
        fs::create_dir_all(dir).map_err(dir_err)?;
        for entry in fs::read_dir(dir).map_err(dir_err)?.flatten() {
            let name = entry.file_name();
            if name.to_string_lossy().ends_with(".tmp") {
                let _ = fs::remove_file(entry.path());
            }
        }
        Ok(Self {
            dir: dir.to_owned(),
            keep,
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Generations on disk with their files, newest first.
    pub fn generations(&self) -> Result<Vec<(u64, PathBuf)>, StoreError> {
        let entries = fs::read_dir(&self.dir).map_err(|source| StoreError::Dir {
            dir: self.dir.clone(),
            source,
        })?;
        let mut found: Vec<(u64, PathBuf)> = entries
            .flatten()
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let generation = name.strip_prefix(PREFIX)?.strip_suffix(SUFFIX)?.parse().ok()?;
                Some((generation, e.path()))
            })
            .collect();
        found.sort_by_key(|g| std::cmp::Reverse(g.0));
        Ok(found)
    }

    /// Writes `bytes` as the next generation atomically and prunes old generations; returns the
    /// new file.
    pub fn write(&self, bytes: &[u8]) -> Result<PathBuf, StoreError> {
        let existing = self.generations()?;
        let generation = existing.first().map_or(1, |g| g.0 + 1);
        let path = self.dir.join(format!("{PREFIX}{generation:020}{SUFFIX}"));
        let tmp = self.dir.join(format!(".{PREFIX}{generation:020}{SUFFIX}.tmp"));
        let result = (|| {
            let mut file = File::create(&tmp)?;
            file.write_all(bytes)?;
            file.sync_all()?;
            fs::rename(&tmp, &path)?;
            File::open(&self.dir)?.sync_all()
        })();
        if let Err(e) = result {
            let _ = fs::remove_file(&tmp);
            return Err(StoreError::Write { path, source: e });
        }
        for (_, old) in existing.iter().skip(self.keep.saturating_sub(1)) {
            if let Err(e) = fs::remove_file(old) {
                warn!(file = %old.display(), error = %e, "cannot remove an old checkpoint");
            }
        }
        Ok(path)
    }

    /// Restores the newest generation that decodes, matches `identity` and `params`, and
    /// refits; every generation passed over is returned with its reason (for the log).
    pub fn restore(
        &self,
        identity: u64,
        params: &WorldParams,
    ) -> Result<(Option<Restored>, Vec<Rejected>), StoreError> {
        let mut rejected = Vec::new();
        for (generation, path) in self.generations()? {
            let loaded = fs::read(&path)
                .map_err(|e| RestoreError::Unreadable(e.kind()))
                .and_then(|bytes| Ok(decode(&bytes, identity)?))
                .and_then(|checkpoint| Ok((checkpoint.restore(params)?, checkpoint)));
            match loaded {
                Ok((world, checkpoint)) => {
                    let restored = Restored {
                        generation,
                        checkpoint,
                        world,
                    };
                    return Ok((Some(restored), rejected));
                }
                Err(e) => rejected.push((path, e)),
            }
        }
        Ok((None, rejected))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checkpoint::tests::sample;
    use crate::checkpoint::{encode, identity, FormatError};

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("rangegp-store-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn generations_are_pruned_and_a_damaged_newest_falls_back() {
        let dir = temp_dir("gens");
        let params = WorldParams::default();
        let id = identity("m", &params);
        let store = Store::open(&dir, 2).expect("open");
        let mut older = sample();
        older.created_unix_ns = 1;
        store
            .write(&encode(&older, id).expect("encode"))
            .expect("write 1");
        store
            .write(&encode(&older, id).expect("encode"))
            .expect("write 2");
        let newest = store
            .write(&encode(&sample(), id).expect("encode"))
            .expect("write 3");
        let gens: Vec<u64> = store.generations().expect("list").iter().map(|g| g.0).collect();
        assert_eq!(gens, vec![3, 2], "two generations kept");

        let (restored, rejected) = store.restore(id, &params).expect("restore");
        assert_eq!(restored.map(|r| r.generation), Some(3));
        assert!(rejected.is_empty());

        let mut bytes = fs::read(&newest).expect("read");
        let last = bytes.len() - 1;
        bytes[last] ^= 1;
        fs::write(&newest, &bytes).expect("damage");
        fs::write(dir.join(".aggregate-9.ckpt.tmp"), b"torn").expect("stray temp file");
        let store = Store::open(&dir, 2).expect("reopen");
        let (restored, rejected) = store.restore(id, &params).expect("restore");
        let restored = restored.expect("the previous generation");
        assert_eq!((restored.generation, restored.checkpoint.created_unix_ns), (2, 1));
        assert_eq!(rejected.len(), 1);
        assert_eq!(rejected[0].1, RestoreError::Format(FormatError::Checksum));
        assert!(!dir.join(".aggregate-9.ckpt.tmp").exists(), "temp files removed");
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_unwritable_directory_is_an_error_not_a_panic() {
        let file = temp_dir("not-a-dir");
        fs::write(&file, b"x").expect("file");
        assert!(matches!(Store::open(&file, 2), Err(StoreError::Dir { .. })));
        let _ = fs::remove_file(&file);
    }
}
