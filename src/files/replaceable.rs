//! Whether a write may replace its target: a regular file or a new one,
//! not read-only, writable by this user, symbolic links resolved. The
//! batch writes make these checks before writing anything, and a bake
//! makes them on its chunks before tracing, to name the locked ones early.

use super::read::kind_of;
use crate::error::{Error, Result};
use std::fs::{self, Metadata};
use std::path::{Path, PathBuf};

#[cfg(unix)]
fn mode_of(meta: &Metadata) -> String {
    use std::os::unix::fs::PermissionsExt;
    format!("mode {:04o}", meta.permissions().mode() & 0o7777)
}

#[cfg(not(unix))]
fn mode_of(_: &Metadata) -> String {
    "read-only attribute".into()
}

/// Where the bytes for `target` go and what they replace, or why `target`
/// must not be replaced.
pub(super) fn plan_target(
    target: &Path,
) -> std::result::Result<(PathBuf, Option<Metadata>), String> {
    let Ok(entry) = fs::symlink_metadata(target) else {
        // A new file (or a parent that is not a folder: reported when the
        // folder is created).
        return Ok((target.to_path_buf(), None));
    };
    let real = if entry.file_type().is_symlink() {
        fs::canonicalize(target).map_err(|e| {
            format!("is a symbolic link that cannot be followed ({e}): fix or remove the link")
        })?
    } else {
        target.to_path_buf()
    };
    let meta = fs::metadata(&real).map_err(|e| format!("cannot be examined: {e}"))?;
    if !meta.is_file() {
        return Err(format!(
            "is {}, not a regular file: only regular files are replaced",
            kind_of(&meta)
        ));
    }
    // A read-only file is locked, as lock-based version control (Perforce)
    // leaves files not checked out. Even root, who could write it, must not.
    if meta.permissions().readonly() {
        return Err(format!(
            "is read-only ({}): locked, e.g. not checked out; make it writable (`p4 edit`, `chmod u+w`) or write elsewhere with --out",
            mode_of(&meta)
        ));
    }
    // Can this user write it (access(W_OK) without libc)? Opening for
    // writing without truncating changes nothing.
    let mut options = fs::OpenOptions::new();
    options.write(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    if let Err(e) = options.open(&real) {
        return Err(format!(
            "cannot be written by this user ({}: {e}); make it writable or write elsewhere with --out",
            mode_of(&meta)
        ));
    }
    Ok((real, Some(meta)))
}

/// The targets that must not be replaced ([`Error::Refused`], every such
/// file named): the checks [`write_files`](super::write_files) makes before it writes, for a
/// caller that wants to know before any work.
pub fn check_replaceable<'a>(targets: impl IntoIterator<Item = &'a Path>) -> Result<()> {
    let refused: Vec<(PathBuf, String)> = targets
        .into_iter()
        .filter_map(|target| {
            plan_target(target)
                .err()
                .map(|why| (target.to_path_buf(), why))
        })
        .collect();
    if refused.is_empty() {
        Ok(())
    } else {
        Err(Error::Refused { files: refused })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_replaceable_names_every_locked_file() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b, new) = (
            dir.path().join("a.chunk"),
            dir.path().join("b.chunk"),
            dir.path().join("new.chunk"),
        );
        for path in [&a, &b] {
            std::fs::write(path, b"old").unwrap();
        }
        check_replaceable([a.as_path(), b.as_path(), new.as_path()]).unwrap();
        let mut permissions = std::fs::metadata(&b).unwrap().permissions();
        permissions.set_readonly(true);
        std::fs::set_permissions(&b, permissions).unwrap();
        let message = check_replaceable([a.as_path(), b.as_path(), new.as_path()])
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("nothing was written: 1 file(s)")
                && message.contains("b.chunk: is read-only"),
            "{message}"
        );
    }
}
