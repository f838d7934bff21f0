//! The temporary files of batch writes (`.NAME.shadowcull-HOST-PID.tmp`,
//! beside their targets) and the sweep that removes those a killed run
//! left: this host's of processes no longer running, other hosts' older
//! than [`STALE_TEMPORARY_AGE`].

use super::folder_of;
use super::process::{host_name, process_alive};
use std::fs;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// How old a temporary file of another host must be before it counts as
/// stale: its process cannot be looked up from here (a live bake on another
/// machine sharing the volume has a process id this machine does not know),
/// and a live bake keeps a temporary file only while it writes its batch,
/// far less than this.
pub const STALE_TEMPORARY_AGE: Duration = Duration::from_secs(3600);

/// `.NAME.shadowcull-HOST-PID.tmp`, beside `real`.
pub(super) fn temporary_path(real: &Path) -> PathBuf {
    let name = real
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    folder_of(real).join(format!(
        ".{name}.shadowcull-{}-{}.tmp",
        host_name(),
        std::process::id()
    ))
}

/// Who wrote a temporary file of [`temporary_path`]'s form.
#[derive(Debug, PartialEq, Eq)]
struct TemporaryOwner<'a> {
    /// `None` in the form without a host (`.NAME.shadowcull-PID.tmp`):
    /// its process may be on any machine, so only its age tells.
    host: Option<&'a str>,
    pid: u32,
}

/// The host and process in a temporary file name, or `None` for any other
/// name.
fn temporary_owner(name: &str) -> Option<TemporaryOwner<'_>> {
    let rest = name.strip_prefix('.')?.strip_suffix(".tmp")?;
    let (_, owner) = rest.rsplit_once(".shadowcull-")?;
    let (host, pid) = match owner.rsplit_once('-') {
        Some((host, pid)) if !host.is_empty() => (Some(host), pid),
        Some(_) => return None,
        None => (None, owner),
    };
    if pid.is_empty() || !pid.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(TemporaryOwner {
        host,
        pid: pid.parse().ok()?,
    })
}

/// Whether a temporary file is left over from a run that will never finish
/// it: this host's, of a process no longer running; or another host's (or
/// of an unknown host) last written [`STALE_TEMPORARY_AGE`] ago or more.
fn is_stale(owner: &TemporaryOwner, modified: SystemTime) -> bool {
    match owner.host {
        Some(host) if host == host_name() => {
            owner.pid != std::process::id() && !process_alive(owner.pid)
        }
        _ => SystemTime::now()
            .duration_since(modified)
            .is_ok_and(|age| age >= STALE_TEMPORARY_AGE),
    }
}

/// Removes the temporary files that earlier runs, killed while writing,
/// left in `dir` (see [`is_stale`]). One that cannot be removed does not
/// stop the write.
pub(super) fn remove_stale_temporaries(dir: &Path) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(owner) = name.to_str().and_then(temporary_owner) else {
            continue;
        };
        let Ok(meta) = entry.metadata() else {
            continue;
        };
        let modified = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
        if !meta.is_dir() && is_stale(&owner, modified) {
            let _ = fs::remove_file(entry.path());
        }
    }
}

/// The folder a write of `target` puts its temporary file in: beside the
/// file a symbolic link leads to, else beside `target`.
pub(super) fn temporary_folder(target: &Path) -> PathBuf {
    let is_link = fs::symlink_metadata(target).is_ok_and(|m| m.file_type().is_symlink());
    match is_link.then(|| fs::canonicalize(target)) {
        Some(Ok(real)) => folder_of(&real),
        _ => folder_of(target),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::{names, write_atomic, write_files_beside};
    use std::fs::File;

    #[test]
    fn temporary_names_give_their_host_and_process() {
        let owner = |host, pid| Some(TemporaryOwner { host, pid });
        assert_eq!(
            temporary_owner(".a.chunk.shadowcull-box-7.example-123.tmp"),
            owner(Some("box-7.example"), 123)
        );
        assert_eq!(
            temporary_owner(".a.shadowcull-x.chunk.shadowcull-h-9.tmp"),
            owner(Some("h"), 9)
        );
        // The form without a host.
        assert_eq!(
            temporary_owner(".a.chunk.shadowcull-123.tmp"),
            owner(None, 123)
        );
        for name in [
            "a.chunk.shadowcull-h-123.tmp",
            ".a.chunk.shadowcull-.tmp",
            ".a.chunk.shadowcull-h-.tmp",
            ".a.chunk.shadowcull--12.tmp",
            ".a.chunk.shadowcull-h-1x.tmp",
        ] {
            assert_eq!(temporary_owner(name), None, "{name}");
        }
        let temp = temporary_path(Path::new("d/x.chunk"));
        let name = temp.file_name().unwrap().to_str().unwrap();
        assert_eq!(
            temporary_owner(name),
            owner(Some(host_name()), std::process::id())
        );
    }

    /// A file in `dir` last written `age` ago.
    fn written_ago(dir: &Path, name: &str, age: Duration) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, b"half").unwrap();
        let file = File::options().write(true).open(&path).unwrap();
        file.set_modified(SystemTime::now() - age).unwrap();
        path
    }

    #[test]
    fn stale_temporary_files_of_dead_runs_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let host = host_name();
        let fresh = Duration::ZERO;
        let old = STALE_TEMPORARY_AGE + Duration::from_secs(60);
        // No process has this id (above Linux's pid_max, 2^22).
        let dead = written_ago(
            dir.path(),
            &format!(".x.chunk.shadowcull-{host}-4194305.tmp"),
            fresh,
        );
        let other = written_ago(dir.path(), ".x.chunk.shadowcull-4194305.keep", old);
        // Another machine's live bake on a shared volume: its process id
        // means nothing here, so only its age tells.
        let elsewhere = written_ago(dir.path(), ".x.chunk.shadowcull-elsewhere-1.tmp", fresh);
        let abandoned = written_ago(dir.path(), ".y.chunk.shadowcull-elsewhere-1.tmp", old);
        let unknown = written_ago(dir.path(), ".y.chunk.shadowcull-1.tmp", old);
        // This host's live process (this test's) keeps its files.
        let live = written_ago(
            dir.path(),
            &format!(".z.chunk.shadowcull-{host}-{}.tmp", std::process::id()),
            old,
        );
        write_atomic(&dir.path().join("x.chunk"), b"new").unwrap();
        for removed in [&dead, &abandoned, &unknown] {
            assert!(!removed.exists(), "{}", removed.display());
        }
        for kept in [&other, &elsewhere, &live] {
            assert!(kept.exists(), "{}", kept.display());
        }
    }

    #[test]
    fn unchanged_targets_have_their_folders_swept_too() {
        let (written, untouched) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let kept = untouched.path().join("k.chunk");
        std::fs::write(&kept, b"same").unwrap();
        let stale = written_ago(
            untouched.path(),
            &format!(".k.chunk.shadowcull-{}-4194305.tmp", host_name()),
            Duration::ZERO,
        );
        write_files_beside(
            &[(&written.path().join("w.chunk"), b"new")],
            &[&kept],
            &mut || {},
        )
        .unwrap();
        assert!(!stale.exists());
        assert_eq!(names(untouched.path()), ["k.chunk"]);
        // Nothing to write at all: still swept.
        let stale = written_ago(
            untouched.path(),
            ".k.chunk.shadowcull-elsewhere-1.tmp",
            STALE_TEMPORARY_AGE,
        );
        write_files_beside(&[], &[&kept], &mut || {}).unwrap();
        assert!(!stale.exists());
    }
}
