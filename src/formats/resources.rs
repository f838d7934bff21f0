//! Resource lookup over several res paths (like the engine's `paths.xml`,
//! searched in order) and every file-system access of the crate: reads,
//! folder walks and atomic writes.

use crate::error::{Error, Result};
use std::path::{Path, PathBuf};

/// The resource roots, searched in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResPaths {
    pub roots: Vec<PathBuf>,
}

/// A resource name as written in XML, normalised: forward slashes, no
/// leading slash, no surrounding white space.
pub fn normalise(name: &str) -> String {
    name.trim()
        .replace('\\', "/")
        .trim_start_matches('/')
        .to_string()
}

impl ResPaths {
    pub fn new(roots: Vec<PathBuf>) -> Self {
        ResPaths { roots }
    }

    /// The first root holding `name`, as a full path.
    pub fn resolve(&self, name: &str) -> Option<PathBuf> {
        let name = normalise(name);
        if name.is_empty() || name.split('/').any(|part| part == "..") {
            return None;
        }
        self.roots
            .iter()
            .map(|root| root.join(&name))
            .find(|path| path.is_file())
    }

    /// The root a full path lies under, and the path relative to it.
    pub fn relative<'a>(&'a self, path: &'a Path) -> Option<(&'a Path, &'a Path)> {
        self.roots.iter().find_map(|root| {
            path.strip_prefix(root)
                .ok()
                .map(|rel| (root.as_path(), rel))
        })
    }

    /// Reads resource `name`; `referenced_by` is the file that named it, for
    /// the error.
    pub fn read(&self, name: &str, referenced_by: &Path) -> Result<(PathBuf, Vec<u8>)> {
        let path = self.resolve(name).ok_or_else(|| Error::NotFound {
            name: normalise(name),
            referenced_by: referenced_by.to_path_buf(),
            searched: self.roots.clone(),
        })?;
        let bytes = read_file(&path)?;
        Ok((path, bytes))
    }
}

pub fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, "read", e))
}

/// Every file under `dir` (recursively) whose name ends with `suffix`,
/// sorted, so callers see a deterministic order.
pub fn find_files(dir: &Path, suffix: &str) -> Result<Vec<PathBuf>> {
    find_files_in(dir, suffix, true)
}

/// As [`find_files`]; `recursive` false looks in `dir` itself only.
pub fn find_files_in(dir: &Path, suffix: &str, recursive: bool) -> Result<Vec<PathBuf>> {
    let mut found = Vec::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(dir) = pending.pop() {
        let entries = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, "list folder", e))?;
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(&dir, "list folder", e))?;
            let path = entry.path();
            let kind = entry.file_type().map_err(|e| Error::io(&path, "stat", e))?;
            if kind.is_dir() {
                if recursive {
                    pending.push(path);
                }
            } else if path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(suffix))
            {
                found.push(path);
            }
        }
    }
    found.sort();
    Ok(found)
}

/// Replaces `path` atomically: the bytes go to a temporary file in the same
/// folder, which is then renamed over the target, so a crash leaves either
/// the old file or the new one, never half of either.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, "create folder", e))?;
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let temp = dir.join(format!(
        ".{file_name}.shadowcull-{}.tmp",
        std::process::id()
    ));
    let result = std::fs::write(&temp, bytes)
        .map_err(|e| Error::io(&temp, "write", e))
        .and_then(|()| std::fs::rename(&temp, path).map_err(|e| Error::io(path, "replace", e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

/// Writes a tree of files (paths relative to `dir`, `/`-separated), each
/// atomically.
pub fn write_tree(dir: &Path, files: &[(String, Vec<u8>)]) -> Result<()> {
    for (relative, bytes) in files {
        write_atomic(&dir.join(relative), bytes)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn search_order_and_normalisation() {
        let first = tempfile::tempdir().unwrap();
        let second = tempfile::tempdir().unwrap();
        write_atomic(&second.path().join("sets/a.model"), b"2").unwrap();
        write_atomic(&first.path().join("sets/b.model"), b"1").unwrap();
        write_atomic(&second.path().join("sets/b.model"), b"2").unwrap();
        let paths = ResPaths::new(vec![first.path().into(), second.path().into()]);
        assert_eq!(paths.read("sets/b.model", Path::new("x")).unwrap().1, b"1");
        assert_eq!(
            paths.read("\t/sets\\a.model ", Path::new("x")).unwrap().1,
            b"2"
        );
        assert_eq!(paths.resolve("../etc/passwd"), None);
        let err = paths
            .read("sets/none.model", Path::new("c.chunk"))
            .unwrap_err();
        let message = err.to_string();
        assert!(
            message.starts_with("c.chunk:") && message.contains("sets/none.model"),
            "{message}"
        );
    }

    #[test]
    fn atomic_write_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("x.chunk");
        write_atomic(&target, b"one").unwrap();
        write_atomic(&target, b"two").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"two");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }
}
