//! The bake cache's folder on disk: entries read whole (capped), written
//! atomically (a uniquely named temporary renamed over the entry, so a
//! reader sees the old entry, the new one or none, never a torn one, and
//! two bakes writing the same entry cannot corrupt it), listed with their
//! size and age for eviction, and removed. What an entry holds and how it
//! is checked is `cache`'s business.

use crate::error::{Error, Result};
use rayon::prelude::*;
use std::fs;
use std::io::{ErrorKind, Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::SystemTime;

/// The largest entry read; a larger file is not an entry this tool wrote.
pub const CACHE_ENTRY_CAP: u64 = 1 << 30;

/// Suffix of an entry being written.
const TEMPORARY_SUFFIX: &str = ".tmp";

/// One file of the cache folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CacheFile {
    pub path: PathBuf,
    pub bytes: u64,
    /// Last written or used.
    pub modified: SystemTime,
    /// A temporary a writer left behind (killed while writing).
    pub temporary: bool,
}

/// The bytes of entry `path`, or `None` when there is none (or it vanished:
/// another bake evicted it). Only regular files are read, up to
/// [`CACHE_ENTRY_CAP`].
pub fn read_cache_entry(path: &Path) -> Result<Option<Vec<u8>>> {
    let file = match fs::File::open(path) {
        Ok(file) => file,
        Err(err) if err.kind() == ErrorKind::NotFound => return Ok(None),
        Err(err) => return Err(Error::io(path, "read the cache entry", err)),
    };
    let meta = file
        .metadata()
        .map_err(|e| Error::io(path, "read the cache entry", e))?;
    if !meta.is_file() {
        return Err(Error::invalid(path, "not a regular file"));
    }
    let mut bytes = Vec::with_capacity(meta.len().min(CACHE_ENTRY_CAP) as usize);
    file.take(CACHE_ENTRY_CAP + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, "read the cache entry", e))?;
    Ok(Some(bytes))
}

/// Writes entry `path` atomically: a temporary unique to this process and
/// write, then a rename over the entry. Folders are made as needed.
pub fn write_cache_entry(path: &Path, bytes: &[u8]) -> Result<()> {
    static WRITES: AtomicU64 = AtomicU64::new(0);
    let dir = super::folder_of(path);
    fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, "create the cache folder", e))?;
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let temp = dir.join(format!(
        ".{name}.{}-{}{TEMPORARY_SUFFIX}",
        std::process::id(),
        WRITES.fetch_add(1, Ordering::Relaxed)
    ));
    let written = fs::File::create(&temp).and_then(|mut file| file.write_all(bytes));
    if let Err(err) = written {
        let _ = fs::remove_file(&temp);
        return Err(Error::io(&temp, "write the cache entry", err));
    }
    fs::rename(&temp, path).map_err(|err| {
        let _ = fs::remove_file(&temp);
        Error::io(path, "write the cache entry", err)
    })
}

/// Whether entry `path` exists (a regular file; not read).
pub fn cache_entry_exists(path: &Path) -> bool {
    fs::symlink_metadata(path).is_ok_and(|m| m.is_file())
}

/// Marks entry `path` as used now (eviction removes the least recently
/// used first). A vanished entry is not an error.
pub fn touch_cache_entry(path: &Path) {
    if let Ok(file) = fs::File::options().append(true).open(path) {
        let _ = file.set_modified(SystemTime::now());
    }
}

/// Removes one file of the cache; one already gone is not an error.
pub fn remove_cache_file(path: &Path) -> Result<()> {
    match fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(err) if err.kind() == ErrorKind::NotFound => Ok(()),
        Err(err) => Err(Error::io(path, "remove the cache entry", err)),
    }
}

/// Every file under the cache folder `dir` (none when it does not exist),
/// sorted by path. Links and other special files are not followed.
pub fn list_cache_files(dir: &Path) -> Result<Vec<CacheFile>> {
    // Folder by folder in parallel, each entry's metadata read through
    // its folder: a large world's cache holds a few hundred thousand.
    let mut files = Vec::new();
    let mut pending = vec![dir.to_path_buf()];
    while !pending.is_empty() {
        let listed: Vec<(Vec<PathBuf>, Vec<CacheFile>)> = pending
            .par_iter()
            .map(|f| list_folder(f))
            .collect::<Result<_>>()?;
        pending = Vec::new();
        for (folders, found) in listed {
            pending.extend(folders);
            files.extend(found);
        }
    }
    files.sort_unstable_by(|a, b| a.path.as_os_str().cmp(b.path.as_os_str()));
    Ok(files)
}

/// The sub-folders and files of one folder of the cache (none if it is
/// gone).
fn list_folder(folder: &Path) -> Result<(Vec<PathBuf>, Vec<CacheFile>)> {
    let (mut folders, mut files) = (Vec::new(), Vec::new());
    let entries = match fs::read_dir(folder) {
        Ok(entries) => entries,
        Err(err) if err.kind() == ErrorKind::NotFound => return Ok((folders, files)),
        Err(err) => return Err(Error::io(folder, "list the cache folder", err)),
    };
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(folder, "list the cache folder", e))?;
        let Ok(meta) = entry.metadata() else {
            continue;
        };
        let path = entry.path();
        if meta.is_dir() {
            folders.push(path);
        } else if meta.is_file() {
            let temporary = path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().ends_with(TEMPORARY_SUFFIX));
            files.push(CacheFile {
                modified: meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
                bytes: meta.len(),
                path,
                temporary,
            });
        }
    }
    Ok((folders, files))
}

/// Removes the empty folders under `dir` (left by eviction or `clear`).
pub fn remove_empty_cache_folders(dir: &Path) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if fs::symlink_metadata(&path).is_ok_and(|m| m.is_dir()) {
            remove_empty_cache_folders(&path);
            let _ = fs::remove_dir(&path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_entry_is_written_whole_listed_touched_and_removed() {
        let dir = tempfile::tempdir().unwrap();
        let entry = dir.path().join("tile/ab/abcdef");
        assert_eq!(read_cache_entry(&entry).unwrap(), None);
        write_cache_entry(&entry, b"first").unwrap();
        write_cache_entry(&entry, b"second").unwrap();
        assert_eq!(read_cache_entry(&entry).unwrap().unwrap(), b"second");
        let listed = list_cache_files(dir.path()).unwrap();
        assert_eq!(listed.len(), 1, "no temporary left: {listed:?}");
        assert_eq!((listed[0].bytes, listed[0].temporary), (6, false));
        touch_cache_entry(&entry);
        remove_cache_file(&entry).unwrap();
        remove_cache_file(&entry).unwrap();
        remove_empty_cache_folders(dir.path());
        assert!(list_cache_files(dir.path()).unwrap().is_empty());
        assert!(fs::read_dir(dir.path()).unwrap().next().is_none());
    }
}
