//! Files whose content keys a world's record vouches for: after an edit,
//! most of a world's files are as the last bake left them, and a file whose
//! stamp equals the recorded one (by git's rule for racy times) need not be
//! read and hashed again to know its content key. A stamp that differs, or
//! one too close to the record's time, proves nothing: that file is read.

use super::{Key, RACY_NANOSECONDS};
use crate::files::{self, Stamp};
use std::collections::HashMap;
use std::ffi::OsString;
use std::path::Path;

/// Paths with the stamp and content key a record holds for each, and when
/// the record was made.
#[derive(Debug, Clone, Default)]
pub struct KnownFiles {
    files: HashMap<OsString, (Stamp, Key)>,
    recorded_at_ns: u64,
}

impl KnownFiles {
    /// The files of a record made at `recorded_at_ns` (taken before the
    /// first of its stamps).
    pub fn new<'a>(
        files: impl Iterator<Item = (&'a Path, Stamp, Key)>,
        recorded_at_ns: u64,
    ) -> KnownFiles {
        let files = files
            .map(|(path, stamp, key)| (path.as_os_str().to_owned(), (stamp, key)))
            .collect();
        KnownFiles {
            files,
            recorded_at_ns,
        }
    }

    /// `path`'s content key when the record holds it and the file's stamp
    /// now proves it unchanged since; `None` means read it.
    pub fn key_of(&self, path: &Path) -> Option<Key> {
        let (recorded, key) = self.files.get(path.as_os_str())?;
        let stamp = files::stamp(path)?;
        (stamp == *recorded && trusted(&stamp, self.recorded_at_ns)).then_some(*key)
    }
}

/// Whether a stamp equal to the recorded one proves its file or folder
/// unchanged since a record made at `recorded_at_ns`: its times must be
/// older than the record by [`RACY_NANOSECONDS`], since a write within the
/// file system's time resolution could leave the same stamp.
pub fn trusted(stamp: &Stamp, recorded_at_ns: u64) -> bool {
    stamp.latest_ns().saturating_add(RACY_NANOSECONDS) < recorded_at_ns
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stamp_is_trusted_only_when_older_than_the_record_by_the_margin() {
        let stamp = Stamp::from_array([0, 0, 0, 1_000, 5_000]);
        assert!(trusted(&stamp, 5_000 + RACY_NANOSECONDS + 1));
        assert!(!trusted(&stamp, 5_000 + RACY_NANOSECONDS));
        assert!(
            !trusted(&stamp, 1_000 + RACY_NANOSECONDS + 1),
            "status change counts"
        );
    }

    #[test]
    fn a_file_is_known_only_while_its_stamp_is_the_recorded_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.chunk");
        files::write_atomic(&path, b"<root/>").unwrap();
        let stamp = files::stamp(&path).unwrap();
        let key = Key([7; 32]);
        let later = stamp.latest_ns() + RACY_NANOSECONDS + 1;
        let known = KnownFiles::new([(path.as_path(), stamp, key)].into_iter(), later);
        assert_eq!(known.key_of(&path), Some(key));
        // Too close to the record's time: a write could hide behind it.
        let racy = KnownFiles::new([(path.as_path(), stamp, key)].into_iter(), later - 2);
        assert_eq!(racy.key_of(&path), None);
        // Written again (same length): another stamp.
        files::write_atomic(&path, b"<root/>").unwrap();
        assert_eq!(known.key_of(&path), None);
        assert_eq!(known.key_of(&dir.path().join("other.chunk")), None);
    }
}
