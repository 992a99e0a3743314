//! The site map on disk: tiles that left the area around the robot, one file per tile in
//! `<checkpoint dir>/tiles/`, each framed like a checkpoint (magic `RGPTILE\0`, the map's
//! identity, length, bincode, xxh3) and written atomically (temp file, fsync, rename). The
//! aggregate thread writes a tile when it is evicted and reads it back when the robot returns
//! within the radius; the keys on disk are listed once at start and kept in memory (a few bytes
//! per tile, whatever the distance driven).

use super::format::{decode_framed, encode_framed, FormatError};
use crate::map::aggregate::world::{Cell, TilePage};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// First bytes of every tile page.
pub const PAGE_MAGIC: [u8; 8] = *b"RGPTILE\0";
/// Layout version of a tile page; bumped when [`TilePage`] changes (apart from checkpoints',
/// so that a checkpoint change leaves the pages of the site map on disk readable; 4: how the
/// cells were seen). Format-3 pages are read too (`decode_page`).
pub const PAGE_FORMAT_VERSION: u32 = 4;
/// The page layout before the cells' seen-from records.
const PAGE_FORMAT_3: u32 = 3;

/// A format-3 [`TilePage`]: the same without `seen`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TilePageV3 {
    key: (i32, i32),
    cells: Vec<((i32, i32), Cell)>,
    points: Vec<[f64; 3]>,
    noise_var: Vec<f64>,
}

/// Decodes a page of this map, format 4 or 3 (a format-3 page's cells have no seen-from
/// records: they answer as seen squarely from the newest sensor until scans fuse them again).
fn decode_page(bytes: &[u8], identity: u64) -> Result<TilePage, FormatError> {
    match decode_framed(PAGE_MAGIC, PAGE_FORMAT_VERSION, bytes, identity) {
        Err(FormatError::Version {
            found: PAGE_FORMAT_3, ..
        }) => decode_framed::<TilePageV3>(PAGE_MAGIC, PAGE_FORMAT_3, bytes, identity).map(|p| TilePage {
            key: p.key,
            cells: p.cells,
            points: p.points,
            noise_var: p.noise_var,
            seen: Vec::new(),
        }),
        decoded => decoded,
    }
}
const SUFFIX: &str = ".page";

/// A tile page could not be written or read.
#[derive(Debug, Error)]
pub enum PageError {
    /// The directory cannot be created or listed.
    #[error("tile directory {dir}")]
    Dir {
        /// Directory.
        dir: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// Writing, syncing, renaming or reading a file failed.
    #[error("tile page {path}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// The file is damaged or from another map.
    #[error("tile page {path}: {source}")]
    Format {
        /// File.
        path: PathBuf,
        /// Cause.
        source: FormatError,
    },
}

/// The tile pages of one map.
#[derive(Debug)]
pub struct PageStore {
    dir: PathBuf,
    identity: u64,
    keys: BTreeSet<(i32, i32)>,
}

impl PageStore {
    /// Opens (creating) `<dir>/tiles` for the map with `identity` and lists the pages there.
    pub fn open(dir: &Path, identity: u64) -> Result<Self, PageError> {
        let dir = dir.join("tiles");
        let dir_err = |source| PageError::Dir {
            dir: dir.clone(),
            source,
        };
        fs::create_dir_all(&dir).map_err(dir_err)?;
        let mut keys = BTreeSet::new();
        for entry in fs::read_dir(&dir).map_err(dir_err)? {
            let name = entry.map_err(dir_err)?.file_name();
            if let Some(key) = name.to_str().and_then(key_of) {
                keys.insert(key);
            }
        }
        Ok(Self { dir, identity, keys })
    }

    /// Tiles with a page on disk.
    pub fn keys(&self) -> &BTreeSet<(i32, i32)> {
        &self.keys
    }

    /// Writes `page` atomically, replacing an older page of the same tile.
    pub fn write(&mut self, page: &TilePage) -> Result<(), PageError> {
        self.put(page)?;
        self.keys.insert(page.key);
        Ok(())
    }

    /// Replaces the page of a tile already on disk, atomically (several at once: it needs no
    /// exclusive access).
    pub fn rewrite(&self, page: &TilePage) -> Result<(), PageError> {
        self.put(page)
    }

    fn put(&self, page: &TilePage) -> Result<(), PageError> {
        let path = self.path(page.key);
        let tmp = path.with_extension("page.tmp");
        let bytes =
            encode_framed(PAGE_MAGIC, PAGE_FORMAT_VERSION, page, self.identity).map_err(|source| {
                PageError::Format {
                    path: path.clone(),
                    source,
                }
            })?;
        let io = |source| PageError::Io {
            path: path.clone(),
            source,
        };
        let written = File::create(&tmp)
            .and_then(|mut f| f.write_all(&bytes).and_then(|()| f.sync_all()))
            .and_then(|()| fs::rename(&tmp, &path));
        if let Err(e) = written {
            let _ = fs::remove_file(&tmp);
            return Err(io(e));
        }
        Ok(())
    }

    /// Reads the page of tile `key`.
    pub fn read(&self, key: (i32, i32)) -> Result<TilePage, PageError> {
        self.reader().read(key)
    }

    /// A handle that reads this store's pages from another thread (a page is replaced by an
    /// atomic rename, so a reader sees the old page or the new one, never a mix).
    pub fn reader(&self) -> PageReader {
        PageReader {
            dir: self.dir.clone(),
            identity: self.identity,
        }
    }

    /// Removes every page under `dir` (the deliberate reset); returns how many.
    pub fn reset(dir: &Path) -> Result<usize, PageError> {
        let dir = dir.join("tiles");
        let dir_err = |source| PageError::Dir {
            dir: dir.clone(),
            source,
        };
        let entries = match fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
            Err(e) => return Err(dir_err(e)),
        };
        let mut removed = 0;
        for entry in entries {
            let path = entry.map_err(dir_err)?.path();
            if path
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(key_of)
                .is_some()
            {
                fs::remove_file(&path).map_err(|source| PageError::Io { path, source })?;
                removed += 1;
            }
        }
        Ok(removed)
    }

    fn path(&self, key: (i32, i32)) -> PathBuf {
        path_in(&self.dir, key)
    }
}

/// Reads the pages of one map; the fleet publisher's way to a departed tile's cells.
#[derive(Debug, Clone)]
pub struct PageReader {
    dir: PathBuf,
    identity: u64,
}

impl PageReader {
    /// Reads the page of tile `key`.
    pub fn read(&self, key: (i32, i32)) -> Result<TilePage, PageError> {
        let path = path_in(&self.dir, key);
        let bytes = fs::read(&path).map_err(|source| PageError::Io {
            path: path.clone(),
            source,
        })?;
        decode_page(&bytes, self.identity).map_err(|source| PageError::Format { path, source })
    }
}

/// The file of tile `(i, j)`'s page in the tiles directory `dir`.
fn path_in(dir: &Path, (i, j): (i32, i32)) -> PathBuf {
    dir.join(format!("tile_{i}_{j}{SUFFIX}"))
}

/// The tile key a page's file name carries (`tile_<i>_<j>.page`).
fn key_of(name: &str) -> Option<(i32, i32)> {
    let (i, j) = name
        .strip_prefix("tile_")?
        .strip_suffix(SUFFIX)?
        .split_once('_')?;
    Some((i.parse().ok()?, j.parse().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::aggregate::world::Cell;

    fn page(key: (i32, i32)) -> TilePage {
        TilePage {
            key,
            cells: vec![(
                (key.0 * 10, key.1 * 10),
                Cell {
                    z: 0.5,
                    var: 1e-4,
                    scans: 3,
                },
            )],
            points: vec![[1.0, 2.0, 0.5]],
            noise_var: vec![1e-4],
            seen: vec![((key.0 * 10, key.1 * 10), [4.5, 0.75])],
        }
    }

    #[test]
    fn a_format_3_page_is_read_without_seen_from_records() {
        let dir = std::env::temp_dir().join(format!("rangegp-pages3-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let store = PageStore::open(&dir, 7).expect("open");
        let new = page((2, -1));
        let old = TilePageV3 {
            key: new.key,
            cells: new.cells.clone(),
            points: new.points.clone(),
            noise_var: new.noise_var.clone(),
        };
        let bytes = encode_framed(PAGE_MAGIC, PAGE_FORMAT_3, &old, 7).expect("encode");
        fs::write(store.path(new.key), bytes).expect("write");
        let read = store.read(new.key).expect("a format-3 page decodes");
        assert_eq!(
            read,
            TilePage {
                seen: Vec::new(),
                ..new
            }
        );
        let other = encode_framed(PAGE_MAGIC, 2, &old, 7).expect("encode");
        fs::write(store.path((2, -1)), other).expect("write");
        assert!(matches!(
            store.read((2, -1)),
            Err(PageError::Format {
                source: FormatError::Version { found: 2, .. },
                ..
            })
        ));
        fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn pages_round_trip_are_listed_at_open_and_refuse_other_maps() {
        let dir = std::env::temp_dir().join(format!("rangegp-pages-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let mut store = PageStore::open(&dir, 7).expect("open");
        for key in [(-3, 4), (5, -6)] {
            store.write(&page(key)).expect("write");
        }
        store.write(&page((-3, 4))).expect("rewrite");
        assert_eq!(store.read((-3, 4)).expect("read"), page((-3, 4)));
        let again = PageStore::open(&dir, 7).expect("reopen");
        assert_eq!(
            again.keys().iter().copied().collect::<Vec<_>>(),
            [(-3, 4), (5, -6)]
        );
        let foreign = PageStore::open(&dir, 8).expect("open");
        assert!(matches!(
            foreign.read((5, -6)),
            Err(PageError::Format {
                source: FormatError::Foreign { .. },
                ..
            })
        ));
        fs::write(dir.join("tiles/tile_5_-6.page"), b"torn").expect("damage");
        assert!(matches!(again.read((5, -6)), Err(PageError::Format { .. })));
        assert_eq!(PageStore::reset(&dir).expect("reset"), 2);
        assert!(PageStore::open(&dir, 7).expect("open").keys().is_empty());
        fs::remove_dir_all(&dir).ok();
    }
}
