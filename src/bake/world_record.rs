//! A baked world's record: every file the bake read (chunks as written)
//! with its stamp and content key, the folders its lookups went through
//! with their entry names, and the space's chunk list, kept in the cache
//! after a bake in place. A later bake with the same settings, options and
//! build checks the record before loading anything: when every file and
//! folder is as recorded, a bake would write every chunk as it is
//! (re-baking a baked world changes no byte, docs/contract.md §5), so
//! there is nothing to load, trace or write.
//!
//! A file counts as unchanged by its stamp alone only when its times are
//! older than the record by [`crate::cache::RACY_NANOSECONDS`] (git's rule for racily
//! clean entries: a write within the file system's time resolution could
//! leave the same stamp); otherwise it is read and its content key
//! compared. A folder is trusted the same way or by its entry names, so a
//! file that appears where a lookup would find it first (a `.cdata` beside
//! its chunk, a model in an earlier res path) is never missed. Any
//! difference, or anything that cannot be read, sends the bake down the
//! ordinary path, which reports it.

use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{content_key, trusted, Cache, Key, KeyHasher, Kind, KnownFiles};
use crate::digest::Digest;
use crate::files::{self, Stamp};
use crate::scene::Scene;
use rayon::prelude::*;
use std::collections::{BTreeSet, HashMap, HashSet};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// One light's line of the bake's table, kept for the record's report.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LightLine {
    pub bit: u32,
    pub name: String,
    pub kind: String,
    pub useful: u64,
    pub culled: u64,
}

/// What a bake found when the record held: how much it checked and the
/// recorded bake's table.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UpToDate {
    pub files: usize,
    pub folders: usize,
    /// Files read again (stamped too recently, or touched).
    pub files_read: usize,
    pub chunk_files: usize,
    pub lights: Vec<LightLine>,
}

/// A file as the record keeps it.
#[derive(Debug, Clone, PartialEq, Eq)]
struct FileEntry {
    path: PathBuf,
    stamp: Stamp,
    key: Key,
}

/// A folder as the record keeps it: the hash of its sorted entry names.
#[derive(Debug, Clone, PartialEq, Eq)]
struct FolderEntry {
    path: PathBuf,
    stamp: Stamp,
    names: Key,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Record {
    /// Taken before the first stamp.
    recorded_at_ns: u64,
    space_dir: PathBuf,
    /// The loader walks sub-folders (no `<singleDir>`).
    recursive: bool,
    chunk_list: Key,
    files: Vec<FileEntry>,
    folders: Vec<FolderEntry>,
    chunk_files: usize,
    lights: Vec<LightLine>,
}

/// The key of a world's record: `facts` are everything besides the files
/// that decides the bake's output (the settings after every override,
/// the bake's options, the settings file's path).
pub fn record_key(cache: &Cache, facts: &[&str]) -> Key {
    let mut hasher = cache.hasher(Kind::World);
    hasher.u64(facts.len() as u64);
    for fact in facts {
        hasher.str(fact);
    }
    hasher.finish()
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The hash of a folder's sorted entry names.
fn names_key(dir: &Path) -> Option<Key> {
    let names = files::folder_names(dir).ok()?;
    let mut hasher = KeyHasher::content("folder names");
    hasher.u64(names.len() as u64);
    for name in &names {
        hasher.bytes(name.as_encoded_bytes());
    }
    Some(hasher.finish())
}

/// The hash of the chunk files a load of `space_dir` would read; `None`
/// when the walk refuses an entry (the load reports it as a problem).
fn chunk_list(space_dir: &Path, recursive: bool) -> Option<(Key, usize)> {
    let walk = files::walk(space_dir, ".chunk", recursive).ok()?;
    if !walk.refused.is_empty() {
        return None;
    }
    let mut hasher = KeyHasher::content("chunk list");
    hasher.u64(walk.files.len() as u64);
    for path in &walk.files {
        hasher.bytes(path.as_os_str().as_encoded_bytes());
    }
    Some((hasher.finish(), walk.files.len()))
}

/// What [`check`] found.
#[derive(Debug)]
pub enum Checked {
    /// Every file, folder and the chunk list are as recorded.
    UpToDate(UpToDate),
    /// Something differs: the recorded files, whose stamps tell which of
    /// them need not be read again.
    Changed(KnownFiles),
    /// No record (or one that cannot be read).
    NoRecord,
}

/// Checks `cache`'s record under `key` (refreshing it when files had to
/// be read, so the next check reads none).
pub fn check(cache: &Cache, key: &Key) -> Checked {
    let Some(record) = cache.get(Kind::World, key).and_then(|value| decode(&value)) else {
        return Checked::NoRecord;
    };
    match up_to_date(cache, key, &record) {
        Some(found) => Checked::UpToDate(found),
        None => Checked::Changed(KnownFiles::new(
            record
                .files
                .iter()
                .map(|f| (f.path.as_path(), f.stamp, f.key)),
            record.recorded_at_ns,
        )),
    }
}

/// `Some` when every file, folder and the chunk list of `record` (under
/// `key`) are as recorded.
fn up_to_date(cache: &Cache, key: &Key, record: &Record) -> Option<UpToDate> {
    let started = now_ns();
    let files: Vec<(FileEntry, bool)> = record
        .files
        .par_iter()
        .map(|entry| check_file(entry, record.recorded_at_ns))
        .collect::<Option<_>>()?;
    let folders: Vec<(FolderEntry, bool)> = record
        .folders
        .par_iter()
        .map(|entry| check_folder(entry, record.recorded_at_ns))
        .collect::<Option<_>>()?;
    let (list, _) = chunk_list(&record.space_dir, record.recursive)?;
    if list != record.chunk_list {
        return None;
    }
    let files_read = files.iter().filter(|(_, read)| *read).count();
    let folders_listed = folders.iter().filter(|(_, listed)| *listed).count();
    let found = UpToDate {
        files: files.len(),
        folders: folders.len(),
        files_read,
        chunk_files: record.chunk_files,
        lights: record.lights.clone(),
    };
    if files_read + folders_listed > 0 {
        let refreshed = Record {
            recorded_at_ns: started,
            files: files.into_iter().map(|(entry, _)| entry).collect(),
            folders: folders.into_iter().map(|(entry, _)| entry).collect(),
            space_dir: record.space_dir.clone(),
            chunk_list: record.chunk_list,
            lights: record.lights.clone(),
            ..*record
        };
        cache.put(Kind::World, key, &encode(&refreshed));
    }
    Some(found)
}

/// The file's entry as it is now, and whether it had to be read; `None`
/// when it changed (or cannot be read).
fn check_file(entry: &FileEntry, recorded_at_ns: u64) -> Option<(FileEntry, bool)> {
    let stamp = files::stamp(&entry.path)?;
    if stamp == entry.stamp && trusted(&stamp, recorded_at_ns) {
        return Some((entry.clone(), false));
    }
    let bytes = files::read_file(&entry.path).ok()?;
    (content_key(&bytes) == entry.key).then(|| {
        let entry = FileEntry {
            stamp,
            ..entry.clone()
        };
        (entry, true)
    })
}

/// As [`check_file`] for a folder: listed again unless its stamp proves it
/// unchanged.
fn check_folder(entry: &FolderEntry, recorded_at_ns: u64) -> Option<(FolderEntry, bool)> {
    let stamp = files::stamp(&entry.path)?;
    if stamp == entry.stamp && trusted(&stamp, recorded_at_ns) {
        return Some((entry.clone(), false));
    }
    (names_key(&entry.path)? == entry.names).then(|| {
        let entry = FolderEntry {
            stamp,
            ..entry.clone()
        };
        (entry, true)
    })
}

/// What a finished in-place bake leaves for the record: its scene, the
/// bytes each chunk file now holds, the res roots its lookups searched,
/// and its table.
pub struct Baked<'a> {
    pub scene: &'a Scene,
    /// Every chunk file's path and the content key of the bytes the bake
    /// left in it.
    pub chunks: Vec<(&'a Path, Key)>,
    pub res_roots: &'a [PathBuf],
    pub lights: Vec<LightLine>,
}

/// Why no record was kept (the bake itself is done either way).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NotRecorded {
    /// The scene has problems: a record could not say what a re-bake
    /// would find.
    Problems,
    /// A file changed while the bake ran, or could not be read again.
    Changed(PathBuf),
}

/// What a file must hold to be recorded: the bytes a bake left in a chunk
/// (by content key), or the bytes the load read (by digest).
#[derive(Clone, Copy)]
enum Expected {
    Key(Key),
    Digest(Digest),
}

/// Stores the record of `baked` under `key`. Every file is stamped, then
/// read again and compared with what the bake used (the chunks with the
/// bytes it left in them), so a file edited during the bake is never
/// recorded as baked; a file whose stamp proves it unchanged since the
/// last record keeps that record's key without being read.
pub fn record(cache: &Cache, key: &Key, baked: &Baked) -> Result<(), NotRecorded> {
    let scene = baked.scene;
    if !scene.problems.is_empty() {
        return Err(NotRecorded::Problems);
    }
    let recorded_at_ns = now_ns();
    // By their bytes: the paths come from the same places, and comparing
    // paths component by component costs seconds on a large world.
    let chunks: HashMap<&OsStr, Key> = baked
        .chunks
        .iter()
        .map(|&(path, key)| (path.as_os_str(), key))
        .collect();
    let expected: Vec<(&Path, Expected)> = scene
        .inputs
        .iter()
        .map(|input| match chunks.get(input.path.as_os_str()) {
            Some(key) => (input.path.as_path(), Expected::Key(*key)),
            None => (input.path.as_path(), Expected::Digest(input.digest)),
        })
        .collect();
    // A file the last record holds with a stamp that proves it unchanged
    // since is what this bake read: its key is reused, not read again.
    let previous = cache.get(Kind::World, key).and_then(|value| decode(&value));
    let unchanged: HashMap<&OsStr, &FileEntry> = previous
        .iter()
        .flat_map(|record| &record.files)
        .map(|entry| (entry.path.as_os_str(), entry))
        .collect();
    let previous_at = previous.as_ref().map_or(0, |record| record.recorded_at_ns);
    let files: Vec<FileEntry> = expected
        .par_iter()
        .map(|&(path, expected)| {
            let changed = || NotRecorded::Changed(path.to_path_buf());
            let stamp = files::stamp(path).ok_or_else(changed)?;
            if let Some(&entry) = unchanged.get(path.as_os_str()) {
                if entry.stamp == stamp && trusted(&stamp, previous_at) {
                    return Ok(entry.clone());
                }
            }
            let bytes = files::read_file(path).map_err(|_| changed())?;
            let key = content_key(&bytes);
            let same = match expected {
                Expected::Key(k) => k == key,
                Expected::Digest(d) => d == Digest::of(&bytes),
            };
            if !same {
                return Err(changed());
            }
            Ok(FileEntry {
                path: path.to_path_buf(),
                stamp,
                key,
            })
        })
        .collect::<Result<_, _>>()?;
    let folders = looked_through(files.iter().map(|f| f.path.as_path()), baked.res_roots)
        .into_par_iter()
        .map(|path| {
            let changed = || NotRecorded::Changed(path.clone());
            let stamp = files::stamp(&path).ok_or_else(changed)?;
            let names = names_key(&path).ok_or_else(changed)?;
            Ok(FolderEntry { path, stamp, names })
        })
        .collect::<Result<_, _>>()?;
    let recursive = !scene.settings.single_dir;
    let (chunk_list, chunk_files) = chunk_list(&scene.space_dir, recursive)
        .ok_or_else(|| NotRecorded::Changed(scene.space_dir.clone()))?;
    let record = Record {
        recorded_at_ns,
        space_dir: scene.space_dir.clone(),
        recursive,
        chunk_list,
        files,
        folders,
        chunk_files,
        lights: baked.lights.clone(),
    };
    cache.put(Kind::World, key, &encode(&record));
    Ok(())
}

/// The folders whose entries decide what the bake's lookups found: each
/// file's own folder (a file beside it found first), and for a file under
/// a res root, the same folder under every root (a file there found
/// first), or its nearest folder that exists (where that folder would
/// appear).
fn looked_through<'p>(paths: impl Iterator<Item = &'p Path>, roots: &[PathBuf]) -> Vec<PathBuf> {
    let mut folders = BTreeSet::new();
    // A space's files share a few folders: each is looked through once.
    let mut seen: HashSet<&OsStr> = HashSet::new();
    for path in paths {
        let Some(dir) = path.parent() else { continue };
        if !seen.insert(dir.as_os_str()) {
            continue;
        }
        folders.insert(dir.to_path_buf());
        let Some(relative) = roots.iter().find_map(|r| dir.strip_prefix(r).ok()) else {
            continue;
        };
        for root in roots {
            let mut candidate = root.join(relative);
            while !files::exists(&candidate) {
                match candidate.parent() {
                    Some(up) if up != candidate => candidate = up.to_path_buf(),
                    _ => break,
                }
            }
            folders.insert(candidate);
        }
    }
    folders.into_iter().collect()
}

fn encode(record: &Record) -> Vec<u8> {
    let mut e = Encoder::new();
    e.u64(record.recorded_at_ns)
        .bytes(record.space_dir.as_os_str().as_encoded_bytes())
        .u8(u8::from(record.recursive))
        .bytes(&record.chunk_list.0)
        .var(record.chunk_files as u64);
    e.var(record.files.len() as u64);
    for file in &record.files {
        encode_stamped(&mut e, &file.path, &file.stamp, &file.key);
    }
    e.var(record.folders.len() as u64);
    for folder in &record.folders {
        encode_stamped(&mut e, &folder.path, &folder.stamp, &folder.names);
    }
    e.var(record.lights.len() as u64);
    for light in &record.lights {
        e.u32(light.bit)
            .str(&light.name)
            .str(&light.kind)
            .var(light.useful)
            .var(light.culled);
    }
    e.into_bytes()
}

fn encode_stamped(e: &mut Encoder, path: &Path, stamp: &Stamp, key: &Key) {
    e.bytes(path.as_os_str().as_encoded_bytes());
    for v in stamp.to_array() {
        e.u64(v);
    }
    e.bytes(&key.0);
}

fn decode(bytes: &[u8]) -> Option<Record> {
    let mut d = Decoder::new(bytes);
    let recorded_at_ns = d.u64().ok()?;
    let space_dir = path_of(d.bytes().ok()?)?;
    let recursive = d.u8().ok()? != 0;
    let chunk_list = key_of(d.bytes().ok()?)?;
    let chunk_files = d.var().ok()? as usize;
    let mut files = Vec::new();
    for _ in 0..d.len(1).ok()? {
        let (path, stamp, key) = decode_stamped(&mut d)?;
        files.push(FileEntry { path, stamp, key });
    }
    let mut folders = Vec::new();
    for _ in 0..d.len(1).ok()? {
        let (path, stamp, names) = decode_stamped(&mut d)?;
        folders.push(FolderEntry { path, stamp, names });
    }
    let mut lights = Vec::new();
    for _ in 0..d.len(1).ok()? {
        lights.push(LightLine {
            bit: d.u32().ok()?,
            name: d.str().ok()?,
            kind: d.str().ok()?,
            useful: d.var().ok()?,
            culled: d.var().ok()?,
        });
    }
    d.is_done().then_some(Record {
        recorded_at_ns,
        space_dir,
        recursive,
        chunk_list,
        files,
        folders,
        chunk_files,
        lights,
    })
}

fn decode_stamped(d: &mut Decoder) -> Option<(PathBuf, Stamp, Key)> {
    let path = path_of(d.bytes().ok()?)?;
    let mut stamp = [0u64; 5];
    for v in &mut stamp {
        *v = d.u64().ok()?;
    }
    let key = key_of(d.bytes().ok()?)?;
    Some((path, Stamp::from_array(stamp), key))
}

fn path_of(bytes: &[u8]) -> Option<PathBuf> {
    Some(PathBuf::from(std::str::from_utf8(bytes).ok()?))
}

fn key_of(bytes: &[u8]) -> Option<Key> {
    Some(Key(bytes.try_into().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Record {
        let stamp = Stamp::from_array([1, 2, 3, 4, 5]);
        Record {
            recorded_at_ns: 77,
            space_dir: PathBuf::from("/w/spaces/a"),
            recursive: true,
            chunk_list: Key([9; 32]),
            files: vec![FileEntry {
                path: PathBuf::from("/w/spaces/a/00000000o.chunk"),
                stamp,
                key: Key([1; 32]),
            }],
            folders: vec![FolderEntry {
                path: PathBuf::from("/w/spaces/a"),
                stamp,
                names: Key([2; 32]),
            }],
            chunk_files: 1,
            lights: vec![LightLine {
                bit: 3,
                name: "sun".into(),
                kind: "directional".into(),
                useful: 10,
                culled: 4,
            }],
        }
    }

    #[test]
    fn a_record_reads_back_and_a_cut_one_is_no_record() {
        let record = sample();
        let bytes = encode(&record);
        assert_eq!(decode(&bytes), Some(record));
        for cut in 0..bytes.len() {
            assert_eq!(decode(&bytes[..cut]), None, "cut at {cut}");
        }
    }

    #[test]
    fn lookups_are_watched_in_every_root() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        crate::files::write_atomic(&b.join("sets/x/m.model"), b"").unwrap();
        crate::files::write_atomic(&a.join("other"), b"").unwrap();
        let file = b.join("sets/x/m.model");
        let folders = looked_through([file.as_path()].into_iter(), &[a.clone(), b.clone()]);
        // Its own folder, and in root `a` the nearest folder that exists.
        assert_eq!(folders, vec![a, b.join("sets/x")]);
    }
}
