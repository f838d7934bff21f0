//! How many bytes a cache folder holds: what its last listing found plus
//! what the bakes since wrote. Listing a world's cache means reading the
//! size and age of tens of thousands of entries, a visible part of a
//! bake after a small edit; with the ledger a bake lists the folder only
//! when the limit may be reached, or when the count is an hour old (bakes
//! that ran at once or were killed may have written entries it misses).
//! The ledger is only a hint: a missing or unreadable one means "list".

use crate::files;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The ledger's file, at the top of the cache folder (entries live in
/// one folder per kind).
pub const FILE_NAME: &str = "size";

/// A count older than this is not trusted: the next eviction lists.
pub const TRUSTED_FOR: Duration = Duration::from_secs(3600);

const HEADER: &str = "shadowcull cache size 1";

/// Bytes the folder's entries hold, as last counted and added to since.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SizeLedger {
    pub bytes: u64,
    /// When the folder was last listed (seconds since the epoch).
    pub listed: u64,
}

impl SizeLedger {
    /// A count just made by listing the folder.
    pub fn listed_now(bytes: u64, now: SystemTime) -> SizeLedger {
        SizeLedger {
            bytes,
            listed: seconds(now),
        }
    }

    /// The ledger of cache folder `dir`, `None` when there is none or it
    /// does not read as one.
    pub fn read(dir: &Path) -> Option<SizeLedger> {
        let bytes = files::read_cache_entry(&path(dir)).ok()??;
        let text = std::str::from_utf8(&bytes).ok()?;
        let mut lines = text.lines();
        if lines.next()? != HEADER {
            return None;
        }
        let mut fields = lines.next()?.split(' ');
        let ledger = SizeLedger {
            bytes: fields.next()?.parse().ok()?,
            listed: fields.next()?.parse().ok()?,
        };
        (fields.next().is_none() && lines.next().is_none()).then_some(ledger)
    }

    /// Writes the ledger whole (another bake reads the old one or this).
    pub fn write(&self, dir: &Path) -> crate::Result<()> {
        let text = format!("{HEADER}\n{} {}\n", self.bytes, self.listed);
        files::write_cache_entry(&path(dir), text.as_bytes())
    }

    /// Removes the ledger of cache folder `dir`, if any.
    pub fn remove(dir: &Path) -> crate::Result<()> {
        files::remove_cache_file(&path(dir))
    }

    /// Whether the count is recent enough at `now` to skip a listing (a
    /// count from the future, another machine's clock, is not).
    pub fn trusted_at(&self, now: SystemTime) -> bool {
        let now = seconds(now);
        self.listed <= now && now - self.listed < TRUSTED_FOR.as_secs()
    }
}

/// Whether `file` of cache folder `dir` is the ledger (not an entry).
pub fn is_ledger(dir: &Path, file: &Path) -> bool {
    file == path(dir)
}

fn path(dir: &Path) -> PathBuf {
    dir.join(FILE_NAME)
}

fn seconds(time: SystemTime) -> u64 {
    time.duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ledger_reads_back_and_anything_else_reads_as_none() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(SizeLedger::read(dir.path()), None, "no ledger yet");
        let now = SystemTime::now();
        let ledger = SizeLedger::listed_now(123_456, now);
        ledger.write(dir.path()).unwrap();
        assert_eq!(SizeLedger::read(dir.path()), Some(ledger));
        for garbage in [
            "",
            "shadowcull cache size 1\n",
            "shadowcull cache size 1\n12 x\n",
            "shadowcull cache size 1\n12 34 56\n",
            "shadowcull cache size 2\n12 34\n",
            "shadowcull cache size 1\n12 34\nmore\n",
        ] {
            std::fs::write(dir.path().join(FILE_NAME), garbage).unwrap();
            assert_eq!(SizeLedger::read(dir.path()), None, "{garbage:?}");
        }
    }

    #[test]
    fn a_count_is_trusted_for_an_hour_and_never_from_the_future() {
        let now = SystemTime::now();
        let ledger = SizeLedger::listed_now(1, now);
        assert!(ledger.trusted_at(now));
        assert!(ledger.trusted_at(now + TRUSTED_FOR - Duration::from_secs(2)));
        assert!(!ledger.trusted_at(now + TRUSTED_FOR));
        assert!(!ledger.trusted_at(now - Duration::from_secs(60)));
    }
}
