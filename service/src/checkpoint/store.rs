//! Checkpoint generations in one directory: `aggregate-<generation>.ckpt`, newest restored first.
//!
//! A write goes to a hidden temp file, is fsynced, renamed over its final name and the directory
//! is fsynced, so a crash at any instant leaves either the old set of files or the new one. The
//! newest `keep` generations stay; a generation that fails to load is logged and the next older
//! one is tried.
//!
//! Only files this store wrote count: a name of exactly `aggregate-` + 20 digits + `.ckpt` whose
//! first bytes are the checkpoint magic. Anything else in the directory is never counted, never
//! pruned. Generation numbers are checked: at `u64::MAX` the store refuses to write
//! ([`StoreError::GenerationsExhausted`]) rather than wrap and prune the valid files. The new
//! generation is never pruned, and nothing is pruned unless the new file is durable.

use super::format::MAGIC;
use super::{decode, Checkpoint, RestoreError};
use crate::map::aggregate::world::{WorldAggregate, WorldParams};
use std::fs::{self, File};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
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
    /// The newest generation on disk is `u64::MAX`: no next number exists. Move the
    /// checkpoints away (or `rangegpd reset-checkpoints`) to start the numbering again.
    #[error("checkpoint generation {0} is the last one; reset the checkpoint directory")]
    GenerationsExhausted(u64),
}

/// The file operations a store uses, so that tests can make each of them fail.
pub trait Disk: Send + Sync + std::fmt::Debug {
    /// Creates `path` (truncating) and writes all of `bytes` to it.
    fn write_file(&self, path: &Path, bytes: &[u8]) -> std::io::Result<()>;
    /// Flushes `path`'s content to stable storage.
    fn sync_file(&self, path: &Path) -> std::io::Result<()>;
    /// Renames `from` over `to`.
    fn rename(&self, from: &Path, to: &Path) -> std::io::Result<()>;
    /// Flushes the directory entry list of `dir` to stable storage.
    fn sync_dir(&self, dir: &Path) -> std::io::Result<()>;
    /// Removes `path`.
    fn remove(&self, path: &Path) -> std::io::Result<()>;
}

/// The real file system.
#[derive(Debug, Clone, Copy, Default)]
pub struct OsDisk;

impl Disk for OsDisk {
    fn write_file(&self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        File::create(path)?.write_all(bytes)
    }

    fn sync_file(&self, path: &Path) -> std::io::Result<()> {
        File::open(path)?.sync_all()
    }

    fn rename(&self, from: &Path, to: &Path) -> std::io::Result<()> {
        fs::rename(from, to)
    }

    fn sync_dir(&self, dir: &Path) -> std::io::Result<()> {
        File::open(dir)?.sync_all()
    }

    fn remove(&self, path: &Path) -> std::io::Result<()> {
        fs::remove_file(path)
    }
}

/// The directory of checkpoint generations.
#[derive(Debug, Clone)]
pub struct Store {
    dir: PathBuf,
    keep: usize,
    disk: Arc<dyn Disk>,
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
/// Digits of a generation number in a file name (`u64::MAX` has 20).
const DIGITS: usize = 20;

/// The generation a file name names, if it is exactly a name this store writes.
fn parse_name(name: &str) -> Option<u64> {
    let digits = name.strip_prefix(PREFIX)?.strip_suffix(SUFFIX)?;
    if digits.len() != DIGITS || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

/// Whether `path` starts with the checkpoint magic (a file this store wrote, maybe damaged since).
fn has_magic(path: &Path) -> bool {
    let mut head = [0u8; MAGIC.len()];
    File::open(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok_and(|()| head == MAGIC)
}

impl Store {
    /// Opens (creating) `dir` on the real file system; see [`Store::open_on`].
    pub fn open(dir: &Path, keep: usize) -> Result<Self, StoreError> {
        Self::open_on(dir, keep, Arc::new(OsDisk))
    }

    /// Opens (creating) `dir` with the file operations of `disk`, keeping the newest `keep`
    /// generations (panics if `keep` < 1) and removing temp files a crash left behind.
    pub fn open_on(dir: &Path, keep: usize, disk: Arc<dyn Disk>) -> Result<Self, StoreError> {
        assert!(keep >= 1, "keep at least one checkpoint generation");
        let dir_err = |source| StoreError::Dir {
            dir: dir.to_owned(),
            source,
        };
        fs::create_dir_all(dir).map_err(dir_err)?;
        for entry in fs::read_dir(dir).map_err(dir_err)?.flatten() {
            let name = entry.file_name();
            let name = name.to_string_lossy();
            let ours = name
                .strip_prefix('.')
                .and_then(|n| n.strip_suffix(".tmp"))
                .and_then(parse_name)
                .is_some();
            if ours {
                let _ = disk.remove(&entry.path());
            }
        }
        Ok(Self {
            dir: dir.to_owned(),
            keep,
            disk,
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Generations on disk with their files, newest first: only files named and headed as this
    /// store writes them (the ones it may number after and prune).
    pub fn generations(&self) -> Result<Vec<(u64, PathBuf)>, StoreError> {
        let mut found = self.named()?;
        found.retain(|(_, path)| has_magic(path));
        Ok(found)
    }

    /// Files named as this store names them, newest first, whatever their content.
    fn named(&self) -> Result<Vec<(u64, PathBuf)>, StoreError> {
        let entries = fs::read_dir(&self.dir).map_err(|source| StoreError::Dir {
            dir: self.dir.clone(),
            source,
        })?;
        let mut found: Vec<(u64, PathBuf)> = entries
            .flatten()
            .filter_map(|e| Some((parse_name(e.file_name().to_str()?)?, e.path())))
            .collect();
        found.sort_by_key(|g| std::cmp::Reverse(g.0));
        Ok(found)
    }

    /// Writes `bytes` as the next generation atomically and prunes old generations; returns the
    /// new file. On any failure the generations already on disk are untouched.
    pub fn write(&self, bytes: &[u8]) -> Result<PathBuf, StoreError> {
        let existing = self.generations()?;
        let mut generation = match existing.first() {
            Some(&(newest, _)) => newest
                .checked_add(1)
                .ok_or(StoreError::GenerationsExhausted(newest))?,
            None => 1,
        };
        // Never rename over a file this store does not count (a generation whose header was
        // damaged, say): the next free number instead.
        while self
            .dir
            .join(format!("{PREFIX}{generation:020}{SUFFIX}"))
            .exists()
        {
            generation = generation
                .checked_add(1)
                .ok_or(StoreError::GenerationsExhausted(generation))?;
        }
        let path = self.dir.join(format!("{PREFIX}{generation:020}{SUFFIX}"));
        let tmp = self.dir.join(format!(".{PREFIX}{generation:020}{SUFFIX}.tmp"));
        let staged = self
            .disk
            .write_file(&tmp, bytes)
            .and_then(|()| self.disk.sync_file(&tmp))
            .and_then(|()| self.disk.rename(&tmp, &path));
        if let Err(source) = staged {
            let _ = self.disk.remove(&tmp);
            return Err(StoreError::Write { path, source });
        }
        // Renamed but perhaps not durable: keep every older generation.
        self.disk
            .sync_dir(&self.dir)
            .map_err(|source| StoreError::Write {
                path: path.clone(),
                source,
            })?;
        let old = existing.iter().filter(|(_, p)| *p != path);
        for (_, old) in old.skip(self.keep.saturating_sub(1)) {
            if let Err(e) = self.disk.remove(old) {
                warn!(file = %old.display(), error = %e, "cannot remove an old checkpoint");
            }
        }
        Ok(path)
    }

    /// Removes every generation (the deliberate reset an operator asks for); returns how many.
    pub fn reset(&self) -> Result<usize, StoreError> {
        let generations = self.generations()?;
        for (_, path) in &generations {
            self.disk.remove(path).map_err(|source| StoreError::Write {
                path: path.clone(),
                source,
            })?;
        }
        self.disk
            .sync_dir(&self.dir)
            .map_err(|source| StoreError::Write {
                path: self.dir.clone(),
                source,
            })?;
        Ok(generations.len())
    }

    /// Restores the newest file named as a generation that decodes, matches `identity` and
    /// `params`, and refits; every file passed over is returned with its reason (for the log).
    pub fn restore(
        &self,
        identity: u64,
        params: &WorldParams,
    ) -> Result<(Option<Restored>, Vec<Rejected>), StoreError> {
        let mut rejected = Vec::new();
        // Every file named as a generation is tried, so that one whose header was damaged is
        // reported (bad magic) rather than passed over in silence.
        for (generation, path) in self.named()? {
            let loaded = fs::read(&path)
                .map_err(|e| RestoreError::Unreadable(e.kind()))
                .and_then(|bytes| Ok(decode(&bytes, identity)?))
                .and_then(|mut checkpoint| {
                    checkpoint.drop_invalid_scales();
                    Ok((checkpoint.restore(params)?, checkpoint))
                });
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
        let torn = dir.join(".aggregate-00000000000000000009.ckpt.tmp");
        fs::write(&torn, b"torn").expect("a temp file a crash left");
        let store = Store::open(&dir, 2).expect("reopen");
        let (restored, rejected) = store.restore(id, &params).expect("restore");
        let restored = restored.expect("the previous generation");
        assert_eq!((restored.generation, restored.checkpoint.created_unix_ns), (2, 1));
        assert_eq!(rejected.len(), 1);
        assert_eq!(rejected[0].1, RestoreError::Format(FormatError::Checksum));
        assert!(!torn.exists(), "temp files removed");
        let _ = fs::remove_dir_all(&dir);
    }

    fn encoded(created: u64) -> Vec<u8> {
        let mut c = sample();
        c.created_unix_ns = created;
        encode(&c, identity("m", &WorldParams::default())).expect("encode")
    }

    fn restored_created(store: &Store) -> Option<u64> {
        let params = WorldParams::default();
        let (restored, _) = store.restore(identity("m", &params), &params).expect("restore");
        restored.map(|r| r.checkpoint.created_unix_ns)
    }

    #[test]
    fn a_stray_file_named_like_the_last_generation_is_never_counted_or_pruned() {
        let dir = temp_dir("stray");
        let store = Store::open(&dir, 2).expect("open");
        store.write(&encoded(1)).expect("write 1");
        store.write(&encoded(2)).expect("write 2");
        let stray = dir.join(format!("{PREFIX}{}{SUFFIX}", u64::MAX));
        fs::write(&stray, b"not ours").expect("stray file");
        let loose = dir.join("aggregate-7.ckpt");
        fs::write(&loose, encoded(9)).expect("a hand-named file");
        let damaged = dir.join(format!("{PREFIX}{:020}{SUFFIX}", 3));
        fs::write(&damaged, b"a generation whose header was damaged").expect("damaged file");
        for created in 3..6 {
            store
                .write(&encoded(created))
                .expect("write after the stray file");
        }
        assert_eq!(
            fs::read(&damaged).expect("kept"),
            b"a generation whose header was damaged"
        );
        let gens: Vec<u64> = store.generations().expect("list").iter().map(|g| g.0).collect();
        assert_eq!(
            gens,
            vec![6, 5],
            "numbering goes on past the stray and the damaged file"
        );
        assert!(
            stray.exists() && loose.exists(),
            "files it did not write are left alone"
        );
        assert_eq!(restored_created(&store), Some(5));
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_last_generation_number_refuses_to_write_instead_of_wrapping() {
        let dir = temp_dir("last");
        let store = Store::open(&dir, 2).expect("open");
        store.write(&encoded(1)).expect("write 1");
        let last = dir.join(format!("{PREFIX}{}{SUFFIX}", u64::MAX));
        fs::write(&last, encoded(2)).expect("a checkpoint at the last number");
        let err = store.write(&encoded(3)).expect_err("no number after u64::MAX");
        assert!(matches!(err, StoreError::GenerationsExhausted(u64::MAX)), "{err}");
        let gens: Vec<u64> = store.generations().expect("list").iter().map(|g| g.0).collect();
        assert_eq!(gens, vec![u64::MAX, 1], "nothing deleted");
        assert_eq!(store.reset().expect("reset"), 2);
        store
            .write(&encoded(4))
            .expect("numbering starts again after a reset");
        assert_eq!(restored_created(&store), Some(4));
        let _ = fs::remove_dir_all(&dir);
    }

    /// Which file operation fails, and how.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Fault {
        DiskFull,
        ShortWrite,
        FileSync,
        Rename,
        DirSync,
    }

    /// The real file system with one operation failing.
    #[derive(Debug)]
    struct FaultyDisk(Fault);

    impl Disk for FaultyDisk {
        fn write_file(&self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
            match self.0 {
                Fault::DiskFull => Err(std::io::ErrorKind::StorageFull.into()),
                Fault::ShortWrite => {
                    OsDisk.write_file(path, &bytes[..bytes.len() / 2])?;
                    Err(std::io::ErrorKind::WriteZero.into())
                }
                _ => OsDisk.write_file(path, bytes),
            }
        }

        fn sync_file(&self, path: &Path) -> std::io::Result<()> {
            match self.0 {
                Fault::FileSync => Err(std::io::Error::from_raw_os_error(libc::EIO)),
                _ => OsDisk.sync_file(path),
            }
        }

        fn rename(&self, from: &Path, to: &Path) -> std::io::Result<()> {
            match self.0 {
                Fault::Rename => Err(std::io::ErrorKind::PermissionDenied.into()),
                _ => OsDisk.rename(from, to),
            }
        }

        fn sync_dir(&self, dir: &Path) -> std::io::Result<()> {
            match self.0 {
                Fault::DirSync => Err(std::io::Error::from_raw_os_error(libc::EIO)),
                _ => OsDisk.sync_dir(dir),
            }
        }

        fn remove(&self, path: &Path) -> std::io::Result<()> {
            OsDisk.remove(path)
        }
    }

    #[test]
    fn every_failing_file_operation_leaves_the_previous_generations_restorable() {
        for fault in [
            Fault::DiskFull,
            Fault::ShortWrite,
            Fault::FileSync,
            Fault::Rename,
            Fault::DirSync,
        ] {
            let dir = temp_dir(&format!("fault-{fault:?}"));
            let good = Store::open(&dir, 2).expect("open");
            good.write(&encoded(1)).expect("write 1");
            good.write(&encoded(2)).expect("write 2");
            let faulty = Store::open_on(&dir, 2, Arc::new(FaultyDisk(fault))).expect("open");
            let err = faulty.write(&encoded(3)).expect_err("the fault surfaces");
            assert!(matches!(err, StoreError::Write { .. }), "{fault:?}: {err}");
            let gens: Vec<u64> = good.generations().expect("list").iter().map(|g| g.0).collect();
            let expected = if fault == Fault::DirSync {
                vec![3, 2, 1]
            } else {
                vec![2, 1]
            };
            assert_eq!(gens, expected, "{fault:?}: nothing pruned");
            let leftovers = fs::read_dir(&dir)
                .expect("list")
                .flatten()
                .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
                .count();
            assert_eq!(leftovers, 0, "{fault:?}: no temp file left");
            let newest = if fault == Fault::DirSync { 3 } else { 2 };
            assert_eq!(restored_created(&good), Some(newest), "{fault:?}");
            good.write(&encoded(4)).expect("a healthy disk writes again");
            assert_eq!(restored_created(&good), Some(4), "{fault:?}");
            let _ = fs::remove_dir_all(&dir);
        }
    }

    #[test]
    fn an_unwritable_directory_is_an_error_not_a_panic() {
        let file = temp_dir("not-a-dir");
        fs::write(&file, b"x").expect("file");
        assert!(matches!(Store::open(&file, 2), Err(StoreError::Dir { .. })));
        let _ = fs::remove_file(&file);
    }
}
