//! The bake cache: results a later bake can reuse, each stored under a key
//! that is the hash of exactly the inputs that produced it (content, not
//! modification times). A bake with a cache computes only what is missing,
//! and the cache is only ever an optimisation: an entry is used only when
//! it passes every check (format, kind, key, length, checksum); any other
//! entry (truncated, bit-flipped, swapped with another, from another
//! format) is recomputed and replaced, with a one-line warning. Entries are
//! written atomically (`files::write_cache_entry`), so a bake killed at any
//! moment, or two bakes sharing one cache, leave entries that are whole or
//! absent. The folder is kept under a size limit by removing the least
//! recently used entries.

pub mod codec;
mod known;
mod size_ledger;

pub use known::{trusted, KnownFiles};

use crate::files::{self, CacheFile};
use size_ledger::SizeLedger;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, SystemTime};

/// Bumped whenever an entry's layout or a value's encoding changes.
pub const FORMAT_VERSION: u32 = 1;

/// The default size limit of a cache folder.
pub const DEFAULT_MAX_BYTES: u64 = 2 << 30;

/// A temporary older than this was left by a killed writer.
const STALE_TEMPORARY: Duration = Duration::from_secs(3600);

const MAGIC: &[u8; 8] = b"SCCACHE\0";
/// Magic, format version, kind, key, payload length.
const HEADER_BYTES: usize = 8 + 4 + 1 + 32 + 8;
const CHECKSUM_BYTES: usize = 32;

/// What an entry holds; each kind has its own folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Kind {
    /// A chunk file's parsed items.
    Chunk,
    /// A model's loaded geometry.
    Model,
    /// A space's terrain blocks' height ranges, so their samples wait to
    /// be decoded.
    Terrain,
    /// The casters one cell of a light's grid proves useful.
    Cell,
    /// The casters refinement's rays prove useful, for the casters of one
    /// chunk it refines under one light.
    Refine,
    /// A light's record of its cells' inputs at its last bake, to say
    /// which input changed when a cell is traced again.
    Manifest,
    /// The `<shadow>`s a chunk file's bytes were written with, so a later
    /// bake whose masks are the same keeps the file without parsing it.
    Output,
    /// A baked world's record: every file it read and how it found them,
    /// so a bake of an unchanged world knows it without loading it.
    World,
}

impl Kind {
    pub const ALL: [Kind; 8] = [
        Kind::Chunk,
        Kind::Model,
        Kind::Terrain,
        Kind::Cell,
        Kind::Refine,
        Kind::Manifest,
        Kind::Output,
        Kind::World,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Kind::Chunk => "chunk",
            Kind::Model => "model",
            Kind::Terrain => "terrain",
            Kind::Cell => "cell",
            Kind::Refine => "refine",
            Kind::Manifest => "manifest",
            Kind::Output => "output",
            Kind::World => "world",
        }
    }

    fn code(self) -> u8 {
        self as u8
    }
}

/// An entry's key: the BLAKE3 hash of everything that decides its value.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Key(pub [u8; 32]);

impl Key {
    fn hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// The first 8 bytes as a number: a short digest for records that
    /// only compare inputs (a manifest), never for an entry's address.
    pub fn short(&self) -> u64 {
        u64::from_le_bytes(self.0[..8].try_into().unwrap_or_default())
    }
}

/// Builds a [`Key`] from typed values; every value is framed (lengths
/// prefixed) so two different sequences cannot hash alike. Small values
/// gather in a buffer before they reach the hash: a part's key is a few
/// dozen of them, and the hash's cost per call would outweigh them.
#[derive(Debug, Clone)]
pub struct KeyHasher {
    hasher: blake3::Hasher,
    buffer: [u8; KeyHasher::BUFFER],
    held: usize,
}

impl KeyHasher {
    const BUFFER: usize = 1024;

    fn empty() -> KeyHasher {
        KeyHasher {
            hasher: blake3::Hasher::new(),
            buffer: [0; KeyHasher::BUFFER],
            held: 0,
        }
    }

    fn update(&mut self, bytes: &[u8]) {
        if self.held + bytes.len() > KeyHasher::BUFFER {
            self.hasher.update(&self.buffer[..self.held]);
            self.held = 0;
            if bytes.len() > KeyHasher::BUFFER {
                self.hasher.update(bytes);
                return;
            }
        }
        self.buffer[self.held..self.held + bytes.len()].copy_from_slice(bytes);
        self.held += bytes.len();
    }

    /// A hasher for keys of `kind`, under the cache's build identity.
    pub fn new(kind: Kind, build: &Key) -> KeyHasher {
        let mut hasher = KeyHasher::across_builds(kind);
        hasher.update(&build.0);
        hasher
    }

    /// A hasher for keys of `kind` that every build shares: an entry only
    /// a build's own code reads back for what it says about an earlier
    /// bake (a light's manifest, which records the build that wrote it).
    pub fn across_builds(kind: Kind) -> KeyHasher {
        let mut hasher = KeyHasher::empty();
        hasher.update(MAGIC);
        hasher.update(&FORMAT_VERSION.to_le_bytes());
        hasher.update(&[kind.code()]);
        hasher
    }

    /// A hasher of content (a model's geometry, a terrain block's samples)
    /// for keys that other keys are built from; `domain` keeps the
    /// content keys of different things apart.
    pub fn content(domain: &str) -> KeyHasher {
        let mut hasher = KeyHasher::empty();
        hasher.str("shadowcull content").str(domain);
        hasher
    }

    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.update(&v.to_le_bytes());
        self
    }

    pub fn f32(&mut self, v: f32) -> &mut Self {
        self.u32(v.to_bits())
    }

    pub fn bool(&mut self, v: bool) -> &mut Self {
        self.update(&[u8::from(v)]);
        self
    }

    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.update(&v.to_le_bytes());
        self
    }

    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.u64(v.to_bits())
    }

    pub fn bytes(&mut self, v: &[u8]) -> &mut Self {
        self.u64(v.len() as u64);
        self.update(v);
        self
    }

    /// [`Self::bytes`] of the values' little-endian bytes, without
    /// gathering them first: a big world's terrain samples are hundreds
    /// of megabytes.
    pub fn f32s(&mut self, v: &[f32]) -> &mut Self {
        self.u64(v.len() as u64 * 4);
        let mut run = [0u8; KeyHasher::BUFFER];
        for values in v.chunks(KeyHasher::BUFFER / 4) {
            for (bytes, value) in run.chunks_exact_mut(4).zip(values) {
                bytes.copy_from_slice(&value.to_le_bytes());
            }
            self.update(&run[..values.len() * 4]);
        }
        self
    }

    pub fn str(&mut self, v: &str) -> &mut Self {
        self.bytes(v.as_bytes())
    }

    pub fn key(&mut self, v: &Key) -> &mut Self {
        self.update(&v.0);
        self
    }

    pub fn finish(&self) -> Key {
        let mut hasher = self.hasher.clone();
        hasher.update(&self.buffer[..self.held]);
        Key(*hasher.finalize().as_bytes())
    }
}

/// The hash of `bytes` (a file's content), as a key to build others from.
pub fn content_key(bytes: &[u8]) -> Key {
    Key(*blake3::hash(bytes).as_bytes())
}

/// What [`Cache::fetch`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fetched {
    /// The entry's value, checked.
    Value(Vec<u8>),
    /// No entry.
    Absent,
    /// An entry that failed its check (removed and warned about).
    Damaged,
}

/// The build identity of the running program: the hash of its own
/// executable's bytes, so a new build never reuses an old build's results.
pub fn executable_build() -> crate::Result<Key> {
    let mut hasher = blake3::Hasher::new();
    files::read_own_executable(&mut |bytes| {
        hasher.update(bytes);
    })?;
    Ok(Key(*hasher.finalize().as_bytes()))
}

/// A file this old or older than its hash's record is trusted by its
/// stamp: one written since, within the file system's time resolution,
/// could carry the same times (git's rule for racily clean entries).
pub const RACY_NANOSECONDS: u64 = 2_000_000_000;

/// [`executable_build`] with a stat shortcut kept in the cache folder
/// `dir`: the hash is read again only when the executable's length, inode,
/// device, or modification or status-change time differ from the record,
/// or when it was modified less than two seconds before the record was
/// made (it could have changed since within the same time stamp).
pub fn executable_build_in(dir: &Path) -> crate::Result<Key> {
    let Some(stamp) = files::own_executable_stamp() else {
        return executable_build();
    };
    let mut key = KeyHasher::across_builds(Kind::Manifest);
    key.str("the running executable");
    for v in stamp.to_array() {
        key.u64(v);
    }
    let key = key.finish();
    let record = Cache::open(dir, u64::MAX, Key::default());
    let modified = stamp.modified_ns;
    let recorded = record.get(Kind::Manifest, &key).and_then(|value| {
        let at = u64::from_le_bytes(value.get(..8)?.try_into().ok()?);
        let build = Key(value.get(8..40)?.try_into().ok()?);
        (value.len() == 40 && modified.saturating_add(RACY_NANOSECONDS) < at).then_some(build)
    });
    if let Some(build) = recorded {
        return Ok(build);
    }
    let build = executable_build()?;
    let now = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let mut value = now.to_le_bytes().to_vec();
    value.extend_from_slice(&build.0);
    record.put(Kind::Manifest, &key, &value);
    Ok(build)
}

/// What one bake did with the cache, per kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct KindCounts {
    /// Entries found and used.
    pub reused: u64,
    /// Entries absent, computed.
    pub computed: u64,
    /// Entries that failed their check, computed again.
    pub damaged: u64,
    /// Entries written.
    pub written: u64,
}

/// The cache folder of a bake.
#[derive(Debug)]
pub struct Cache {
    dir: PathBuf,
    max_bytes: u64,
    build: Key,
    counts: Mutex<Vec<KindCounts>>,
    warnings: Mutex<Vec<String>>,
    /// Bytes of the entries this bake wrote, for the folder's size ledger.
    written_bytes: AtomicU64,
}

impl Cache {
    /// The cache in `dir` (made when first written), keeping at most
    /// `max_bytes`. `build` identifies the program that computes the
    /// values: a key includes it, so another build never reuses them.
    pub fn open(dir: impl Into<PathBuf>, max_bytes: u64, build: Key) -> Cache {
        Cache {
            dir: dir.into(),
            max_bytes,
            build,
            counts: Mutex::new(vec![KindCounts::default(); Kind::ALL.len()]),
            warnings: Mutex::new(Vec::new()),
            written_bytes: AtomicU64::new(0),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// A key hasher for `kind` under this cache's build.
    pub fn hasher(&self, kind: Kind) -> KeyHasher {
        KeyHasher::new(kind, &self.build)
    }

    fn path(&self, kind: Kind, key: &Key) -> PathBuf {
        let hex = key.hex();
        self.dir.join(kind.name()).join(&hex[..2]).join(hex)
    }

    fn count(&self, kind: Kind, change: impl FnOnce(&mut KindCounts)) {
        if let Ok(mut counts) = self.counts.lock() {
            change(&mut counts[kind as usize]);
        }
    }

    fn warn(&self, message: String) {
        if let Ok(mut warnings) = self.warnings.lock() {
            warnings.push(message);
        }
    }

    /// The value stored under `key`, if an entry holds it and passes every
    /// check; `None` (counted as computed) otherwise. A damaged entry is
    /// removed and warned about.
    pub fn get(&self, kind: Kind, key: &Key) -> Option<Vec<u8>> {
        match self.fetch(kind, key) {
            Fetched::Value(value) => Some(value),
            Fetched::Absent | Fetched::Damaged => None,
        }
    }

    /// [`Self::get`], saying whether a missing value was absent or
    /// damaged.
    pub fn fetch(&self, kind: Kind, key: &Key) -> Fetched {
        let path = self.path(kind, key);
        let bytes = match files::read_cache_entry(&path) {
            Ok(Some(bytes)) => bytes,
            Ok(None) => {
                self.count(kind, |c| c.computed += 1);
                return Fetched::Absent;
            }
            Err(err) => {
                self.damaged(kind, &path, &err.to_string());
                return Fetched::Damaged;
            }
        };
        match check_entry(&bytes, kind, key) {
            Ok(payload) => {
                self.count(kind, |c| c.reused += 1);
                files::touch_cache_entry(&path);
                // The payload kept in the bytes read, not copied out: a
                // world's chunk entries are hundreds of megabytes.
                let mut bytes = bytes;
                bytes.truncate(payload.end);
                bytes.drain(..payload.start);
                Fetched::Value(bytes)
            }
            Err(why) => {
                self.damaged(kind, &path, why);
                Fetched::Damaged
            }
        }
    }

    /// Whether an entry exists under `key` (not read nor checked): what a
    /// plan counts as reusable.
    pub fn contains(&self, kind: Kind, key: &Key) -> bool {
        files::cache_entry_exists(&self.path(kind, key))
    }

    /// The value got under `key` does not decode as its kind's value: the
    /// entry is removed, counted as damaged and warned about (its caller
    /// computes the value again).
    pub fn reject(&self, kind: Kind, key: &Key) {
        self.count(kind, |c| c.reused = c.reused.saturating_sub(1));
        self.damaged(kind, &self.path(kind, key), "does not decode");
    }

    /// Removes the entry under `key`, if any: a value no later bake can
    /// ask for (the parsed items of chunk bytes a bake replaced in place).
    pub fn forget(&self, kind: Kind, key: &Key) {
        let _ = files::remove_cache_file(&self.path(kind, key));
    }

    fn damaged(&self, kind: Kind, path: &Path, why: &str) {
        self.count(kind, |c| c.damaged += 1);
        let _ = files::remove_cache_file(path);
        self.warn(format!("cache entry {} {why}; recomputed", path.display()));
    }

    /// Stores `value` under `key`. A failed write costs only the reuse: it
    /// is warned about, never an error of the bake.
    pub fn put(&self, kind: Kind, key: &Key, value: &[u8]) {
        let path = self.path(kind, key);
        let bytes = entry_bytes(kind, key, value);
        match files::write_cache_entry(&path, &bytes) {
            Ok(()) => {
                self.count(kind, |c| c.written += 1);
                self.written_bytes
                    .fetch_add(bytes.len() as u64, Ordering::Relaxed);
            }
            Err(err) => self.warn(format!("cannot store a cache entry: {err}")),
        }
    }

    /// The value under `key`, or `compute`'s (then stored) when there is
    /// none or it does not decode with `decode`.
    pub fn get_or_compute<T>(
        &self,
        kind: Kind,
        key: &Key,
        decode: impl FnOnce(&[u8]) -> Option<T>,
        compute: impl FnOnce() -> T,
        encode: impl FnOnce(&T) -> Vec<u8>,
    ) -> T {
        if let Some(bytes) = self.get(kind, key) {
            if let Some(value) = decode(&bytes) {
                return value;
            }
            self.reject(kind, key);
        }
        let value = compute();
        self.put(kind, key, &encode(&value));
        value
    }

    /// What this bake did with the cache, per kind in [`Kind::ALL`] order.
    pub fn counts(&self) -> Vec<(Kind, KindCounts)> {
        let counts = self.counts.lock().map(|c| c.clone()).unwrap_or_default();
        Kind::ALL.into_iter().zip(counts).collect()
    }

    /// The warnings so far (damaged entries, failed writes), each once.
    pub fn take_warnings(&self) -> Vec<String> {
        self.warnings
            .lock()
            .map(|mut w| std::mem::take(&mut *w))
            .unwrap_or_default()
    }

    /// Keeps the folder under its limit. When its size ledger is recent
    /// and, with what this bake wrote, within the limit, only the ledger
    /// is updated; otherwise the folder is listed: stale temporaries
    /// removed, then the least recently used entries until the rest fit,
    /// and the ledger set to what is left. Returns how many entries it
    /// removed.
    pub fn evict(&self) -> crate::Result<usize> {
        let now = SystemTime::now();
        let written = self.written_bytes.swap(0, Ordering::Relaxed);
        if let Some(ledger) = SizeLedger::read(&self.dir).filter(|l| l.trusted_at(now)) {
            let bytes = ledger.bytes.saturating_add(written);
            if bytes <= self.max_bytes {
                if written > 0 {
                    // Only a hint: a ledger not written means a listing next time.
                    let _ = SizeLedger { bytes, ..ledger }.write(&self.dir);
                }
                return Ok(0);
            }
        }
        let (removed, left) = self.evict_listed(now)?;
        if let Some(bytes) = left {
            let _ = SizeLedger::listed_now(bytes, now).write(&self.dir);
        }
        Ok(removed)
    }

    /// [`Self::evict`] by listing the folder: how many entries it removed
    /// and the bytes left (`None` when the folder holds nothing).
    fn evict_listed(&self, now: SystemTime) -> crate::Result<(usize, Option<u64>)> {
        let files = listed(&self.dir)?;
        if files.is_empty() {
            return Ok((0, None));
        }
        let (temporaries, mut entries): (Vec<CacheFile>, Vec<CacheFile>) =
            files.into_iter().partition(|f| f.temporary);
        for temp in temporaries {
            let age = now.duration_since(temp.modified).unwrap_or_default();
            if age > STALE_TEMPORARY {
                files::remove_cache_file(&temp.path)?;
            }
        }
        let mut total: u64 = entries.iter().map(|f| f.bytes).sum();
        entries.sort_by(|a, b| {
            (a.modified.cmp(&b.modified)).then(a.path.as_os_str().cmp(b.path.as_os_str()))
        });
        let mut removed = 0;
        for entry in entries {
            if total <= self.max_bytes {
                break;
            }
            files::remove_cache_file(&entry.path)?;
            total -= entry.bytes;
            removed += 1;
        }
        if removed > 0 {
            files::remove_empty_cache_folders(&self.dir);
        }
        Ok((removed, Some(total)))
    }
}

/// The entries and temporaries of cache folder `dir` (not its ledger).
fn listed(dir: &Path) -> crate::Result<Vec<CacheFile>> {
    let mut files = files::list_cache_files(dir)?;
    files.retain(|f| !size_ledger::is_ledger(dir, &f.path));
    Ok(files)
}

/// An entry: header, payload, checksum of both.
fn entry_bytes(kind: Kind, key: &Key, payload: &[u8]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(HEADER_BYTES + payload.len() + CHECKSUM_BYTES);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    bytes.push(kind.code());
    bytes.extend_from_slice(&key.0);
    bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    bytes.extend_from_slice(payload);
    let checksum = blake3::hash(&bytes);
    bytes.extend_from_slice(checksum.as_bytes());
    bytes
}

/// Where the payload lies in an entry read for (`kind`, `key`), or why
/// the entry cannot be trusted.
fn check_entry(bytes: &[u8], kind: Kind, key: &Key) -> Result<Range<usize>, &'static str> {
    if bytes.len() < HEADER_BYTES + CHECKSUM_BYTES {
        return Err("is truncated");
    }
    if &bytes[..8] != MAGIC {
        return Err("is not a shadowcull cache entry");
    }
    let (body, checksum) = bytes.split_at(bytes.len() - CHECKSUM_BYTES);
    if blake3::hash(body).as_bytes() != checksum {
        return Err("fails its checksum (truncated or damaged)");
    }
    if body[8..12] != FORMAT_VERSION.to_le_bytes() {
        return Err("is of another cache format");
    }
    if body[12] != kind.code() || body[13..45] != key.0 {
        return Err("holds another entry (swapped or renamed)");
    }
    let length = u64::from_le_bytes(body[45..53].try_into().unwrap_or_default());
    if length != (body.len() - HEADER_BYTES) as u64 {
        return Err("has a wrong length");
    }
    Ok(HEADER_BYTES..body.len())
}

/// What a cache folder holds, for `shadowcull cache DIR stats`.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct FolderStats {
    /// Per kind: entries and bytes.
    pub kinds: Vec<(String, u64, u64)>,
    pub entries: u64,
    pub bytes: u64,
    /// Temporaries left by killed writers (removed by the next listing
    /// once an hour old).
    pub temporaries: u64,
}

/// What the cache folder `dir` holds.
pub fn folder_stats(dir: &Path) -> crate::Result<FolderStats> {
    let mut stats = FolderStats {
        kinds: Kind::ALL
            .iter()
            .map(|k| (k.name().to_string(), 0, 0))
            .collect(),
        ..FolderStats::default()
    };
    for file in listed(dir)? {
        if file.temporary {
            stats.temporaries += 1;
            continue;
        }
        stats.entries += 1;
        stats.bytes += file.bytes;
        let kind = file
            .path
            .strip_prefix(dir)
            .ok()
            .and_then(|p| p.components().next())
            .map(|c| c.as_os_str().to_string_lossy().into_owned());
        if let Some(slot) = stats.kinds.iter_mut().find(|k| Some(&k.0) == kind.as_ref()) {
            slot.1 += 1;
            slot.2 += file.bytes;
        }
    }
    Ok(stats)
}

/// Removes every entry and temporary of the cache folder `dir`, and its
/// size ledger (the folder itself stays). Returns how many entries and
/// temporaries it removed.
pub fn clear_folder(dir: &Path) -> crate::Result<usize> {
    let files = listed(dir)?;
    for file in &files {
        files::remove_cache_file(&file.path)?;
    }
    SizeLedger::remove(dir)?;
    files::remove_empty_cache_folders(dir);
    Ok(files.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_hash_as_their_bytes_do() {
        for n in [0, 1, 255, 256, 257, 1000] {
            let values: Vec<f32> = (0..n).map(|i| i as f32 * 0.37 - 20.0).collect();
            let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            let mut by_values = KeyHasher::content("samples");
            let mut by_bytes = by_values.clone();
            by_values.u32(7).f32s(&values).u32(9);
            by_bytes.u32(7).bytes(&bytes).u32(9);
            assert_eq!(by_values.finish(), by_bytes.finish(), "{n} samples");
        }
        let mut one = KeyHasher::content("samples");
        let mut other = one.clone();
        assert_ne!(one.f32s(&[1.0]).finish(), other.f32s(&[1.5]).finish());
    }

    fn cache(dir: &Path, max: u64) -> Cache {
        Cache::open(dir, max, content_key(b"test build"))
    }

    fn key(cache: &Cache, n: u64) -> Key {
        cache.hasher(Kind::Cell).u64(n).finish()
    }

    #[test]
    fn a_value_put_is_got_back_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        let cache = cache(dir.path(), DEFAULT_MAX_BYTES);
        let k = key(&cache, 1);
        assert_eq!(cache.get(Kind::Cell, &k), None);
        cache.put(Kind::Cell, &k, b"value");
        assert_eq!(cache.get(Kind::Cell, &k).unwrap(), b"value");
        assert_eq!(cache.get(Kind::Refine, &k), None, "kinds are apart");
        let tile = cache.counts()[Kind::Cell as usize].1;
        assert_eq!((tile.reused, tile.computed, tile.written), (1, 1, 1));
        assert!(cache.take_warnings().is_empty());
    }

    #[test]
    fn every_damage_is_detected_warned_about_and_recomputed() {
        let dir = tempfile::tempdir().unwrap();
        let cache = cache(dir.path(), DEFAULT_MAX_BYTES);
        let (a, b) = (key(&cache, 1), key(&cache, 2));
        cache.put(Kind::Cell, &a, b"the value of a");
        cache.put(Kind::Cell, &b, b"the value of b");
        let path_a = cache.path(Kind::Cell, &a);
        let good = std::fs::read(&path_a).unwrap();
        type Damage = Box<dyn Fn(&mut Vec<u8>)>;
        let damage: Vec<(&str, Damage)> = vec![
            (
                "truncated",
                Box::new(|b: &mut Vec<u8>| b.truncate(b.len() - 5)),
            ),
            ("empty", Box::new(|b: &mut Vec<u8>| b.clear())),
            ("flipped", Box::new(|b: &mut Vec<u8>| b[60] ^= 1)),
            (
                "checksum flipped",
                Box::new(|b: &mut Vec<u8>| *b.last_mut().unwrap() ^= 1),
            ),
        ];
        for (what, change) in damage {
            let mut bytes = good.clone();
            change(&mut bytes);
            std::fs::write(&path_a, &bytes).unwrap();
            assert_eq!(cache.get(Kind::Cell, &a), None, "{what}");
            assert!(!path_a.exists(), "{what}: the damaged entry is removed");
            assert_eq!(cache.take_warnings().len(), 1, "{what}");
        }
        // Swapped: b's entry under a's name passes its checksum, not its key.
        std::fs::copy(cache.path(Kind::Cell, &b), &path_a).unwrap();
        assert_eq!(cache.get(Kind::Cell, &a), None);
        assert!(cache.take_warnings()[0].contains("another entry"));
        // Another format version.
        let mut other = good.clone();
        other[8] ^= 0xFF;
        let checksum = blake3::hash(&other[..other.len() - 32]);
        let n = other.len();
        other[n - 32..].copy_from_slice(checksum.as_bytes());
        std::fs::write(&path_a, &other).unwrap();
        assert_eq!(cache.get(Kind::Cell, &a), None);
        assert!(cache.take_warnings()[0].contains("format"));
        let computed = cache.get_or_compute(
            Kind::Cell,
            &a,
            |v| Some(v.to_vec()),
            || b"recomputed".to_vec(),
            |v| v.clone(),
        );
        assert_eq!(computed, b"recomputed");
        assert_eq!(cache.get(Kind::Cell, &a).unwrap(), b"recomputed");
    }

    #[test]
    fn another_build_never_sees_the_entries() {
        let dir = tempfile::tempdir().unwrap();
        let one = Cache::open(dir.path(), DEFAULT_MAX_BYTES, content_key(b"one"));
        let two = Cache::open(dir.path(), DEFAULT_MAX_BYTES, content_key(b"two"));
        let k = one.hasher(Kind::Cell).u64(5).finish();
        one.put(Kind::Cell, &k, b"v");
        let k2 = two.hasher(Kind::Cell).u64(5).finish();
        assert_ne!(k, k2);
        assert_eq!(two.get(Kind::Cell, &k2), None);
    }

    #[test]
    fn eviction_keeps_the_folder_under_its_limit_removing_the_oldest() {
        let dir = tempfile::tempdir().unwrap();
        let cache = cache(dir.path(), 1000);
        let keys: Vec<Key> = (0..10).map(|n| key(&cache, n)).collect();
        for (n, k) in keys.iter().enumerate() {
            cache.put(Kind::Cell, k, &[n as u8; 200]);
            let path = cache.path(Kind::Cell, k);
            let when = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000 + n as u64);
            std::fs::File::options()
                .append(true)
                .open(&path)
                .unwrap()
                .set_modified(when)
                .unwrap();
        }
        let removed = cache.evict().unwrap();
        let stats = folder_stats(dir.path()).unwrap();
        assert!(stats.bytes <= 1000, "{stats:?}");
        assert_eq!(stats.entries as usize + removed, 10);
        assert!(
            cache.get(Kind::Cell, &keys[9]).is_some(),
            "the newest stays"
        );
        assert!(cache.get(Kind::Cell, &keys[0]).is_none(), "the oldest goes");
        assert_eq!(clear_folder(dir.path()).unwrap(), stats.entries as usize);
        assert_eq!(folder_stats(dir.path()).unwrap().entries, 0);
        assert_eq!(
            SizeLedger::read(dir.path()),
            None,
            "clear removes the ledger"
        );
    }

    /// Puts an entry of `payload` bytes (285 bytes on disk for 200).
    fn put_sized(cache: &Cache, n: u64, payload: usize) {
        cache.put(Kind::Cell, &key(cache, n), &vec![n as u8; payload]);
    }

    /// An entry another bake wrote, which this cache's ledger does not
    /// know of.
    fn foreign_entry(dir: &Path, name: &str, bytes: usize) {
        let path = dir.join("cell/ff").join(name);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, vec![0u8; bytes]).unwrap();
    }

    #[test]
    fn eviction_lists_the_folder_only_when_its_ledger_is_old_or_the_limit_near() {
        let dir = tempfile::tempdir().unwrap();
        let cache = cache(dir.path(), 1000);
        put_sized(&cache, 1, 200);
        put_sized(&cache, 2, 200);
        assert_eq!(cache.evict().unwrap(), 0);
        let ledger = SizeLedger::read(dir.path()).expect("a listing writes the ledger");
        assert_eq!(ledger.bytes, 570);
        assert_eq!(folder_stats(dir.path()).unwrap().bytes, 570, "not an entry");

        // A recent ledger within the limit: no listing, so an entry it
        // does not know of stays although the folder is over its limit.
        foreign_entry(dir.path(), "one", 900);
        put_sized(&cache, 3, 200);
        assert_eq!(cache.evict().unwrap(), 0);
        assert_eq!(SizeLedger::read(dir.path()).unwrap().bytes, 855);
        assert_eq!(folder_stats(dir.path()).unwrap().bytes, 1755);

        // What this bake wrote takes the count past the limit: it lists.
        put_sized(&cache, 4, 200);
        assert!(cache.evict().unwrap() > 0);
        let stats = folder_stats(dir.path()).unwrap();
        assert!(stats.bytes <= 1000, "{stats:?}");
        assert_eq!(SizeLedger::read(dir.path()).unwrap().bytes, stats.bytes);

        // An hour-old count is listed again whatever it says.
        foreign_entry(dir.path(), "two", 900);
        let old = SystemTime::now() - size_ledger::TRUSTED_FOR - Duration::from_secs(5);
        SizeLedger::listed_now(0, old).write(dir.path()).unwrap();
        assert!(cache.evict().unwrap() > 0);
        assert!(folder_stats(dir.path()).unwrap().bytes <= 1000);

        // A damaged ledger is listed again too.
        foreign_entry(dir.path(), "three", 900);
        std::fs::write(dir.path().join(size_ledger::FILE_NAME), b"garbage").unwrap();
        assert!(cache.evict().unwrap() > 0);
        assert!(folder_stats(dir.path()).unwrap().bytes <= 1000);
    }
}
