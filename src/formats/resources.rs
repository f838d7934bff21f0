//! Resource lookup over several res paths (like the engine's `paths.xml`,
//! searched in order) and every file-system access of the crate: reads
//! (regular files only, each kind of file with a size cap), folder walks,
//! and replacing files (checked first, every temporary file written and
//! synced before the first rename).

use crate::error::{Error, Result};
use std::collections::BTreeMap;
use std::fs::{self, File, Metadata};
use std::io::{Read, Write};
use std::path::{Component, Path, PathBuf};
use std::sync::OnceLock;
use std::time::{Duration, SystemTime};

const MIB: u64 = 1 << 20;
const GIB: u64 = 1 << 30;

/// The most bytes read from one file, by the end of its name: the one place
/// the caps are defined. The engine's XML files (chunks, models, visuals,
/// materials, settings) are kilobytes to a few megabytes; `.primitives` and
/// `.cdata` hold geometry and terrain and can reach hundreds of megabytes.
pub const SIZE_CAPS: &[(&str, u64)] = &[
    (".chunk", 64 * MIB),
    (".model", 64 * MIB),
    (".visual", 64 * MIB),
    (".mfm", 64 * MIB),
    (".settings", 64 * MIB),
    (".primitives", GIB),
    (".cdata", GIB),
    // A distributed bake's partial result: caster bitsets of a huge world.
    (".part", GIB),
];

/// The cap of any other file (the bake settings file, a `--out` target).
pub const DEFAULT_SIZE_CAP: u64 = 64 * MIB;

/// The size cap of `path`, and the kind of file it is the cap of.
pub fn size_cap(path: &Path) -> (u64, String) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    SIZE_CAPS
        .iter()
        .find(|(suffix, _)| name.ends_with(suffix))
        .map(|&(suffix, cap)| (cap, format!("{suffix} files")))
        .unwrap_or((DEFAULT_SIZE_CAP, "files of this kind".into()))
}

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

/// A normalised name that stays below the folder it is joined to: not
/// empty, no `..`, no drive or root prefix.
pub fn stays_inside(name: &str) -> bool {
    !name.is_empty()
        && Path::new(name)
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir))
}

impl ResPaths {
    pub fn new(roots: Vec<PathBuf>) -> Self {
        ResPaths { roots }
    }

    /// The first root holding `name`, as a full path. A name that climbs out
    /// with `..`, or an entry whose symbolic links lead outside every root,
    /// resolves to nothing ([`ResPaths::read`] says why).
    pub fn resolve(&self, name: &str) -> Option<PathBuf> {
        self.locate(name).ok().flatten()
    }

    fn locate(&self, name: &str) -> Result<Option<PathBuf>> {
        let name = normalise(name);
        if !stays_inside(&name) {
            return Ok(None);
        }
        for root in &self.roots {
            let path = root.join(&name);
            // `metadata` follows links but opens nothing: a FIFO is found
            // here and refused by `read_file`, never opened.
            if fs::metadata(&path).is_ok_and(|m| !m.is_dir()) {
                self.check_inside(&path)?;
                return Ok(Some(path));
            }
        }
        Ok(None)
    }

    /// Errors when `path`, with every symbolic link resolved, lies outside
    /// every res root (a link planted in a res folder pointing elsewhere).
    /// A path that does not exist passes: reading it says so.
    pub fn check_inside(&self, path: &Path) -> Result<()> {
        let real = match fs::canonicalize(path) {
            Ok(real) => real,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(Error::io(path, "resolve", e)),
        };
        let inside = self
            .roots
            .iter()
            .filter_map(|root| fs::canonicalize(root).ok())
            .any(|root| real.starts_with(root));
        if inside {
            return Ok(());
        }
        Err(Error::invalid(
            path,
            format!(
                "leads to {}, outside every res path ({}); refused: copy the file into a res path or add its folder to <resPaths>",
                real.display(),
                self.roots_list()
            ),
        ))
    }

    fn roots_list(&self) -> String {
        self.roots
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
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
        let normal = normalise(name);
        if !normal.is_empty() && !stays_inside(&normal) {
            return Err(Error::invalid(
                referenced_by,
                format!("resource `{normal}` climbs out of the res paths (`..` or a drive prefix); refused: name resources relative to a res path"),
            ));
        }
        let path = self.locate(name)?.ok_or_else(|| Error::NotFound {
            name: normal,
            referenced_by: referenced_by.to_path_buf(),
            searched: self.roots.clone(),
        })?;
        let bytes = read_file(&path)?;
        Ok((path, bytes))
    }
}

/// What a file that is not a regular file is, in words.
fn kind_of(meta: &Metadata) -> &'static str {
    let kind = meta.file_type();
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if kind.is_char_device() {
            return "a character device";
        }
        if kind.is_block_device() {
            return "a block device";
        }
        if kind.is_socket() {
            return "a socket";
        }
    }
    if kind.is_dir() {
        "a folder"
    } else if kind.is_file() {
        "a regular file"
    } else {
        "a special file"
    }
}

fn not_regular(path: &Path, meta: &Metadata) -> Error {
    let through_link = fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
    Error::invalid(
        path,
        format!(
            "is {}{}, not a regular file; only regular files are read (a pipe or device can block or never end): put the file itself there",
            kind_of(meta),
            if through_link {
                " (through a symbolic link)"
            } else {
                ""
            }
        ),
    )
}

fn too_large(path: &Path, cap: u64, kind: &str, size: Option<u64>) -> Error {
    Error::invalid(
        path,
        format!(
            "{} the cap of {} MiB for {kind}; no BigWorld file of this kind is that large: check the file",
            match size {
                Some(size) => format!("holds {size} bytes, more than"),
                None => "grew past".to_string(),
            },
            cap / MIB
        ),
    )
}

/// Opens for reading without blocking: with `O_NONBLOCK`, a FIFO swapped in
/// after the metadata check opens at once (and is then refused) instead of
/// waiting for a writer.
fn open_for_reading(path: &Path) -> std::io::Result<File> {
    let mut options = fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    options.open(path)
}

/// At most `cap + 1` bytes of `reader`: one more than the cap tells a file
/// that grew past it from one that fits exactly.
fn read_at_most(reader: impl Read, cap: u64, size_hint: u64) -> std::io::Result<Vec<u8>> {
    let mut bytes = Vec::with_capacity(size_hint.min(cap) as usize);
    reader.take(cap + 1).read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// The summed sizes of files (for estimates; a file that cannot be
/// examined counts 0).
pub fn total_size<'a>(paths: impl Iterator<Item = &'a Path>) -> u64 {
    paths
        .filter_map(|p| std::fs::metadata(p).ok())
        .map(|m| m.len())
        .sum()
}

/// Reads a whole regular file (following symbolic links), refusing FIFOs,
/// devices and folders before opening them and files larger than the cap
/// of their kind ([`SIZE_CAPS`]).
pub fn read_file(path: &Path) -> Result<Vec<u8>> {
    let (cap, kind) = size_cap(path);
    let meta = fs::metadata(path).map_err(|e| Error::io(path, "read", e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    let file = open_for_reading(path).map_err(|e| Error::io(path, "read", e))?;
    // The entry may have changed since the check: ask the open handle.
    let meta = file.metadata().map_err(|e| Error::io(path, "read", e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    if meta.len() > cap {
        return Err(too_large(path, cap, &kind, Some(meta.len())));
    }
    let bytes = read_at_most(file, cap, meta.len()).map_err(|e| Error::io(path, "read", e))?;
    if bytes.len() as u64 > cap {
        return Err(too_large(path, cap, &kind, None));
    }
    Ok(bytes)
}

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

/// Replaces `path` atomically (see [`write_files`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_files(&[(path, bytes)])
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

fn folder_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

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
fn plan_target(target: &Path) -> std::result::Result<(PathBuf, Option<Metadata>), String> {
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

/// How old a temporary file of another host must be before it counts as
/// stale. Its process cannot be looked up from here (a live bake on another
/// machine sharing the volume has a process id this machine does not know),
/// and a live bake keeps a temporary file only while it writes its batch:
/// seconds to minutes.
pub const STALE_TEMPORARY_AGE: Duration = Duration::from_secs(3600);

/// This machine's name as it appears in temporary file names: the host
/// name with anything but letters, digits, `.`, `-` and `_` replaced by
/// `_` (`unknown` when it cannot be read).
pub fn host_name() -> &'static str {
    static NAME: OnceLock<String> = OnceLock::new();
    NAME.get_or_init(|| {
        let name: String = raw_host_name()
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        if name.is_empty() {
            "unknown".into()
        } else {
            name
        }
    })
}

#[cfg(unix)]
fn raw_host_name() -> String {
    let mut buffer = [0u8; 256];
    // SAFETY: the buffer is writable for its whole length; gethostname
    // writes at most that many bytes.
    let status = unsafe { libc::gethostname(buffer.as_mut_ptr().cast(), buffer.len()) };
    if status != 0 {
        return String::new();
    }
    let end = buffer.iter().position(|&b| b == 0).unwrap_or(buffer.len());
    String::from_utf8_lossy(&buffer[..end]).into_owned()
}

#[cfg(not(unix))]
fn raw_host_name() -> String {
    std::env::var("COMPUTERNAME").unwrap_or_default()
}

/// `.NAME.shadowcull-HOST-PID.tmp`, beside `real`.
fn temporary_path(real: &Path) -> PathBuf {
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
    /// `None` in the names of versions before the host was recorded.
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

/// Whether process `pid` still runs (Linux: `/proc`; elsewhere assumed
/// not, so its temporary files count as stale).
fn process_alive(pid: u32) -> bool {
    cfg!(target_os = "linux") && Path::new("/proc").join(pid.to_string()).exists()
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
fn remove_stale_temporaries(dir: &Path) {
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
fn temporary_folder(target: &Path) -> PathBuf {
    let is_link = fs::symlink_metadata(target).is_ok_and(|m| m.file_type().is_symlink());
    match is_link.then(|| fs::canonicalize(target)) {
        Some(Ok(real)) => folder_of(&real),
        _ => folder_of(target),
    }
}

/// The targets that must not be replaced ([`Error::Refused`], every such
/// file named): the checks [`write_files`] makes before it writes, for a
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

/// Writes one temporary file: a new file (never through an existing link),
/// the mode and owner of the file it replaces, synced to disk.
fn write_temporary(temp: &Path, bytes: &[u8], existing: Option<&Metadata>) -> Result<()> {
    let _ = fs::remove_file(temp);
    let mut file = fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(temp)
        .map_err(|e| Error::io(temp, "create", e))?;
    file.write_all(bytes)
        .map_err(|e| Error::io(temp, "write", e))?;
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
    file.sync_all().map_err(|e| Error::io(temp, "sync", e))
}

/// Replaces every file of a batch so that a crash or kill never leaves a
/// torn file:
/// 1. every target is checked first (a regular file or new, writable, not
///    read-only; symbolic links resolved to their target); any refusal
///    fails the batch with every refused file named and nothing written;
/// 2. stale temporary files of earlier runs are removed from the folders
///    ([`is_stale`]);
/// 3. each file's bytes go to a temporary file beside its target, keeping
///    the target's mode (and owner where possible), synced to disk; a
///    failure removes them all, so nothing was replaced;
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
/// file's temporary is written and synced: step 3, the one that takes time
/// (a sync per file; minutes for thousands of chunks), so a caller can show
/// progress while this module keeps the file system to itself.
pub fn write_files_beside(
    files: &[(&Path, &[u8])],
    unchanged: &[&Path],
    written: &mut dyn FnMut(),
) -> Result<()> {
    let mut planned: Vec<Planned> = Vec::with_capacity(files.len());
    let mut refused = Vec::new();
    let mut claimed: BTreeMap<PathBuf, &Path> = BTreeMap::new();
    for &(target, bytes) in files {
        match plan_target(target) {
            Ok((real, existing)) => {
                if let Some(first) = claimed.get(&real) {
                    refused.push((
                        target.to_path_buf(),
                        format!(
                            "is the same file as {}: two outputs would replace it",
                            first.display()
                        ),
                    ));
                    continue;
                }
                claimed.insert(real.clone(), target);
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
    if !refused.is_empty() {
        return Err(Error::Refused { files: refused });
    }

    let mut folders: Vec<&Path> = planned.iter().map(|p| p.folder.as_path()).collect();
    folders.sort();
    folders.dedup();
    for folder in &folders {
        fs::create_dir_all(folder).map_err(|e| Error::io(*folder, "create folder", e))?;
    }
    let mut swept: Vec<PathBuf> = unchanged.iter().map(|t| temporary_folder(t)).collect();
    swept.extend(folders.iter().map(|f| f.to_path_buf()));
    swept.sort();
    swept.dedup();
    for folder in &swept {
        remove_stale_temporaries(folder);
    }

    let mut temporaries: Vec<PathBuf> = Vec::with_capacity(planned.len());
    for file in &planned {
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

    for (index, (file, temp)) in planned.iter().zip(&temporaries).enumerate() {
        if let Err(e) = fs::rename(temp, &file.real) {
            for temp in &temporaries[index..] {
                let _ = fs::remove_file(temp);
            }
            let action = if index == 0 {
                "replace (nothing was replaced)"
            } else {
                "replace (files before it were replaced; run again to complete)"
            };
            return Err(Error::io(&file.real, action, e));
        }
    }

    // Makes the renames durable. Not every file system can sync a folder;
    // the files themselves are complete either way.
    #[cfg(unix)]
    for folder in &folders {
        if let Ok(handle) = File::open(folder) {
            let _ = handle.sync_all();
        }
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
    fn names_that_climb_out_are_refused() {
        for name in ["a/b.model", "./a.model", "x"] {
            assert!(stays_inside(name), "{name}");
        }
        for name in ["", "../a.model", "a/../../b", "a/.."] {
            assert!(!stays_inside(name), "{name}");
        }
        let root = tempfile::tempdir().unwrap();
        let paths = ResPaths::new(vec![root.path().join("res")]);
        write_atomic(&root.path().join("secret.model"), b"x").unwrap();
        let message = paths
            .read("../secret.model", Path::new("c.chunk"))
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("c.chunk:") && message.contains("climbs out"),
            "{message}"
        );
    }

    #[cfg(unix)]
    #[test]
    fn links_out_of_the_res_paths_are_refused() {
        let root = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        write_atomic(&outside.path().join("b.model"), b"outside").unwrap();
        write_atomic(&root.path().join("real/c.model"), b"inside").unwrap();
        std::fs::create_dir_all(root.path().join("sets")).unwrap();
        std::os::unix::fs::symlink(
            outside.path().join("b.model"),
            root.path().join("sets/b.model"),
        )
        .unwrap();
        std::os::unix::fs::symlink(
            root.path().join("real/c.model"),
            root.path().join("sets/c.model"),
        )
        .unwrap();
        let paths = ResPaths::new(vec![root.path().into()]);
        let message = paths
            .read("sets/b.model", Path::new("c.chunk"))
            .unwrap_err()
            .to_string();
        assert!(message.contains("outside every res path"), "{message}");
        assert_eq!(paths.resolve("sets/b.model"), None);
        // A link that stays inside the roots is followed.
        assert_eq!(
            paths.read("sets/c.model", Path::new("c.chunk")).unwrap().1,
            b"inside"
        );
    }

    #[test]
    fn reads_stop_one_byte_past_the_cap() {
        let endless = std::io::repeat(7);
        assert_eq!(read_at_most(endless, 10, 1 << 40).unwrap().len(), 11);
        assert_eq!(read_at_most(&b"abc"[..], 10, 3).unwrap(), b"abc");
    }

    #[test]
    fn caps_are_per_kind_of_file() {
        assert_eq!(size_cap(Path::new("a/b.chunk")).0, 64 * MIB);
        assert_eq!(size_cap(Path::new("b.PRIMITIVES")).0, GIB);
        assert_eq!(size_cap(Path::new("x.cdata")).0, GIB);
        assert_eq!(size_cap(Path::new("bake.xml")).0, DEFAULT_SIZE_CAP);
        // A sparse file one byte over the cap is refused without reading.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.chunk");
        File::create(&path).unwrap().set_len(64 * MIB + 1).unwrap();
        let message = read_file(&path).unwrap_err().to_string();
        assert!(
            message.contains("big.chunk") && message.contains("cap of 64 MiB for .chunk files"),
            "{message}"
        );
    }

    #[test]
    fn folders_are_not_read() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("x.chunk")).unwrap();
        let message = read_file(&dir.path().join("x.chunk"))
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("is a folder, not a regular file"),
            "{message}"
        );
    }

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
        // The names of versions before the host was recorded.
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

    #[test]
    fn host_names_are_file_name_safe() {
        let host = host_name();
        assert!(!host.is_empty());
        assert!(host
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_')));
    }

    /// Names in `dir`, sorted.
    fn names(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
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
