//! What the file system says of a file or folder without reading it: the
//! stamp a record compares to tell a file unchanged since it was hashed (as
//! git's index does), and the names a folder holds. A stamp alone never
//! proves a file unchanged; its reader applies the rule for racy times.

use crate::error::{Error, Result};
use std::ffi::OsString;
use std::fs;
use std::path::Path;

/// Length, inode and device, and the modification and status-change
/// times (nanoseconds since the epoch) of a file or folder, links
/// followed. Any write changes the status-change time, which no user
/// can set, and a file replaced by a rename has another inode.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Stamp {
    pub len: u64,
    pub inode: u64,
    pub device: u64,
    pub modified_ns: u64,
    pub changed_ns: u64,
}

impl Stamp {
    /// The five numbers, in field order.
    pub fn to_array(self) -> [u64; 5] {
        [
            self.len,
            self.inode,
            self.device,
            self.modified_ns,
            self.changed_ns,
        ]
    }

    pub fn from_array([len, inode, device, modified_ns, changed_ns]: [u64; 5]) -> Stamp {
        Stamp {
            len,
            inode,
            device,
            modified_ns,
            changed_ns,
        }
    }

    /// The later of the two times: what a record compares with its own
    /// time to tell whether a change could hide behind the same stamp.
    pub fn latest_ns(&self) -> u64 {
        self.modified_ns.max(self.changed_ns)
    }
}

/// `path`'s stamp, or `None` when it does not exist or cannot be read
/// (and on systems without inodes: there a record is never trusted).
pub fn stamp(path: &Path) -> Option<Stamp> {
    let meta = fs::metadata(path).ok()?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let ns = |s: i64, n: i64| {
            (s as u64)
                .wrapping_mul(1_000_000_000)
                .wrapping_add(n as u64)
        };
        Some(Stamp {
            len: meta.len(),
            inode: meta.ino(),
            device: meta.dev(),
            modified_ns: ns(meta.mtime(), meta.mtime_nsec()),
            changed_ns: ns(meta.ctime(), meta.ctime_nsec()),
        })
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        None
    }
}

/// The names `dir` holds, sorted (what a lookup through it can find).
pub fn folder_names(dir: &Path) -> Result<Vec<OsString>> {
    let mut names = Vec::new();
    for entry in fs::read_dir(dir).map_err(|e| Error::io(dir, "list folder", e))? {
        names.push(
            entry
                .map_err(|e| Error::io(dir, "list folder", e))?
                .file_name(),
        );
    }
    names.sort();
    Ok(names)
}

/// Whether `path` exists (links followed), for finding the nearest folder
/// of a path that does.
pub fn exists(path: &Path) -> bool {
    fs::metadata(path).is_ok()
}

/// Whether `path` is a folder (links followed): what tells a folder of
/// chunk files from a report file.
pub fn is_folder(path: &Path) -> bool {
    fs::metadata(path).is_ok_and(|meta| meta.is_dir())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    #[test]
    fn a_stamp_changes_with_a_write_and_a_replacement() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        crate::files::write_atomic(&path, b"one").unwrap();
        let first = stamp(&path).unwrap();
        assert_eq!(first.len, 3);
        assert_eq!(stamp(&path), Some(first), "nothing changed");
        crate::files::write_atomic(&path, b"two").unwrap();
        let second = stamp(&path).unwrap();
        assert_ne!(second, first, "same length, replaced: another inode");
        assert_eq!(Stamp::from_array(second.to_array()), second);
        assert_eq!(stamp(&dir.path().join("missing")), None);
        let names = folder_names(dir.path()).unwrap();
        assert_eq!(names, vec![OsString::from("f")]);
    }
}
