//! Folder walks: the matching regular files in a deterministic order, and
//! the matching entries that are not regular files, named and never opened.

use super::read::not_regular;
use crate::error::{Error, Result};
use std::fs;
use std::path::{Path, PathBuf};

/// A folder walk: the matching regular files (symbolic links to regular
/// files included), sorted, and the matching entries that are not regular
/// files, each left out with an error saying what it is.
#[derive(Debug, Default)]
pub struct Walk {
    pub files: Vec<PathBuf>,
    pub refused: Vec<(PathBuf, Error)>,
}

/// Every file under `dir` (recursively) whose name ends with `suffix`,
/// sorted, so callers see a deterministic order. Entries that are not
/// regular files are left out (see [`walk`] to hear about them).
pub fn find_files(dir: &Path, suffix: &str) -> Result<Vec<PathBuf>> {
    find_files_in(dir, suffix, true)
}

/// As [`find_files`]; `recursive` false looks in `dir` itself only.
pub fn find_files_in(dir: &Path, suffix: &str, recursive: bool) -> Result<Vec<PathBuf>> {
    Ok(walk(dir, suffix, recursive)?.files)
}

/// The walk behind [`find_files_in`]: no entry is opened; symbolic links
/// to folders are not followed (no loops).
pub fn walk(dir: &Path, suffix: &str, recursive: bool) -> Result<Walk> {
    let mut walk = Walk::default();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(dir) = pending.pop() {
        let entries = fs::read_dir(&dir).map_err(|e| Error::io(&dir, "list folder", e))?;
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(&dir, "list folder", e))?;
            let path = entry.path();
            let kind = entry.file_type().map_err(|e| Error::io(&path, "stat", e))?;
            if kind.is_dir() {
                if recursive {
                    pending.push(path);
                }
                continue;
            }
            let matches = path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(suffix));
            if !matches {
                continue;
            }
            if kind.is_file() {
                walk.files.push(path);
                continue;
            }
            match fs::metadata(&path) {
                Ok(meta) if meta.is_file() => walk.files.push(path),
                Ok(meta) => {
                    let err = not_regular(&path, &meta);
                    walk.refused.push((path, err));
                }
                Err(e) => {
                    let err = Error::io(&path, "follow link", e);
                    walk.refused.push((path, err));
                }
            }
        }
    }
    walk.files.sort();
    walk.refused.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(walk)
}
