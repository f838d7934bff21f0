//! Batch writes that never leave a torn file: every target checked first,
//! every temporary file written and synced to disk before the first rename
//! (one sync of each file system they lie on, not one per file: a big
//! world's output is thousands of files), modes and owners kept, symbolic
//! links written through, folders synced after.

use super::folder_of;
use super::replaceable::plan_target;
use super::temporaries::{remove_stale_temporaries, temporary_folder, temporary_path};
use crate::error::{Error, Result};
use rayon::prelude::*;
use std::collections::HashMap;
use std::fs::{self, File, Metadata};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// Replaces `path` atomically (see [`write_files`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_files(&[(path, bytes)])
}

/// [`write_atomic`] of what `fill` writes as it goes, so a large output
/// (a report) is never held whole in memory: the same checks, a temporary
/// beside the target renamed over it only once `fill` succeeded.
pub fn write_atomic_streamed(
    path: &Path,
    fill: &mut dyn FnMut(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let planned = plan_batch(&[(path, &[])])?;
    let folders = prepare_folders(&planned, &[])?;
    let temp = temporary_path(&planned[0].real);
    let written = write_temporary_with(&temp, planned[0].existing.as_ref(), fill);
    if let Err(err) = written.and_then(|()| sync_temporaries(&[&temp])) {
        let _ = fs::remove_file(&temp);
        return Err(err);
    }
    rename_over_targets(&planned, &[temp])?;
    sync_folders(&folders);
    Ok(())
}

/// Writes a tree of files (paths relative to `dir`, `/`-separated) with
/// [`write_files`].
pub fn write_tree(dir: &Path, files: &[(String, Vec<u8>)]) -> Result<()> {
    let paths: Vec<PathBuf> = files.iter().map(|(r, _)| dir.join(r)).collect();
    let batch: Vec<(&Path, &[u8])> = paths
        .iter()
        .zip(files)
        .map(|(p, (_, b))| (p.as_path(), b.as_slice()))
        .collect();
    write_files(&batch)
}

/// One file of a batch, after the checks.
struct Planned<'a> {
    /// The file itself: a symbolic link's target, resolved.
    real: PathBuf,
    folder: PathBuf,
    /// The file it replaces, whose mode and owner the new file keeps.
    existing: Option<Metadata>,
    bytes: &'a [u8],
}

/// Writes one temporary file: a new file (never through an existing link),
/// the mode and owner of the file it replaces (synced later, with the
/// rest of its batch: [`sync_temporaries`]).
fn write_temporary(temp: &Path, bytes: &[u8], existing: Option<&Metadata>) -> Result<()> {
    write_temporary_with(temp, existing, &mut |out| out.write_all(bytes))
}

/// [`write_temporary`] of what `fill` writes, buffered.
fn write_temporary_with(
    temp: &Path,
    existing: Option<&Metadata>,
    fill: &mut dyn FnMut(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let _ = fs::remove_file(temp);
    let file = fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(temp)
        .map_err(|e| Error::io(temp, "create", e))?;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
    fill(&mut out).map_err(|e| Error::io(temp, "write", e))?;
    let file = out
        .into_inner()
        .map_err(|e| Error::io(temp, "write", e.into_error()))?;
    if let Some(meta) = existing {
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            // Keeping another user's ownership needs privileges: kept where
            // possible, else the file belongs to this user.
            let _ = std::os::unix::fs::fchown(&file, Some(meta.uid()), Some(meta.gid()));
        }
        file.set_permissions(meta.permissions())
            .map_err(|e| Error::io(temp, "set the mode of", e))?;
    }
    Ok(())
}

/// The bytes of every temporary file of `temps` on disk before any is
/// renamed: on Linux one `syncfs` of each file system they lie on (a
/// sync per file costs a big world's output seconds), falling back to
/// the files' own syncs where a file system refuses it; elsewhere each
/// file synced.
fn sync_temporaries(temps: &[&Path]) -> Result<()> {
    let of_each: Vec<PathBuf> = temps.iter().map(|t| folder_of(t)).collect();
    let mut synced_devices = Vec::new();
    for folder in distinct(of_each.iter().map(PathBuf::as_path).collect()) {
        match sync_file_system(folder, &mut synced_devices) {
            Ok(true) => {}
            Ok(false) => sync_each(
                temps
                    .iter()
                    .zip(&of_each)
                    .filter(|(_, of)| of.as_path() == folder)
                    .map(|(temp, _)| temp),
            )?,
            Err(err) => return Err(Error::io(folder, "sync the file system of", err)),
        }
    }
    Ok(())
}

/// Syncs the file system `folder` lies on, once per device in `synced`;
/// `false` when it cannot be synced whole (not Linux, or refused).
#[cfg(target_os = "linux")]
fn sync_file_system(folder: &Path, synced: &mut Vec<u64>) -> std::io::Result<bool> {
    use std::os::unix::fs::MetadataExt;
    use std::os::unix::io::AsRawFd;
    let handle = File::open(folder)?;
    let device = handle.metadata()?.dev();
    if synced.contains(&device) {
        return Ok(true);
    }
    // SAFETY: `handle` is an open descriptor for the whole call.
    let done = unsafe { libc::syncfs(handle.as_raw_fd()) } == 0;
    if done {
        synced.push(device);
    }
    Ok(done)
}

#[cfg(not(target_os = "linux"))]
fn sync_file_system(_folder: &Path, _synced: &mut Vec<u64>) -> std::io::Result<bool> {
    Ok(false)
}

/// Each of `temps` synced on its own.
fn sync_each<'a>(temps: impl Iterator<Item = &'a &'a Path>) -> Result<()> {
    for temp in temps {
        fs::OpenOptions::new()
            .write(true)
            .open(temp)
            .and_then(|file| file.sync_all())
            .map_err(|e| Error::io(temp, "sync", e))?;
    }
    Ok(())
}

/// Replaces every file of a batch so that a crash or kill never leaves a
/// torn file:
/// 1. every target is checked first (a regular file or new, writable, not
///    read-only; symbolic links resolved to their target); any refusal
///    fails the batch with every refused file named and nothing written;
/// 2. stale temporary files of earlier runs are removed from the folders
///    (see `temporaries`);
/// 3. each file's bytes go to a temporary file beside its target, keeping
///    the target's mode (and owner where possible), and all are synced to
///    disk ([`sync_temporaries`]); a failure removes them all, so nothing
///    was replaced;
/// 4. only then are they renamed over their targets, one by one;
/// 5. the folders are synced so the renames last.
///
/// A kill during 3 leaves temporary files only (removed by the next run);
/// a kill during 4 leaves some targets replaced, each whole, and the rest
/// as they were: running again completes the batch.
pub fn write_files(files: &[(&Path, &[u8])]) -> Result<()> {
    write_files_beside(files, &[], &mut || {})
}

/// [`write_files`], also removing stale temporary files beside `unchanged`
/// (the other targets of the same output, whose bytes stay as they are: a
/// re-run that completes a killed bake may change no file at all, and must
/// still remove what the killed run left), and calling `written` as each
/// file's temporary is written, so a caller can show its progress while
/// this module keeps the file system to itself.
pub fn write_files_beside(
    files: &[(&Path, &[u8])],
    unchanged: &[&Path],
    written: &mut dyn FnMut(),
) -> Result<()> {
    let planned = plan_batch(files)?;
    let folders = prepare_folders(&planned, unchanged)?;
    let temporaries = write_temporaries(&planned, written)?;
    let temps: Vec<&Path> = temporaries.iter().map(PathBuf::as_path).collect();
    if let Err(err) = sync_temporaries(&temps) {
        for temp in &temporaries {
            let _ = fs::remove_file(temp);
        }
        return Err(err);
    }
    rename_over_targets(&planned, &temporaries)?;
    sync_folders(&folders);
    Ok(())
}

/// A file's new bytes waiting beside it in a temporary file ([`stage`]),
/// synced and renamed over it by [`commit_staged`]; dropped without
/// that, the temporary is removed. A large batch is staged file by file
/// as its bytes are made, so it is never held whole in memory, and still
/// replaces nothing until every file is staged.
#[derive(Debug)]
pub struct Staged {
    /// As the caller named it (for messages).
    target: PathBuf,
    /// The file itself: a symbolic link's target, resolved.
    real: PathBuf,
    folder: PathBuf,
    temp: PathBuf,
    /// Renamed over its target, or removed: nothing left to clean.
    done: AtomicBool,
}

impl Staged {
    /// Removes its temporary file now (a batch that failed).
    pub fn discard(&self) {
        if !self.done.swap(true, Ordering::Relaxed) {
            let _ = fs::remove_file(&self.temp);
        }
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        self.discard();
    }
}

/// What [`stage`] made of a target.
#[derive(Debug)]
pub enum Staging {
    Staged(Staged),
    /// The target may not be replaced (not regular, read-only, not
    /// writable): why. Nothing was written.
    Refused(String),
}

/// Checks `target` as a batch's first step does and writes `bytes` to a
/// temporary file beside it (creating its folder), keeping the mode and
/// owner of the file it will replace.
pub fn stage(target: &Path, bytes: &[u8]) -> Result<Staging> {
    let (real, existing) = match plan_target(target) {
        Ok(planned) => planned,
        Err(why) => return Ok(Staging::Refused(why)),
    };
    let folder = folder_of(&real);
    fs::create_dir_all(&folder).map_err(|e| Error::io(&folder, "create folder", e))?;
    let temp = temporary_path(&real);
    if let Err(err) = write_temporary(&temp, bytes, existing.as_ref()) {
        let _ = fs::remove_file(&temp);
        return Err(err);
    }
    Ok(Staging::Staged(Staged {
        target: target.to_path_buf(),
        real,
        folder,
        temp,
        done: AtomicBool::new(false),
    }))
}

/// The rest of [`write_files`] for files already staged: every target
/// checked again (it may have changed since it was staged) and two that
/// are one file refused, with every staged file discarded and nothing
/// replaced; stale temporaries swept beside them and beside `unchanged`;
/// the temporaries synced to disk (a failure discards them all); each
/// renamed over its target in order (`renamed` called after each); the
/// folders synced.
pub fn commit_staged(
    staged: &[&Staged],
    unchanged: &[&Path],
    renamed: &mut dyn FnMut(),
) -> Result<()> {
    let mut claims = Claims::default();
    let mut refused = Vec::new();
    for file in staged {
        let why = plan_target(&file.target)
            .err()
            .or_else(|| claims.refuse_second(&file.real, &file.target));
        refused.extend(why.map(|why| (file.target.clone(), why)));
    }
    if !refused.is_empty() {
        staged.iter().for_each(|file| file.discard());
        return Err(Error::Refused { files: refused });
    }
    let folders = distinct(staged.iter().map(|f| f.folder.as_path()).collect());
    sweep_beside(&folders, unchanged);
    let temps: Vec<&Path> = staged.iter().map(|f| f.temp.as_path()).collect();
    if let Err(err) = sync_temporaries(&temps) {
        staged.iter().for_each(|file| file.discard());
        return Err(err);
    }
    let pairs: Vec<(&Path, &Path)> = staged
        .iter()
        .map(|f| (f.temp.as_path(), f.real.as_path()))
        .collect();
    let outcome = rename_each(&pairs, renamed);
    let renamed_count = outcome
        .as_ref()
        .err()
        .map_or(staged.len(), |(index, _)| *index);
    for (index, file) in staged.iter().enumerate() {
        match index < renamed_count {
            true => file.done.store(true, Ordering::Relaxed),
            false => file.discard(),
        }
    }
    outcome.map_err(|(_, err)| err)?;
    sync_folders(&folders);
    Ok(())
}

/// Step 1: every target checked, and two targets that are one file (links
/// to it) refused, before anything is written.
fn plan_batch<'a>(files: &[(&Path, &'a [u8])]) -> Result<Vec<Planned<'a>>> {
    let mut planned: Vec<Planned> = Vec::with_capacity(files.len());
    let mut refused = Vec::new();
    let mut claims = Claims::default();
    for &(target, bytes) in files {
        match plan_target(target) {
            Ok((real, existing)) => {
                if let Some(why) = claims.refuse_second(&real, target) {
                    refused.push((target.to_path_buf(), why));
                    continue;
                }
                planned.push(Planned {
                    folder: folder_of(&real),
                    real,
                    existing,
                    bytes,
                });
            }
            Err(why) => refused.push((target.to_path_buf(), why)),
        }
    }
    if refused.is_empty() {
        Ok(planned)
    } else {
        Err(Error::Refused { files: refused })
    }
}

/// Step 2: the folders the batch writes in, created, and those and the
/// folders of `unchanged` targets swept of stale temporary files; returns
/// the folders written in, sorted.
fn prepare_folders<'a>(planned: &'a [Planned], unchanged: &[&Path]) -> Result<Vec<&'a Path>> {
    let folders = distinct(planned.iter().map(|p| p.folder.as_path()).collect());
    for folder in &folders {
        fs::create_dir_all(folder).map_err(|e| Error::io(*folder, "create folder", e))?;
    }
    sweep_beside(&folders, unchanged);
    Ok(folders)
}

/// Removes stale temporary files from `folders` and the folders of the
/// `unchanged` targets.
fn sweep_beside(folders: &[&Path], unchanged: &[&Path]) {
    // A large world's chunks share few folders: each is swept once.
    let owned: Vec<PathBuf> = unchanged.par_iter().map(|t| temporary_folder(t)).collect();
    let mut swept: Vec<&Path> = owned.iter().map(PathBuf::as_path).collect();
    swept.extend(folders);
    for folder in distinct(swept) {
        remove_stale_temporaries(folder);
    }
}

/// Step 3: every temporary file written, in batch order; on a failure
/// every one written so far is removed, so nothing was replaced.
fn write_temporaries(planned: &[Planned], written: &mut dyn FnMut()) -> Result<Vec<PathBuf>> {
    let mut temporaries: Vec<PathBuf> = Vec::with_capacity(planned.len());
    for file in planned {
        let temp = temporary_path(&file.real);
        let outcome = write_temporary(&temp, file.bytes, file.existing.as_ref());
        temporaries.push(temp);
        if let Err(err) = outcome {
            for temp in &temporaries {
                let _ = fs::remove_file(temp);
            }
            return Err(err);
        }
        written();
    }
    Ok(temporaries)
}

/// Step 4: each temporary file renamed over its target; a failure removes
/// the temporary files not yet renamed and says whether any target was
/// replaced.
fn rename_over_targets(planned: &[Planned], temporaries: &[PathBuf]) -> Result<()> {
    let pairs: Vec<(&Path, &Path)> = temporaries
        .iter()
        .zip(planned)
        .map(|(temp, file)| (temp.as_path(), file.real.as_path()))
        .collect();
    rename_each(&pairs, &mut || {}).map_err(|(index, err)| {
        for temp in &temporaries[index..] {
            let _ = fs::remove_file(temp);
        }
        err
    })
}

/// Renames each `(temporary, target)` in order, calling `renamed` after
/// each; on a failure, how many were renamed and the error, which says
/// whether any target was replaced (the caller removes the temporaries
/// left).
fn rename_each(
    pairs: &[(&Path, &Path)],
    renamed: &mut dyn FnMut(),
) -> std::result::Result<(), (usize, Error)> {
    for (index, &(temp, real)) in pairs.iter().enumerate() {
        if let Err(e) = fs::rename(temp, real) {
            let action = if index == 0 {
                "replace (nothing was replaced)"
            } else {
                "replace (files before it were replaced; run again to complete)"
            };
            return Err((index, Error::io(real, action, e)));
        }
        renamed();
    }
    Ok(())
}

/// The targets of one batch by the file each resolves to: two that are
/// one file (links to it) may not both replace it.
#[derive(Default)]
struct Claims(HashMap<PathBuf, PathBuf>);

impl Claims {
    /// Claims `real` for `target`; why `target` is refused when another
    /// target claimed it first.
    fn refuse_second(&mut self, real: &Path, target: &Path) -> Option<String> {
        match self.0.get(real) {
            Some(first) => Some(format!(
                "is the same file as {}: two outputs would replace it",
                first.display()
            )),
            None => {
                self.0.insert(real.to_path_buf(), target.to_path_buf());
                None
            }
        }
    }
}

/// `folders` without repeats, sorted by their bytes (a path comparison by
/// components costs seconds on a large world's chunks).
fn distinct(mut folders: Vec<&Path>) -> Vec<&Path> {
    folders.sort_unstable_by(|a, b| a.as_os_str().cmp(b.as_os_str()));
    folders.dedup_by(|a, b| a.as_os_str() == b.as_os_str());
    folders
}

/// Step 5: makes the renames durable. Not every file system can sync a
/// folder; the files themselves are complete either way.
fn sync_folders(folders: &[&Path]) {
    #[cfg(unix)]
    for folder in folders {
        if let Ok(handle) = File::open(folder) {
            let _ = handle.sync_all();
        }
    }
    #[cfg(not(unix))]
    let _ = folders;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::names;
    use crate::files::temporaries::temporary_path;

    fn staged(target: &Path, bytes: &[u8]) -> Staged {
        match stage(target, bytes).unwrap() {
            Staging::Staged(staged) => staged,
            Staging::Refused(why) => panic!("{} refused: {why}", target.display()),
        }
    }

    #[test]
    fn temporaries_in_several_folders_are_synced_and_a_missing_folder_named() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        std::fs::create_dir_all(&a).unwrap();
        std::fs::create_dir_all(&b).unwrap();
        let temps = [a.join(".x.tmp"), a.join(".y.tmp"), b.join(".z.tmp")];
        for temp in &temps {
            write_temporary(temp, b"bytes", None).unwrap();
        }
        let paths: Vec<&Path> = temps.iter().map(PathBuf::as_path).collect();
        sync_temporaries(&paths).unwrap();
        // A temporary named without a folder lies in the current one
        // (whose file system Linux syncs whole).
        if cfg!(target_os = "linux") {
            sync_temporaries(&[Path::new(".not-written.tmp")]).unwrap();
        }
        let gone = dir.path().join("gone").join(".w.tmp");
        let err = sync_temporaries(&[&gone]).unwrap_err().to_string();
        assert!(err.contains("gone"), "{err}");
    }

    fn make_read_only(path: &Path) {
        let mut permissions = std::fs::metadata(path).unwrap().permissions();
        permissions.set_readonly(true);
        std::fs::set_permissions(path, permissions).unwrap();
    }

    /// Staged files replace nothing until committed; committed, every
    /// target holds its new bytes and no temporary is left; dropped
    /// uncommitted, their temporaries go and the targets stay.
    #[test]
    fn staged_files_replace_their_targets_only_when_committed() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.chunk"), dir.path().join("sub/b.chunk"));
        write_atomic(&a, b"old").unwrap();
        let (one, two) = (staged(&a, b"new a"), staged(&b, b"new b"));
        assert_eq!(fs::read(&a).unwrap(), b"old");
        assert!(!b.exists());
        assert_eq!(names(dir.path()).len(), 3, "a, its temporary, sub");
        drop((one, two));
        assert_eq!(names(dir.path()), ["a.chunk", "sub"]);
        assert!(names(&dir.path().join("sub")).is_empty());
        let (one, two) = (staged(&a, b"new a"), staged(&b, b"new b"));
        let mut renamed = 0;
        commit_staged(&[&one, &two], &[], &mut || renamed += 1).unwrap();
        drop((one, two));
        assert_eq!(renamed, 2);
        assert_eq!(fs::read(&a).unwrap(), b"new a");
        assert_eq!(fs::read(&b).unwrap(), b"new b");
        assert_eq!(names(dir.path()), ["a.chunk", "sub"]);
        assert_eq!(names(&dir.path().join("sub")), ["b.chunk"]);
    }

    /// A target read-only when staged is refused with nothing written; one
    /// made read-only after it was staged fails the commit, every staged
    /// file discarded and nothing replaced.
    #[test]
    fn a_target_refused_before_or_after_staging_replaces_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.chunk"), dir.path().join("b.chunk"));
        for path in [&a, &b] {
            write_atomic(path, b"old").unwrap();
        }
        make_read_only(&b);
        match stage(&b, b"new").unwrap() {
            Staging::Refused(why) => assert!(why.contains("read-only"), "{why}"),
            Staging::Staged(_) => panic!("a read-only target was staged"),
        }
        assert_eq!(names(dir.path()), ["a.chunk", "b.chunk"]);
        let mut permissions = fs::metadata(&b).unwrap().permissions();
        #[allow(clippy::permissions_set_readonly_false)]
        permissions.set_readonly(false);
        fs::set_permissions(&b, permissions).unwrap();
        let (one, two) = (staged(&a, b"new"), staged(&b, b"new"));
        make_read_only(&b);
        let message = commit_staged(&[&one, &two], &[], &mut || {})
            .unwrap_err()
            .to_string();
        assert!(message.contains("b.chunk: is read-only"), "{message}");
        assert_eq!(
            names(dir.path()),
            ["a.chunk", "b.chunk"],
            "temporaries gone"
        );
        for path in [&a, &b] {
            assert_eq!(fs::read(path).unwrap(), b"old");
        }
    }

    #[test]
    fn a_read_only_file_fails_the_whole_batch_before_any_write() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b, c) = (
            dir.path().join("a.chunk"),
            dir.path().join("b.chunk"),
            dir.path().join("c.chunk"),
        );
        for path in [&a, &b, &c] {
            write_atomic(path, b"old").unwrap();
        }
        for path in [&b, &c] {
            let mut permissions = std::fs::metadata(path).unwrap().permissions();
            permissions.set_readonly(true);
            std::fs::set_permissions(path, permissions).unwrap();
        }
        let err = write_files(&[(&a, b"new"), (&b, b"new"), (&c, b"new")]).unwrap_err();
        let message = err.to_string();
        assert!(
            message.contains("nothing was written: 2 file(s)")
                && message.contains("b.chunk: is read-only")
                && message.contains("c.chunk: is read-only"),
            "{message}"
        );
        for path in [&a, &b, &c] {
            assert_eq!(std::fs::read(path).unwrap(), b"old");
        }
        assert_eq!(names(dir.path()), ["a.chunk", "b.chunk", "c.chunk"]);
    }

    #[test]
    fn every_temporary_file_is_written_before_the_first_rename() {
        // The second file's temporary file cannot be created (a folder
        // holds its name): the first file must not have been replaced yet.
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.chunk"), dir.path().join("b.chunk"));
        write_atomic(&a, b"old").unwrap();
        std::fs::create_dir(temporary_path(&b)).unwrap();
        assert!(write_files(&[(&a, b"new"), (&b, b"new")]).is_err());
        assert_eq!(std::fs::read(&a).unwrap(), b"old");
        assert!(!temporary_path(&a).exists());
        assert!(!b.exists());
    }

    #[cfg(unix)]
    #[test]
    fn mode_is_kept_and_links_are_written_through() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let elsewhere = tempfile::tempdir().unwrap();
        let real = elsewhere.path().join("real.chunk");
        write_atomic(&real, b"old").unwrap();
        std::fs::set_permissions(&real, std::fs::Permissions::from_mode(0o640)).unwrap();
        let link = dir.path().join("x.chunk");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        write_atomic(&link, b"new").unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&real).unwrap(), b"new");
        assert_eq!(
            std::fs::metadata(&real).unwrap().permissions().mode() & 0o7777,
            0o640
        );
        assert_eq!(names(dir.path()), ["x.chunk"]);
        assert_eq!(names(elsewhere.path()), ["real.chunk"]);
        // Two links to one file in one batch: refused.
        let second = dir.path().join("y.chunk");
        std::os::unix::fs::symlink(&real, &second).unwrap();
        let message = write_files(&[(&link, b"1"), (&second, b"2")])
            .unwrap_err()
            .to_string();
        assert!(message.contains("is the same file as"), "{message}");
        // A dangling link: refused.
        std::fs::remove_file(&real).unwrap();
        let message = write_atomic(&link, b"x").unwrap_err().to_string();
        assert!(
            message.contains("symbolic link that cannot be followed"),
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
