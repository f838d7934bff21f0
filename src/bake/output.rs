//! From masks to results: the `<shadow>` content of every chunk (docs/contract.md §5)
//! and the JSON report (docs/contract.md §8).

use super::cached::{CacheReport, PhaseCounts};
use super::casters::CasterTable;
use super::{BakeResult, LightReport, Skipped};
use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{content_key, Cache, Fetched, Key, Kind};
use crate::files::{self, ResPaths};
use crate::formats::chunk::ChunkFile;
use crate::formats::chunk::InstanceKind;
use crate::formats::shadow_write::{self, ChunkShadows, InstanceShadow, ShadowSites};
use crate::formats::Section;
use crate::progress::{Counter, Phase, Progress};
use crate::scene::chunk_cache::{self, ParsedChunk};
use crate::scene::Scene;
use crate::{Error, Result};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The masks of one chunk, ready for `shadow_write`.
pub fn chunk_shadows(scene: &Scene, result: &BakeResult, chunk: usize) -> ChunkShadows {
    chunk_shadows_of(scene, &result.casters, chunk, |id| result.masks[id])
}

/// [`chunk_shadows`] with each caster's mask from `mask_of`.
fn chunk_shadows_of(
    scene: &Scene,
    casters: &CasterTable,
    chunk: usize,
    mask_of: impl Fn(usize) -> u32,
) -> ChunkShadows {
    let chunk = &scene.chunks[chunk];
    let mut instances: Vec<Option<InstanceShadow>> = vec![None; chunk.instance_elements];
    let mut speedtrees: Vec<Option<InstanceShadow>> = vec![None; chunk.speedtree_elements];
    for index in chunk.instances.clone() {
        let instance = &scene.instances[index];
        let Some(first) = casters.first_of_instance[index] else {
            continue;
        };
        let mut caster = first as usize;
        let mut shadow = InstanceShadow {
            mask: 0,
            render_sets: Vec::new(),
        };
        if instance.is_unmodelled() {
            // No render sets: the mask stands alone.
            shadow.mask = mask_of(caster);
        }
        for &model in instance.parts.iter().flatten() {
            for geometries in &scene.models[model].layout {
                let mut render_set = Vec::new();
                for &groups in geometries {
                    let masks: Vec<u32> = (caster..caster + groups).map(&mask_of).collect();
                    caster += groups;
                    shadow.mask |= masks.iter().fold(0, |a, b| a | b);
                    render_set.push(masks);
                }
                shadow.render_sets.push(render_set);
            }
        }
        let slots = match instance.kind {
            InstanceKind::SpeedTree => &mut speedtrees,
            InstanceKind::Model | InstanceKind::Shell => &mut instances,
        };
        if let Some(slot) = slots.get_mut(instance.index) {
            *slot = Some(shadow);
        }
    }
    let terrain = chunk
        .terrain
        .map(|block| mask_of(casters.of_block[block] as usize));
    ChunkShadows {
        instances,
        speedtrees,
        terrain,
    }
}

/// The masks the chunk files hold now, per caster id: per group where an
/// instance's `<shadow>` has its model's shape, else the instance mask for
/// every group; `None` where the chunk holds no `<shadow>` for the caster
/// (never baked), and for receiver-only instances. A chunk that cannot be
/// read back is an error naming it.
pub fn masks_from_chunks(scene: &Scene, casters: &CasterTable) -> Result<Vec<Option<u32>>> {
    let per_chunk: Vec<Vec<(u32, u32)>> = scene
        .chunks
        .par_iter()
        .map(|chunk| chunk_masks(scene, casters, chunk))
        .collect::<Result<_>>()?;
    let mut masks = vec![None; casters.casters.len()];
    for (id, mask) in per_chunk.into_iter().flatten() {
        masks[id as usize] = Some(mask);
    }
    Ok(masks)
}

/// One chunk file's masks now, as (caster id, mask) pairs.
fn chunk_masks(
    scene: &Scene,
    casters: &CasterTable,
    chunk: &crate::scene::Chunk,
) -> Result<Vec<(u32, u32)>> {
    let bytes = files::read_file(&chunk.file)?;
    let root =
        crate::formats::parse_data_section(&bytes).map_err(|e| e.in_source(&chunk.file, &bytes))?;
    old_masks(scene, casters, chunk, &bytes, &root)
}

/// The masks the `<shadow>`s of `root` (the chunk file `bytes`, parsed)
/// hold, as (caster id, mask) pairs; see [`masks_from_chunks`].
fn old_masks(
    scene: &Scene,
    casters: &CasterTable,
    chunk: &crate::scene::Chunk,
    bytes: &[u8],
    root: &Section,
) -> Result<Vec<(u32, u32)>> {
    let old =
        shadow_write::read_chunk_shadows(root).map_err(|e| e.in_source(&chunk.file, bytes))?;
    Ok(masks_held(scene, casters, chunk, &old))
}

/// The masks `old` (a chunk's `<shadow>`s, read back or as last written)
/// holds, as (caster id, mask) pairs; see [`masks_from_chunks`].
fn masks_held(
    scene: &Scene,
    casters: &CasterTable,
    chunk: &crate::scene::Chunk,
    old: &ChunkShadows,
) -> Vec<(u32, u32)> {
    let mut masks = Vec::new();
    for index in chunk.instances.clone() {
        let instance = &scene.instances[index];
        let written = match instance.kind {
            InstanceKind::SpeedTree => &old.speedtrees,
            InstanceKind::Model | InstanceKind::Shell => &old.instances,
        };
        let Some(Some(shadow)) = written.get(instance.index) else {
            continue;
        };
        if !instance.casts_shadow {
            continue;
        }
        let ids = casters.of_instance(scene, index);
        let groups: Vec<u32> = shadow.groups().collect();
        for (n, id) in ids.clone().enumerate() {
            let mask = if groups.len() == ids.len() {
                groups[n]
            } else {
                shadow.mask
            };
            masks.push((id, mask));
        }
    }
    if let (Some(block), Some(mask)) = (chunk.terrain, old.terrain) {
        masks.push((casters.of_block[block], mask));
    }
    masks
}

/// One chunk file's new content and where it goes (or, under `--out`,
/// the space's `space.settings`: [`space_settings_output`]).
#[derive(Debug)]
pub struct ChunkOutput {
    pub source: PathBuf,
    pub target: PathBuf,
    /// The target's new content, where it waits for [`write_outputs`].
    pub content: Content,
    /// The content key of what the target holds after writing, for the
    /// world's record a bake with a cache keeps (`None` without one: a big
    /// world's chunks are not hashed for nothing).
    pub key: Option<Key>,
    /// The target would hold different bytes after writing.
    pub changed: bool,
}

/// Where an output's new bytes wait to be written.
#[derive(Debug)]
pub enum Content {
    /// Not held: the target keeps its bytes (a chunk baked in place that
    /// stays as it is), or the bake writes nothing
    /// ([`OutputBytes::Dropped`]).
    None,
    /// In a temporary file beside the target, written as the
    /// output was prepared: a large world's rewritten chunks would fill
    /// memory.
    Staged(files::Staged),
    /// The target may not be replaced: why ([`write_outputs`] refuses the
    /// batch, naming every such target).
    Refused(String),
}

impl Content {
    /// `bytes` staged beside `target`, or why `target` is refused.
    fn staged(target: &Path, bytes: &[u8]) -> Result<Content> {
        Ok(match files::stage(target, bytes)? {
            files::Staging::Staged(staged) => Content::Staged(staged),
            files::Staging::Refused(why) => Content::Refused(why),
        })
    }
}

/// Where chunk outputs go, and whether their bytes are wanted.
#[derive(Debug, Clone, Copy)]
pub struct Destination<'a> {
    /// Under this folder, at the path relative to the chunk's res root;
    /// `None`: in place.
    pub out_dir: Option<&'a Path>,
    pub bytes: OutputBytes,
}

/// Whether an output's bytes are kept once compared with its target.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputBytes {
    /// Kept for writing: staged beside the target ([`Content::Staged`]).
    Kept,
    /// Dropped: the bake writes nothing (`--dry-run`, `--check`).
    Dropped,
}

/// Computes every chunk's new content, each staged beside its target as
/// it is made, before anything is replaced: a failure in one chunk
/// leaves every file untouched.
/// `out_dir`: write under it at the path relative to the chunk's res root
/// instead of in place.
///
/// Puts back, in `result` too, the bits this bake did not decide (lights
/// of other settings files, or left out by `--light`) from the chunk files'
/// existing `<shadow>`s, so a bake of some lights never clobbers the
/// others. Each chunk file is read and parsed once for both, as
/// [`Phase::Output`] of `progress` (seconds on a large world).
pub fn chunk_outputs(
    scene: &Scene,
    result: &mut BakeResult,
    res_paths: &ResPaths,
    out_dir: Option<&Path>,
    progress: &dyn Progress,
) -> Result<Vec<ChunkOutput>> {
    let to = Destination {
        out_dir,
        bytes: OutputBytes::Kept,
    };
    let (outputs, _) = chunk_outputs_cached(scene, result, res_paths, to, progress, None)?;
    Ok(outputs)
}

/// [`chunk_outputs`] with a cache: a chunk file whose bytes the cache
/// knows as written with `<shadow>`s (a [`Kind::Output`] entry) keeps
/// those bytes without being parsed when its new `<shadow>`s are the same
/// (writing a chunk's masks into bytes that hold them gives the same
/// bytes, docs/contract.md §5); every chunk prepared stores its new bytes'
/// entry. Returns the outputs and how many chunks were kept so (`reused`)
/// or prepared (`computed`).
pub fn chunk_outputs_cached(
    scene: &Scene,
    result: &mut BakeResult,
    res_paths: &ResPaths,
    to: Destination,
    progress: &dyn Progress,
    cache: Option<&Cache>,
) -> Result<(Vec<ChunkOutput>, PhaseCounts)> {
    let counter = Counter::begin(progress, Phase::Output, None, scene.chunks.len() as u64);
    let made: Vec<Made> = {
        let result = &*result;
        let output = ChunkOutputs {
            scene,
            result,
            res_paths,
            out_dir: to.out_dir,
            bytes: to.bytes,
            cache,
        };
        // Chunks are independent; collecting keeps their order, and the
        // first error in chunk order is the one reported, as a loop would.
        scene
            .chunks
            .par_iter()
            .enumerate()
            .map(|(index, chunk)| {
                let made = output.chunk(index, chunk);
                counter.add(1);
                made
            })
            .collect::<Result<_>>()?
    };
    counter.finish();
    let mut outputs = Vec::with_capacity(made.len());
    let mut counts = PhaseCounts::default();
    for made in made {
        for (id, mask) in made.kept {
            result.masks[id as usize] = mask;
        }
        match made.parsed {
            true => counts.computed += 1,
            false => counts.reused += 1,
        }
        counts.damaged += u64::from(made.damaged);
        outputs.push(made.output);
    }
    Ok((outputs, counts))
}

/// One chunk's output, the masks it holds where they differ from the
/// bake's (bits kept from the file), and whether it was parsed.
struct Made {
    output: ChunkOutput,
    kept: Vec<(u32, u32)>,
    parsed: bool,
    /// Its cache entry failed its check.
    damaged: bool,
}

/// What every chunk's output is made from.
struct ChunkOutputs<'o> {
    scene: &'o Scene,
    result: &'o BakeResult,
    res_paths: &'o ResPaths,
    out_dir: Option<&'o Path>,
    bytes: OutputBytes,
    cache: Option<&'o Cache>,
}

impl ChunkOutputs<'_> {
    fn chunk(&self, index: usize, chunk: &crate::scene::Chunk) -> Result<Made> {
        // Baked in place, a chunk loaded from files is known by the key of
        // the bytes the load read: one its entry proves unchanged is not
        // read again.
        let mut original = None;
        let content = match (chunk.file_key, self.out_dir) {
            (Some(key), None) => key,
            _ => content_key(original.insert(files::read_file(&chunk.file)?)),
        };
        // The key of `original` when it was read for it.
        let read_key = original.as_ref().map(|_| content);
        let mut damaged = false;
        if let Some(cache) = self.cache {
            let key = output_key(cache, &content);
            match cache.fetch(Kind::Output, &key) {
                Fetched::Value(value) if self.as_baked(index, &value) => {
                    return self.kept_as_is(chunk, content, Vec::new(), &original);
                }
                Fetched::Value(value) => match decode_shadows(&value) {
                    Some(written) => {
                        let unchanged =
                            self.unchanged(index, chunk, content, &written, &original)?;
                        if let Some(made) = unchanged {
                            return Ok(made);
                        }
                    }
                    None => {
                        cache.reject(Kind::Output, &key);
                        damaged = true;
                    }
                },
                Fetched::Damaged => damaged = true,
                Fetched::Absent => {}
            }
        }
        let original = match original {
            Some(bytes) => bytes,
            None => files::read_file(&chunk.file)?,
        };
        let Rewritten {
            kept,
            shadows,
            bytes,
            written,
        } = self.rewrite(index, chunk, &original, read_key)?;
        let key = self.cache.map(|_| content_key(&bytes));
        // New bytes a bake does not write (`--dry-run`, `--check`) are in
        // no file a later bake reads: their entries would only fill the
        // cache.
        let kept_by_target = bytes == original || self.bytes == OutputBytes::Kept;
        if let (Some(cache), Some(key)) = (self.cache.filter(|_| kept_by_target), key) {
            cache.put(
                Kind::Output,
                &output_key(cache, &key),
                &encode_shadows(&shadows),
            );
            if bytes != original {
                self.keep_items(cache, chunk, (&content, &key), written);
                // Written in place, the old bytes are gone: so is any use
                // of their entry.
                if self.out_dir.is_none() {
                    cache.forget(Kind::Chunk, &chunk_cache::key(cache, &content));
                }
            }
        }
        let output = self.output(chunk, &original, bytes, key)?;
        Ok(Made {
            output,
            kept,
            parsed: true,
            damaged,
        })
    }

    /// The chunk's new `<shadow>`s (with the bits kept from the file) and
    /// bytes, and what a later load reads of those bytes. Written at the
    /// places the load found when `original` is the bytes it read and
    /// holds no bit to keep; else parsed. `read_key`: the content key of
    /// `original`, when known.
    fn rewrite(
        &self,
        index: usize,
        chunk: &crate::scene::Chunk,
        original: &[u8],
        read_key: Option<Key>,
    ) -> Result<Rewritten> {
        let keep = !self.result.baked_bits;
        let loaded = || chunk.file_key == Some(read_key.unwrap_or_else(|| content_key(original)));
        let sites = chunk
            .sites
            .as_ref()
            .filter(|sites| sites.held().is_some_and(|held| held & keep == 0) && loaded());
        if let Some(sites) = sites {
            let (kept, shadows) = self.shadows(index, || Ok(Vec::new()))?;
            let (bytes, moved) = sites
                .write(original, &shadows)
                .map_err(|e| e.in_file(&chunk.file))?;
            return Ok(Rewritten {
                kept,
                shadows,
                bytes,
                written: Written::AtSites(moved),
            });
        }
        let root = crate::formats::parse_data_section(original)
            .map_err(|e| e.in_source(&chunk.file, original))?;
        let old = || old_masks(self.scene, &self.result.casters, chunk, original, &root);
        let (kept, shadows) = self.shadows(index, old)?;
        let (bytes, sites) = shadow_write::write_shadows_parsed(original, &root, &shadows)
            .map_err(|e| e.in_file(&chunk.file))?;
        // Only a cache keeps them (`keep_items`).
        let items = self
            .cache
            .and_then(|_| crate::formats::chunk::parse(&root).ok());
        Ok(Rewritten {
            kept,
            shadows,
            bytes,
            written: Written::Parsed(items.map(Box::new), sites),
        })
    }

    /// Stores the chunk's items under the content key `key` of its new
    /// bytes: writing masks changes neither them nor the chunk as an input
    /// (`scene::chunk_cache`), so the next load reads them back instead of
    /// parsing what this bake wrote. Written at places, the items are those
    /// of the old bytes' entry (`content`).
    fn keep_items(
        &self,
        cache: &Cache,
        chunk: &crate::scene::Chunk,
        (content, key): (&Key, &Key),
        written: Written,
    ) {
        let parsed = match written {
            Written::AtSites(sites) => cached_chunk(cache, content).map(|old| ParsedChunk {
                sites: Some(sites),
                ..old
            }),
            Written::Parsed(items, sites) => {
                let inputs = &self.scene.inputs;
                let at = inputs.binary_search_by(|f| f.path.as_path().cmp(&chunk.file));
                items.zip(at.ok()).map(|(items, at)| ParsedChunk {
                    chunk: *items,
                    canonical: inputs[at].digest,
                    sites,
                })
            }
        };
        if let Some(parsed) = parsed {
            cache.put(
                Kind::Chunk,
                &chunk_cache::key(cache, key),
                &chunk_cache::encode(&parsed),
            );
        }
    }

    /// The chunk's output when its bytes (of content key `content`; read
    /// into `original` unless baked in place) were written with `written`
    /// and its new `<shadow>`s are the same: those bytes, not parsed;
    /// `None` when they differ.
    fn unchanged(
        &self,
        index: usize,
        chunk: &crate::scene::Chunk,
        content: Key,
        written: &ChunkShadows,
        original: &Option<Vec<u8>>,
    ) -> Result<Option<Made>> {
        let old = || Ok(masks_held(self.scene, &self.result.casters, chunk, written));
        let (kept, shadows) = self.shadows(index, old)?;
        if shadows != *written {
            return Ok(None);
        }
        self.kept_as_is(chunk, content, kept, original).map(Some)
    }

    /// Whether the chunk's bytes were written with exactly the bake's
    /// masks (`value`, their entry, as [`encode_shadows`] wrote it): then
    /// they hold no bit of another light to keep and stay as they are,
    /// found without decoding the entry (one encoding per shadows).
    fn as_baked(&self, index: usize, value: &[u8]) -> bool {
        let result = self.result;
        encode_shadows_of(self.scene, &result.casters, index, |id| result.masks[id]) == value
    }

    /// The output of a chunk whose bytes (of content key `content`; read
    /// into `original` unless baked in place) stay as they are.
    fn kept_as_is(
        &self,
        chunk: &crate::scene::Chunk,
        content: Key,
        kept: Vec<(u32, u32)>,
        original: &Option<Vec<u8>>,
    ) -> Result<Made> {
        let output = match original {
            Some(bytes) => self.output(chunk, bytes, bytes.clone(), Some(content))?,
            None => ChunkOutput {
                source: chunk.file.clone(),
                target: chunk.file.clone(),
                content: Content::None,
                key: Some(content),
                changed: false,
            },
        };
        Ok(Made {
            output,
            kept,
            parsed: false,
            damaged: false,
        })
    }

    /// The chunk's new `<shadow>`s: the bake's bits, the others of each
    /// mask from `old` (the masks the file holds).
    fn shadows(
        &self,
        index: usize,
        old: impl FnOnce() -> Result<Vec<(u32, u32)>>,
    ) -> Result<(Vec<(u32, u32)>, ChunkShadows)> {
        let result = self.result;
        let keep = !result.baked_bits;
        let mut kept: Vec<(u32, u32)> = Vec::new();
        if keep != 0 {
            for (id, old) in old()? {
                let mask = result.masks[id as usize] | (old & keep);
                if mask != result.masks[id as usize] {
                    kept.push((id, mask));
                }
            }
        }
        kept.sort_unstable();
        let mask_of = |id: usize| match kept.binary_search_by_key(&(id as u32), |k| k.0) {
            Ok(at) => kept[at].1,
            Err(_) => result.masks[id],
        };
        let shadows = chunk_shadows_of(self.scene, &result.casters, index, mask_of);
        Ok((kept, shadows))
    }

    /// Where `bytes` (the chunk's new content; `original` its file's) go,
    /// and whether they change the target.
    fn output(
        &self,
        chunk: &crate::scene::Chunk,
        original: &[u8],
        bytes: Vec<u8>,
        key: Option<Key>,
    ) -> Result<ChunkOutput> {
        let target = match self.out_dir {
            None => chunk.file.clone(),
            Some(dir) => {
                let (_, relative) = self.res_paths.relative(&chunk.file).ok_or_else(|| {
                    Error::invalid(
                        &chunk.file,
                        "is not under any res path, so it has no place under --out",
                    )
                })?;
                dir.join(relative)
            }
        };
        let changed = match self.out_dir {
            None => bytes != original,
            Some(_) => files::read_file(&target)
                .map(|old| old != bytes)
                .unwrap_or(true),
        };
        // Only what changes a target is staged: bytes that stay are not
        // held.
        let content = match self.bytes == OutputBytes::Kept && changed {
            true => Content::staged(&target, &bytes)?,
            false => Content::None,
        };
        Ok(ChunkOutput {
            source: chunk.file.clone(),
            target,
            content,
            key,
            changed,
        })
    }
}

/// A chunk's new `<shadow>`s and bytes, with the bits kept from the file.
struct Rewritten {
    kept: Vec<(u32, u32)>,
    shadows: ChunkShadows,
    bytes: Vec<u8>,
    written: Written,
}

/// What a later load reads of a chunk's new bytes, as its output made
/// them.
enum Written {
    /// Written at the places the load found: the places in the new bytes.
    AtSites(ShadowSites),
    /// Parsed: the items, and the places in the new bytes (text XML).
    Parsed(Option<Box<ChunkFile>>, Option<ShadowSites>),
}

/// The entry of the chunk file whose content key is `content`, if the
/// cache holds a sound one.
fn cached_chunk(cache: &Cache, content: &Key) -> Option<ParsedChunk> {
    chunk_cache::decode(&cache.get(Kind::Chunk, &chunk_cache::key(cache, content))?)
}

/// The key of the [`Kind::Output`] entry of chunk bytes whose content
/// key is `content`.
fn output_key(cache: &Cache, content: &Key) -> Key {
    cache.hasher(Kind::Output).key(content).finish()
}

fn encode_shadows(shadows: &ChunkShadows) -> Vec<u8> {
    let mut e = Encoder::new();
    for items in [&shadows.instances, &shadows.speedtrees] {
        encode_instances(&mut e, items);
    }
    match shadows.terrain {
        Some(mask) => e.u8(1).var(u64::from(mask)),
        None => e.u8(0),
    };
    e.into_bytes()
}

/// `encode_shadows(&chunk_shadows_of(..))`, written straight from the
/// scene: every chunk of a cached bake is compared with its entry this
/// way, and building each instance's nested mask lists first was most of
/// that comparison's time.
fn encode_shadows_of(
    scene: &Scene,
    casters: &CasterTable,
    chunk: usize,
    mask_of: impl Fn(usize) -> u32,
) -> Vec<u8> {
    let chunk = &scene.chunks[chunk];
    // Which instance fills each element's slot, as `chunk_shadows_of`
    // fills them (a later one in the same slot wins).
    let mut instances: Vec<Option<usize>> = vec![None; chunk.instance_elements];
    let mut speedtrees: Vec<Option<usize>> = vec![None; chunk.speedtree_elements];
    for index in chunk.instances.clone() {
        let instance = &scene.instances[index];
        if casters.first_of_instance[index].is_none() {
            continue;
        }
        let slots = match instance.kind {
            InstanceKind::SpeedTree => &mut speedtrees,
            InstanceKind::Model | InstanceKind::Shell => &mut instances,
        };
        if let Some(slot) = slots.get_mut(instance.index) {
            *slot = Some(index);
        }
    }
    let mut e = Encoder::new();
    for slots in [&instances, &speedtrees] {
        e.var(slots.len() as u64);
        for slot in slots {
            match slot {
                Some(index) => encode_instance_shadow(&mut e, scene, casters, *index, &mask_of),
                None => {
                    e.u8(0);
                }
            }
        }
    }
    match chunk.terrain {
        Some(block) => e
            .u8(1)
            .var(u64::from(mask_of(casters.of_block[block] as usize))),
        None => e.u8(0),
    };
    e.into_bytes()
}

/// One placed instance's `<shadow>` as [`encode_instances`] writes it.
fn encode_instance_shadow(
    e: &mut Encoder,
    scene: &Scene,
    casters: &CasterTable,
    index: usize,
    mask_of: &impl Fn(usize) -> u32,
) {
    let instance = &scene.instances[index];
    let first = casters.first_of_instance[index].map_or(0, |f| f as usize);
    let layouts = || {
        instance
            .parts
            .iter()
            .flatten()
            .flat_map(|&model| scene.models[model].layout.iter())
    };
    let groups: usize = layouts().flatten().sum();
    let mask = if instance.is_unmodelled() {
        mask_of(first)
    } else {
        (first..first + groups).fold(0, |bits, caster| bits | mask_of(caster))
    };
    e.u8(1).var(u64::from(mask)).var(layouts().count() as u64);
    let mut caster = first;
    for geometries in layouts() {
        e.var(geometries.len() as u64);
        for &count in geometries {
            e.var(count as u64);
            for id in caster..caster + count {
                e.var(u64::from(mask_of(id)));
            }
            caster += count;
        }
    }
}

fn decode_shadows(bytes: &[u8]) -> Option<ChunkShadows> {
    let mut d = Decoder::new(bytes);
    let instances = decode_instances(&mut d)?;
    let speedtrees = decode_instances(&mut d)?;
    let terrain = match d.u8().ok()? {
        0 => None,
        1 => Some(var_mask(&mut d)?),
        _ => return None,
    };
    d.is_done().then_some(ChunkShadows {
        instances,
        speedtrees,
        terrain,
    })
}

/// One list of items' `<shadow>`s (`None`: left as it is), as
/// [`encode_shadows`] writes it.
fn encode_instances(e: &mut Encoder, items: &[Option<InstanceShadow>]) {
    e.var(items.len() as u64);
    for instance in items {
        let Some(instance) = instance else {
            e.u8(0);
            continue;
        };
        e.u8(1)
            .var(u64::from(instance.mask))
            .var(instance.render_sets.len() as u64);
        for geometries in &instance.render_sets {
            e.var(geometries.len() as u64);
            for groups in geometries {
                e.var(groups.len() as u64);
                for &mask in groups {
                    e.var(u64::from(mask));
                }
            }
        }
    }
}

fn decode_instances(d: &mut Decoder) -> Option<Vec<Option<InstanceShadow>>> {
    let mut items = Vec::new();
    for _ in 0..d.len(1).ok()? {
        items.push(match d.u8().ok()? {
            0 => None,
            1 => {
                let mask = var_mask(d)?;
                let mut render_sets = Vec::new();
                for _ in 0..d.len(1).ok()? {
                    let mut geometries = Vec::new();
                    for _ in 0..d.len(1).ok()? {
                        let groups = (0..d.len(1).ok()?)
                            .map(|_| var_mask(d))
                            .collect::<Option<Vec<u32>>>()?;
                        geometries.push(groups);
                    }
                    render_sets.push(geometries);
                }
                Some(InstanceShadow { mask, render_sets })
            }
            _ => return None,
        });
    }
    Some(items)
}

/// A mask as [`encode_shadows`] writes it (LEB128).
fn var_mask(d: &mut Decoder) -> Option<u32> {
    u32::try_from(d.var().ok()?).ok()
}

/// The space's `space.settings` copied under `out_dir` beside the chunks
/// (the same bytes, at its path relative to its res root), so the copy is
/// a res root of the space: with the original root after it in the res
/// paths, it is found first and its chunks are the ones read. Staged
/// beside its target when it changes it, as the chunks are.
pub fn space_settings_output(
    scene: &Scene,
    res_paths: &ResPaths,
    out_dir: &Path,
) -> Result<ChunkOutput> {
    let source = scene.space_dir.join("space.settings");
    let bytes = files::read_file(&source)?;
    let (_, relative) = res_paths.relative(&source).ok_or_else(|| {
        Error::invalid(
            &source,
            "is not under any res path, so it has no place under --out",
        )
    })?;
    let target = out_dir.join(relative);
    let changed = files::read_file(&target).map_or(true, |old| old != bytes);
    let content = match changed {
        true => Content::staged(&target, &bytes)?,
        false => Content::None,
    };
    Ok(ChunkOutput {
        source,
        target,
        key: Some(content_key(&bytes)),
        content,
        changed,
    })
}

/// Writes the outputs that change something, as one batch
/// ([`files::commit_staged`]): a target refused when its output was
/// prepared (a read-only chunk) fails the batch, naming every such file,
/// before anything is replaced; every new content is in a synced
/// temporary file since its output was made, each rename counted in
/// [`Phase::Writing`] of `progress`, and stale temporary files of killed
/// runs are removed beside every output, unchanged ones too. Returns how
/// many files were written.
pub fn write_outputs<'a>(
    outputs: impl IntoIterator<Item = &'a ChunkOutput>,
    progress: &dyn Progress,
) -> Result<usize> {
    let (changed, unchanged): (Vec<&ChunkOutput>, Vec<&ChunkOutput>) =
        outputs.into_iter().partition(|o| o.changed);
    let (mut batch, mut refused) = (Vec::new(), Vec::new());
    for output in &changed {
        match &output.content {
            Content::Staged(staged) => batch.push(staged),
            Content::Refused(why) => refused.push((output.target.clone(), why.clone())),
            Content::None => {}
        }
    }
    if !refused.is_empty() {
        batch.iter().for_each(|staged| staged.discard());
        return Err(Error::Refused { files: refused });
    }
    let unchanged: Vec<&Path> = unchanged.iter().map(|o| o.target.as_path()).collect();
    let counter = Counter::begin(progress, Phase::Writing, None, batch.len() as u64);
    files::commit_staged(&batch, &unchanged, &mut || counter.add(1))?;
    counter.finish();
    Ok(batch.len())
}

/// The version of the report's layout: raised when a field changes
/// meaning or goes away (new fields may appear without it).
pub const REPORT_VERSION: u32 = 3;

/// The `--report` JSON (docs/contract.md §8), written as it is made: its
/// casters come chunk by chunk ([`CasterEntries`]), so a world of
/// millions of instances never holds its report whole.
#[derive(Serialize)]
pub struct Report<'a> {
    /// [`REPORT_VERSION`].
    pub report_version: u32,
    /// The shadowcull version that wrote it.
    pub tool_version: &'static str,
    /// Chunk files written (none for `--dry-run` and `--check`).
    pub files_written: Vec<String>,
    /// Chunk files whose bytes the bake changes (or would change).
    pub files_changed: Vec<String>,
    pub lights: Vec<LightReport>,
    pub casters: CasterEntries<'a>,
    pub skipped: Vec<Skipped>,
    /// What a bake with a cache reused and computed, per phase and light.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cache: Option<CacheReport>,
}

#[derive(Debug, Clone, Serialize, PartialEq, Eq)]
pub struct CasterEntry {
    pub chunk: String,
    /// `model` (a `<model>` or `<shell>` instance), `speedtree` or
    /// `terrain`.
    pub kind: &'static str,
    /// `model` or `shell`: the instance's element tag.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub element: Option<&'static str>,
    /// Position among the chunk's `<model>`/`<shell>` elements, or among
    /// its `<speedtree>` elements for a speedtree.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub index: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resources: Option<Vec<String>>,
    /// A speedtree's `.spt`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spt: Option<String>,
    /// A speedtree's proxy: its `.model`, or `parametric`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub proxy: Option<String>,
    pub mask: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub groups: Option<Vec<u32>>,
    /// `castsShadow` false: listed with mask 0.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub receiver_only: bool,
    /// A speedtree without a proxy: every baked bit set, no `groups`.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub unmodelled: bool,
}

pub fn report<'a>(scene: &'a Scene, result: &'a BakeResult) -> Report<'a> {
    Report {
        report_version: REPORT_VERSION,
        tool_version: env!("CARGO_PKG_VERSION"),
        files_written: Vec::new(),
        files_changed: Vec::new(),
        lights: result.lights.clone(),
        casters: CasterEntries { scene, result },
        skipped: result.skipped.clone(),
        cache: result.cache.clone(),
    }
}

/// The report's casters, sorted by chunk, then kind, then index: made
/// chunk by chunk in that order (chunks are sorted by name; a chunk's
/// `<model>`/`<shell>` instances come in document order, then its
/// speedtrees, then its terrain block).
#[derive(Clone, Copy)]
pub struct CasterEntries<'a> {
    scene: &'a Scene,
    result: &'a BakeResult,
}

impl CasterEntries<'_> {
    /// Every entry, in report order.
    pub fn iter(&self) -> impl Iterator<Item = CasterEntry> + '_ {
        (0..self.scene.chunks.len()).flat_map(|index| self.of_chunk(index))
    }

    /// The entries of chunk `index`.
    fn of_chunk(&self, index: usize) -> Vec<CasterEntry> {
        let (scene, chunk) = (self.scene, &self.scene.chunks[index]);
        let shadows = chunk_shadows(scene, self.result, index);
        let mut casters = Vec::new();
        for instance in &scene.instances[chunk.instances.clone()] {
            let written = match instance.kind {
                InstanceKind::SpeedTree => &shadows.speedtrees,
                InstanceKind::Model | InstanceKind::Shell => &shadows.instances,
            };
            let Some(Some(shadow)) = written.get(instance.index) else {
                continue;
            };
            casters.push(caster_entry(scene, &chunk.name, instance, shadow));
        }
        if let Some(mask) = shadows.terrain {
            casters.push(CasterEntry {
                chunk: chunk.name.clone(),
                kind: "terrain",
                element: None,
                index: None,
                resources: None,
                spt: None,
                proxy: None,
                mask,
                groups: None,
                receiver_only: false,
                unmodelled: false,
            });
        }
        casters
    }
}

impl Serialize for CasterEntries<'_> {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_seq(self.iter())
    }
}

/// The report's entry of a model, shell or speedtree that was written.
fn caster_entry(
    scene: &Scene,
    chunk: &str,
    instance: &crate::scene::Instance,
    shadow: &InstanceShadow,
) -> CasterEntry {
    let groups = Some(shadow.groups().collect());
    let entry = CasterEntry {
        chunk: chunk.to_string(),
        kind: "model",
        element: Some(instance.kind.tag()),
        index: Some(instance.index),
        resources: None,
        spt: None,
        proxy: None,
        mask: shadow.mask,
        groups,
        receiver_only: !instance.casts_shadow,
        unmodelled: false,
    };
    if instance.kind != InstanceKind::SpeedTree {
        let resources = instance.resources.iter().map(|r| r.trim().to_string());
        return CasterEntry {
            resources: Some(resources.collect()),
            ..entry
        };
    }
    let proxy = instance.parts.iter().flatten().next().map(|&m| {
        let model = &scene.models[m];
        if model.parametric {
            "parametric".to_string()
        } else {
            model.resource.clone()
        }
    });
    CasterEntry {
        kind: "speedtree",
        element: None,
        spt: Some(crate::scene::items::spt_of(instance).to_string()),
        unmodelled: proxy.is_none(),
        groups: proxy.as_ref().and(entry.groups.clone()),
        proxy,
        ..entry
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_shadows_read_back_from_their_entry() {
        let shadows = ChunkShadows {
            instances: vec![
                None,
                Some(InstanceShadow::from_groups(vec![
                    vec![vec![3, 0, 1 << 31]],
                    vec![],
                ])),
                Some(InstanceShadow::from_groups(Vec::new())),
            ],
            speedtrees: vec![
                Some(InstanceShadow {
                    mask: 7,
                    render_sets: Vec::new(),
                }),
                None,
                Some(InstanceShadow::from_groups(vec![vec![vec![1, 2]]])),
            ],
            terrain: Some(5),
        };
        let bytes = encode_shadows(&shadows);
        assert_eq!(decode_shadows(&bytes), Some(shadows.clone()));
        for cut in 0..bytes.len() {
            assert_eq!(decode_shadows(&bytes[..cut]), None, "cut at {cut}");
        }
        let none = ChunkShadows::default();
        assert_eq!(decode_shadows(&encode_shadows(&none)), Some(none));
    }

    /// Straight from the scene, the bytes of the masks built first: every
    /// chunk of the village under seeded masks, one of its instances made
    /// an unmodelled speedtree and one left out.
    #[test]
    fn shadows_encoded_from_the_scene_are_those_of_the_built_masks() {
        use crate::files::ResPaths;
        use crate::scene::{load_scene, LoadConfig};
        use std::sync::Arc;
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/worlds/village");
        let mut scene = load_scene(&LoadConfig {
            res_paths: ResPaths::new(vec![root]),
            space: "spaces/village".into(),
            speedtrees: Default::default(),
        })
        .expect("the village fixture loads");
        let tree = scene.chunks[0].instances.start;
        scene.instances[tree].kind = InstanceKind::SpeedTree;
        scene.instances[tree].index = 0;
        scene.instances[tree].parts = Arc::from([]);
        scene.chunks[0].speedtree_elements = 2;
        scene.instances[tree + 1].parts = Arc::from([None]);
        let casters = CasterTable::new(&scene);
        assert!(casters.first_of_instance[tree + 1].is_none());
        let mut rng = crate::rng::Rng::new(0x5ad0);
        let masks: Vec<u32> = (0..casters.casters.len())
            .map(|_| rng.next_u64() as u32 >> rng.below(32))
            .collect();
        let mask_of = |id: usize| masks[id];
        let mut render_sets = 0;
        for chunk in 0..scene.chunks.len() {
            let built = chunk_shadows_of(&scene, &casters, chunk, mask_of);
            render_sets += built
                .instances
                .iter()
                .flatten()
                .map(|s| s.render_sets.len())
                .sum::<usize>();
            assert_eq!(
                encode_shadows_of(&scene, &casters, chunk, mask_of),
                encode_shadows(&built),
                "chunk {chunk}"
            );
        }
        assert!(render_sets > scene.chunks.len(), "models with render sets");
    }
}
