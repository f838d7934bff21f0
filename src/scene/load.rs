//! Builds a [`Scene`] from a space on disk: parses every chunk, loads each
//! distinct model once, reads the terrain blocks. Bad parts of a world are
//! left out and listed in `Scene::problems` (so `inspect` can list every
//! missing resource, not just the first); only a world that cannot be read
//! at all (no settings, no chunks) is an error. Stray placements (world
//! boxes outside the space's `SpaceRegion`) are found after the terrain is
//! read, since how high an instance may reach follows the terrain.
//! Speedtrees take the proxy the settings give their `.spt`: a `.model`
//! loaded like any other, or a parametric model built once per shape.

use super::chunk_cache::{self, ParsedChunk};
use super::items::ItemCount;
use super::terrain::HeightRange;
use super::terrain_cache::{self, HeightRanges};
use super::{Chunk, Group, InputFile, Instance, Model, Problem, Scene, SpaceRegion, TerrainBlock};
use crate::cache::{content_key, Cache, Fetched, Key, Kind, KnownFiles};
use crate::digest::Digest;
use crate::error::{Error, Result};
use crate::files::{self, ResPaths};
use crate::formats::bake_settings::{BakeSettings, ParametricTree, Proxy, SpeedTreeProxies};
use crate::formats::chunk::{self, ChunkFile, InstanceKind};
use crate::formats::chunk_scan;
use crate::formats::shadow_write::ShadowSites;
use crate::formats::space_settings;
use crate::formats::{
    self, binsection, model, primitives, shadow_write, terrain as terrain_format, visual,
};
use crate::progress::{Counter, Phase, Progress};
use glam::{DMat4, DVec3};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Where the world is, and the proxies of its speedtrees.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    pub res_paths: ResPaths,
    /// Space folder as a resource name, e.g. `spaces/arctic`.
    pub space: String,
    /// `<speedtrees>` of the settings file: without a rule that matches
    /// its `.spt`, a speedtree is an unmodelled caster.
    pub speedtrees: SpeedTreeProxies,
}

impl LoadConfig {
    /// The world a settings file names, with its speedtree proxies.
    pub fn from_settings(settings: &BakeSettings) -> LoadConfig {
        LoadConfig {
            res_paths: ResPaths::new(settings.res_paths.clone()),
            space: settings.space.clone(),
            speedtrees: settings.speedtrees.clone(),
        }
    }
}

/// Below this |determinant| a placement has collapsed to a plane, line or
/// point: it casts nothing and its inverse does not exist.
const SINGULAR_DETERMINANT: f64 = 1e-12;

/// Every file the load read, with its content hash, so a distributed bake
/// can prove its shards saw the same inputs (`bake::shard`). Filled from
/// the loading threads; sorted when the scene is made.
#[derive(Default)]
struct ReadLog(Mutex<Vec<InputFile>>);

impl ReadLog {
    fn record(&self, path: &Path, bytes: &[u8]) {
        self.record_digest(path, Digest::of(bytes));
    }

    fn record_digest(&self, path: &Path, digest: Digest) {
        let file = InputFile {
            path: path.to_path_buf(),
            digest,
        };
        self.0.lock().unwrap_or_else(|e| e.into_inner()).push(file);
    }

    fn into_sorted(self) -> Vec<InputFile> {
        let mut files = self.0.into_inner().unwrap_or_else(|e| e.into_inner());
        files.sort();
        files.dedup();
        files
    }
}

pub fn load_scene(config: &LoadConfig) -> Result<Scene> {
    load_scene_with(config, &crate::progress::Silent)
}

/// [`load_scene`], telling `progress` how many chunks, models and terrain
/// blocks are done.
pub fn load_scene_with(config: &LoadConfig, progress: &dyn Progress) -> Result<Scene> {
    load_scene_cached(config, progress, None, &KnownFiles::default())
}

/// [`load_scene_with`], reading the items of chunks parsed before from
/// `cache` (and storing the others'): the same scene, without parsing
/// the XML of unchanged chunks. A chunk file `known` vouches for is not
/// even read when the cache holds its items.
pub fn load_scene_cached(
    config: &LoadConfig,
    progress: &dyn Progress,
    cache: Option<&Cache>,
    known: &KnownFiles,
) -> Result<Scene> {
    let log = ReadLog::default();
    let mut loader = Loader {
        config,
        progress,
        cache,
        known,
        log: &log,
        problems: Vec::new(),
    };
    let (space_dir, settings) = loader.read_space_settings()?;
    let parsed = loader.parse_chunk_files(&space_dir, &settings)?;
    let by_name = loader.keep_chunks_by_name(parsed, &space_dir, &settings)?;
    // The terrain is decoded while the models load and the chunks are
    // placed, which leave a core idle at times.
    let reading = TerrainReading {
        config,
        cache,
        log: &log,
        progress,
        space_dir: &space_dir,
        chunk_size: settings.chunk_size,
    };
    let jobs = terrain_jobs(&by_name, settings.chunk_size);
    let ((models, placed), blocks) = rayon::join(
        || {
            let (models, model_names) = loader.load_models(&by_name);
            (
                models,
                loader.place_chunks(by_name, &settings, &model_names),
            )
        },
        || reading.decode(jobs),
    );
    let Placed {
        mut chunks,
        mut instances,
        items,
    } = placed;
    let region = SpaceRegion::of(&settings);
    let terrain = loader.keep_terrain_blocks(blocks, &region, &mut chunks);
    // Instances are held to the terrain's heights, known only now.
    let region = region.around_terrain(&terrain);
    let Loader { mut problems, .. } = loader;
    drop_strays(&mut chunks, &mut instances, &models, &region, &mut problems);
    problems.sort();
    Ok(Scene {
        space_dir,
        settings,
        chunks,
        models,
        instances,
        terrain,
        items,
        problems,
        inputs: log.into_sorted(),
    })
}

/// What every step of a load shares: where the world is, whom to tell of
/// progress, the files read so far and the problems found so far.
struct Loader<'a> {
    config: &'a LoadConfig,
    progress: &'a dyn Progress,
    /// Where parsed chunks are kept between bakes.
    cache: Option<&'a Cache>,
    /// Files whose content keys a record vouches for.
    known: &'a KnownFiles,
    log: &'a ReadLog,
    problems: Vec<Problem>,
}

/// The chunks in name order with their instances placed in the world.
struct Placed {
    chunks: Vec<Chunk>,
    instances: Vec<Instance>,
    items: Vec<ItemCount>,
}

/// Where a model the chunks need comes from.
enum ModelSource {
    /// A `.model` resource; `referenced_by` is the first chunk that
    /// places it (by a `<resource>` or a speedtree's proxy).
    Resource { referenced_by: PathBuf },
    /// A parametric speedtree proxy, built rather than read.
    Parametric(ParametricTree),
}

/// How much of the world uses one model: what its loss costs.
#[derive(Default)]
struct Usage {
    placements: usize,
    chunks: BTreeSet<String>,
}

impl Usage {
    /// `3 placements in 2 chunks lose it (left out of the bake)`.
    fn loss(&self) -> String {
        let placements = self.placements;
        let chunks = self.chunks.len();
        format!(
            "{placements} placement{} in {chunks} chunk{} lose{} it (left out of the bake)",
            if placements == 1 { "" } else { "s" },
            if chunks == 1 { "" } else { "s" },
            if placements == 1 { "s" } else { "" },
        )
    }
}

/// How many of a chunk's instances place each resource (normalised
/// names). Elements naming the same resources share one list: counted by
/// list, then each list's names added once.
fn resource_placements(file: &ChunkFile) -> BTreeMap<String, usize> {
    let mut lists: HashMap<usize, (&[String], usize)> = HashMap::new();
    for instance in &file.instances {
        let list = &*instance.resources;
        lists.entry(list.as_ptr() as usize).or_insert((list, 0)).1 += 1;
    }
    let mut resources: BTreeMap<String, usize> = BTreeMap::new();
    for (list, placements) in lists.into_values() {
        for resource in list {
            let name = files::normalised(resource);
            match resources.get_mut(&*name) {
                Some(count) => *count += placements,
                None => {
                    resources.insert(name.into_owned(), placements);
                }
            }
        }
    }
    resources
}

/// The model name of a speedtree's proxy (the `.model` resource, or the
/// parametric shape's name) and, for a parametric proxy, its shape;
/// `None` when no rule matches its `.spt`.
fn proxy_model(proxies: &SpeedTreeProxies, spt: &str) -> Option<(String, Option<ParametricTree>)> {
    match proxies.proxy_for(spt)? {
        Proxy::Model(resource) => Some((files::normalise(resource), None)),
        Proxy::Parametric(tree) => Some((tree.name(), Some(*tree))),
    }
}

/// A chunk's terrain block to read: the chunk's index and file, the
/// block's resource name and the chunk's transform.
struct TerrainJob {
    chunk: usize,
    chunk_path: PathBuf,
    resource: String,
    transform: DMat4,
}

/// What decoding the terrain blocks reads, apart from the loader (it runs
/// beside the models' load and the placing).
struct TerrainReading<'a> {
    config: &'a LoadConfig,
    /// Where blocks' height ranges are kept between bakes.
    cache: Option<&'a Cache>,
    log: &'a ReadLog,
    progress: &'a dyn Progress,
    space_dir: &'a Path,
    chunk_size: f64,
}

impl TerrainReading<'_> {
    /// Each job's block, read and decoded in parallel, in job order.
    fn decode(&self, jobs: Vec<TerrainJob>) -> Vec<(usize, Result<TerrainBlock>)> {
        let (res_paths, log) = (&self.config.res_paths, self.log);
        let counter = Counter::begin(self.progress, Phase::Terrain, None, jobs.len() as u64);
        let ranges = self.cache.map(|cache| self.stored_ranges(cache));
        let blocks: Vec<(usize, Result<TerrainBlock>)> = jobs
            .into_par_iter()
            .map(|job| {
                let folder = chunk_folder(&self.config.space, self.space_dir, &job.chunk_path);
                let block = load_terrain(
                    res_paths,
                    log,
                    ranges.as_ref(),
                    &job,
                    &folder,
                    self.chunk_size,
                );
                counter.add(1);
                (job.chunk, block)
            })
            .collect();
        counter.finish();
        if let (Some(cache), Some(stored)) = (self.cache, &ranges) {
            self.store_ranges(cache, stored, &blocks);
        }
        blocks
    }

    /// The height ranges the cache holds for this space's blocks.
    fn stored_ranges(&self, cache: &Cache) -> HeightRanges {
        let key = terrain_cache::key(cache, self.space_dir);
        match cache.fetch(Kind::Terrain, &key) {
            Fetched::Value(value) => terrain_cache::decode(&value).unwrap_or_else(|| {
                cache.reject(Kind::Terrain, &key);
                HeightRanges::default()
            }),
            _ => HeightRanges::default(),
        }
    }

    /// Stores the height ranges of `blocks` (those read from a file), when
    /// they are not the `stored` ones.
    fn store_ranges(
        &self,
        cache: &Cache,
        stored: &HeightRanges,
        blocks: &[(usize, Result<TerrainBlock>)],
    ) {
        let read = blocks.iter().filter_map(|(_, block)| block.as_ref().ok());
        let ranges = read.filter_map(|block| Some((*block.source()?, block.range())));
        let ranges = HeightRanges(ranges.collect());
        if ranges != *stored {
            let key = terrain_cache::key(cache, self.space_dir);
            cache.put(Kind::Terrain, &key, &terrain_cache::encode(&ranges));
        }
    }
}

/// Adds a chunk `file`'s item counts to `items`, by kind.
fn count_items(items: &mut BTreeMap<String, ItemCount>, file: &ChunkFile) {
    for (kind, &count) in &file.items {
        let item = items.entry(kind.clone()).or_insert_with(|| ItemCount {
            kind: kind.clone(),
            count: 0,
            chunks: 0,
        });
        item.count += count;
        item.chunks += 1;
    }
}

/// The terrain block of every chunk that names one, by the chunk's index
/// in name order (as the chunks are placed), with the chunk's transform;
/// a chunk's transform problems are the placing's to report.
fn terrain_jobs(
    by_name: &BTreeMap<String, (PathBuf, ReadChunk)>,
    chunk_size: f64,
) -> Vec<TerrainJob> {
    let chunks = by_name.iter().enumerate();
    let with_terrain = chunks.filter_map(|(chunk, (name, (path, ReadChunk { file, .. })))| {
        let element = file.terrain.as_ref()?;
        let grid = space_settings::parse_outdoor_chunk_name(name);
        let transform = chunk_transform(path, file, grid, chunk_size, &mut Vec::new());
        Some(TerrainJob {
            chunk,
            chunk_path: path.clone(),
            resource: element.resource.clone(),
            transform,
        })
    });
    with_terrain.collect()
}

impl Loader<'_> {
    /// The space's folder and its `space.settings`, found in the res paths.
    fn read_space_settings(&self) -> Result<(PathBuf, space_settings::SpaceSettings)> {
        let config = self.config;
        let space = files::normalise(&config.space);
        let settings_name = format!("{space}/space.settings");
        let settings_path = config.res_paths.resolve(&settings_name).ok_or_else(|| {
            Error::invalid(
                &space,
                format!(
                    "no space.settings for space `{space}` in any res path ({}); check <space> and <resPaths>",
                    config
                        .res_paths
                        .roots
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?;
        let space_dir = settings_path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default();
        let settings = read_parsed(&settings_path, self.log, space_settings::parse)?;
        Ok((space_dir, settings))
    }

    /// Every `.chunk` file of the space, parsed in parallel (in path order).
    fn parse_chunk_files(
        &mut self,
        space_dir: &Path,
        settings: &space_settings::SpaceSettings,
    ) -> Result<Vec<(PathBuf, Result<ReadChunk>)>> {
        // Large spaces keep chunks in `XXXxZZZx/sep/` sub-folders unless
        // space.settings says <singleDir>.
        // Entries that are not regular files (a FIFO, a link to a device) are
        // never opened: each is a problem.
        let walk = files::walk(space_dir, ".chunk", !settings.single_dir)?;
        let chunk_files = walk.files;
        self.problems
            .extend(walk.refused.into_iter().map(|(path, err)| Problem {
                what: path.display().to_string(),
                why: format!("{err}; ignored"),
            }));
        if chunk_files.is_empty() {
            return Err(Error::invalid(
                space_dir,
                match self.problems.first() {
                    None => "the space holds no .chunk files: nothing to bake".to_string(),
                    Some(p) => format!("the space holds no readable .chunk file: {}", p.why),
                },
            ));
        }
        let (log, cache, known) = (self.log, self.cache, self.known);
        let counter = Counter::begin(self.progress, Phase::Chunks, None, chunk_files.len() as u64);
        let parsed = chunk_files
            .par_iter()
            .map(|path| {
                let chunk = match cache {
                    Some(cache) => read_chunk_cached(path, log, cache, known),
                    None => read_chunk(path, log),
                };
                counter.add(1);
                (path.clone(), chunk)
            })
            .collect();
        counter.finish();
        Ok(parsed)
    }

    /// The chunks sorted by name; a name seen twice (sep sub-folders and
    /// the space folder both holding it) keeps the first path in sorted
    /// order. Unreadable chunks and outdoor chunks outside the space's
    /// bounds are problems.
    fn keep_chunks_by_name(
        &mut self,
        parsed: Vec<(PathBuf, Result<ReadChunk>)>,
        space_dir: &Path,
        settings: &space_settings::SpaceSettings,
    ) -> Result<BTreeMap<String, (PathBuf, ReadChunk)>> {
        let problems = &mut self.problems;
        let mut by_name: BTreeMap<String, (PathBuf, ReadChunk)> = BTreeMap::new();
        for (path, chunk) in parsed {
            let name = chunk_name(&path);
            match chunk {
                Err(err) => {
                    let (what, why) = err.as_problem_of(&path);
                    problems.push(Problem { what, why });
                }
                Ok(chunk) => {
                    if let Some((kept, _)) = by_name.get(&name) {
                        problems.push(Problem {
                            what: path.display().to_string(),
                            why: format!("duplicate of chunk {}; ignored", kept.display()),
                        });
                        continue;
                    }
                    if let Some((x, z)) = space_settings::parse_outdoor_chunk_name(&name) {
                        if !settings.contains(x, z) {
                            problems.push(Problem {
                                what: path.display().to_string(),
                                why: format!(
                                    "outdoor chunk ({x}, {z}) lies outside the space bounds in space.settings; ignored"
                                ),
                            });
                            continue;
                        }
                    }
                    by_name.insert(name, (path, chunk));
                }
            }
        }
        if by_name.is_empty() {
            return Err(Error::invalid(
                space_dir,
                format!(
                    "no readable chunk in the space ({} problems, first: {})",
                    problems.len(),
                    problems.first().map(|p| p.why.as_str()).unwrap_or("")
                ),
            ));
        }
        Ok(by_name)
    }

    /// Each distinct model the chunks place (resources, and the proxies of
    /// their speedtrees), once, in name order, loaded in parallel; with
    /// each loaded name's index in the models. A model that fails is a
    /// problem saying how many placements in how many chunks lose it.
    fn load_models(
        &mut self,
        by_name: &BTreeMap<String, (PathBuf, ReadChunk)>,
    ) -> (Vec<Model>, BTreeMap<String, usize>) {
        let (sources, usage) = self.models_needed(by_name);
        let (res_paths, log) = (&self.config.res_paths, self.log);
        let counter = Counter::begin(self.progress, Phase::Models, None, sources.len() as u64);
        let loaded: Vec<(String, Result<Model>)> = sources
            .into_iter()
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|(name, source)| {
                let model = match source {
                    ModelSource::Resource { referenced_by } => {
                        load_model(res_paths, &name, &referenced_by, log)
                    }
                    ModelSource::Parametric(tree) => Ok(super::speedtree::parametric_model(&tree)),
                };
                counter.add(1);
                (name, model)
            })
            .collect();
        counter.finish();
        let mut models = Vec::new();
        let mut model_names = BTreeMap::new();
        for (name, model) in loaded {
            match model {
                Ok(model) => {
                    model_names.insert(name, models.len());
                    models.push(model);
                }
                Err(err) => {
                    let loss = usage.get(&name).map(Usage::loss).unwrap_or_default();
                    self.problems.push(Problem {
                        what: name,
                        why: format!("{err}; {loss}"),
                    });
                }
            }
        }
        (models, model_names)
    }

    /// Every model name the chunks need, with where it comes from and how
    /// much of the world uses it.
    fn models_needed(
        &self,
        by_name: &BTreeMap<String, (PathBuf, ReadChunk)>,
    ) -> (BTreeMap<String, ModelSource>, BTreeMap<String, Usage>) {
        let mut sources: BTreeMap<String, ModelSource> = BTreeMap::new();
        let mut usage: BTreeMap<String, Usage> = BTreeMap::new();
        let mut proxies: BTreeMap<String, Option<(String, Option<ParametricTree>)>> =
            BTreeMap::new();
        let mut need = |name: String, placements: usize, source: ModelSource, chunk: &str| {
            let used = usage.entry(name.clone()).or_default();
            used.placements += placements;
            used.chunks.insert(chunk.to_string());
            sources.entry(name).or_insert(source);
        };
        for (chunk, (path, read)) in by_name {
            let first = || ModelSource::Resource {
                referenced_by: path.clone(),
            };
            for (name, &placements) in &read.placements {
                need(name.clone(), placements, first(), chunk);
            }
            for tree in &read.file.speedtrees {
                let spt = files::normalise(&tree.spt);
                let proxy = proxies
                    .entry(spt)
                    .or_insert_with_key(|spt| proxy_model(&self.config.speedtrees, spt));
                if let Some((name, shape)) = proxy {
                    let source = shape.map_or_else(first, ModelSource::Parametric);
                    need(name.clone(), 1, source, chunk);
                }
            }
        }
        (sources, usage)
    }

    /// Every chunk with its world transform and its instances placed in
    /// the world (those that cannot be placed are problems). Chunks are
    /// placed in parallel, a batch at a time so that only one batch's
    /// instances are ever held twice.
    fn place_chunks(
        &mut self,
        by_name: BTreeMap<String, (PathBuf, ReadChunk)>,
        settings: &space_settings::SpaceSettings,
        model_names: &BTreeMap<String, usize>,
    ) -> Placed {
        const BATCH: usize = 256;
        let mut chunks = Vec::with_capacity(by_name.len());
        let mut instances = Vec::new();
        let mut items: BTreeMap<String, ItemCount> = BTreeMap::new();
        // Held for the whole bake: sized exactly rather than grown by doubling.
        instances.reserve_exact(
            by_name
                .values()
                .map(|(_, read)| read.file.instances.len() + read.file.speedtrees.len())
                .sum(),
        );
        let placing = Placing {
            speedtrees: &self.config.speedtrees,
            model_names,
            chunk_size: settings.chunk_size,
        };
        let mut named = by_name.into_iter().peekable();
        while named.peek().is_some() {
            // A batch's parsed items are freed once it is placed: they are
            // not all held while the terrain is decoded beside.
            let batch: Vec<(String, (PathBuf, ReadChunk))> = named.by_ref().take(BATCH).collect();
            let first_index = chunks.len();
            let placed: Vec<PlacedChunk> = batch
                .par_iter()
                .enumerate()
                .map(|(i, (name, (path, read)))| {
                    placing.chunk(first_index + i, name, path, &read.file)
                })
                .collect();
            for ((name, (path, read)), placed) in batch.into_iter().zip(placed) {
                let ReadChunk {
                    file, key, sites, ..
                } = read;
                count_items(&mut items, &file);
                self.problems.extend(placed.problems);
                let first_instance = instances.len();
                instances.extend(placed.instances);
                chunks.push(Chunk {
                    name,
                    file: path,
                    file_key: Some(key),
                    grid: placed.grid,
                    transform: placed.transform,
                    instances: first_instance..instances.len(),
                    instance_elements: file.instances.len(),
                    speedtree_elements: file.speedtrees.len(),
                    terrain: None,
                    sites,
                });
            }
        }
        Placed {
            chunks,
            instances,
            items: items.into_values().collect(),
        }
    }

    /// The chunks' decoded terrain blocks (`blocks`, by chunk index),
    /// each kept block linked from its chunk. Unreadable blocks and blocks
    /// outside `region` are problems.
    fn keep_terrain_blocks(
        &mut self,
        blocks: Vec<(usize, Result<TerrainBlock>)>,
        region: &SpaceRegion,
        chunks: &mut [Chunk],
    ) -> Vec<TerrainBlock> {
        let mut terrain = Vec::new();
        for (chunk, block) in blocks {
            match block {
                Ok(block) if !region.contains(block.bounds().0, block.bounds().1) => {
                    let (min, max) = block.bounds();
                    self.problems.push(Problem {
                        what: format!("{} <terrain>", chunks[chunk].file.display()),
                        why: region.stray_reason(min, max),
                    });
                }
                Ok(block) => {
                    chunks[chunk].terrain = Some(terrain.len());
                    terrain.push(block);
                }
                Err(err) => self.problems.push(Problem {
                    what: format!("{} <terrain>", chunks[chunk].file.display()),
                    why: err.to_string(),
                }),
            }
        }
        terrain
    }
}

/// What placing a chunk's elements reads: the proxies of speedtrees,
/// the loaded models by name, the outdoor grid's chunk size.
struct Placing<'a> {
    speedtrees: &'a SpeedTreeProxies,
    model_names: &'a BTreeMap<String, usize>,
    chunk_size: f64,
}

/// The models of each resource list of a chunk's elements, by the list's
/// address (alive while the chunk is placed).
type PartsOf = HashMap<usize, Arc<[Option<usize>]>>;

/// One chunk's place and instances, and the problems placing it found.
struct PlacedChunk {
    grid: Option<(i32, i32)>,
    transform: DMat4,
    instances: Vec<Instance>,
    problems: Vec<Problem>,
}

impl Placing<'_> {
    /// Chunk `name` (file `path`, parsed `file`), to be chunk `index`.
    fn chunk(&self, index: usize, name: &str, path: &Path, file: &ChunkFile) -> PlacedChunk {
        let mut problems = Vec::new();
        let grid = space_settings::parse_outdoor_chunk_name(name);
        let transform = chunk_transform(path, file, grid, self.chunk_size, &mut problems);
        let mut instances = Vec::with_capacity(file.instances.len() + file.speedtrees.len());
        let mut parts = PartsOf::default();
        for element in &file.instances {
            instances.extend(self.instance(
                path,
                index,
                transform,
                element,
                &mut parts,
                &mut problems,
            ));
        }
        for element in &file.speedtrees {
            instances.extend(self.speedtree(path, index, transform, element, &mut problems));
        }
        PlacedChunk {
            grid,
            transform,
            instances,
            problems,
        }
    }

    /// One chunk element placed in the world, or a problem when its
    /// transform is not finite or singular, or it names no resource.
    fn instance(
        &self,
        chunk_path: &Path,
        chunk_index: usize,
        chunk_transform: DMat4,
        element: &chunk::InstanceElement,
        parts_of: &mut PartsOf,
        problems: &mut Vec<Problem>,
    ) -> Option<Instance> {
        let what = || format!("{} <{}>", chunk_path.display(), element.path);
        let (world, determinant) =
            world_transform(what, chunk_transform * element.transform, problems)?;
        if element.resources.is_empty() {
            problems.push(Problem {
                what: what(),
                why: "no <resource>; instance left out".into(),
            });
            return None;
        }
        // Keyed by the list's address: the elements read back from the
        // cache that name the same resources share one list.
        let parts = parts_of
            .entry(element.resources.as_ptr() as usize)
            .or_insert_with(|| {
                element
                    .resources
                    .iter()
                    .map(|r| self.model_names.get(&*files::normalised(r)).copied())
                    .collect()
            })
            .clone();
        Some(Instance {
            chunk: chunk_index,
            index: element.index,
            kind: element.kind,
            resources: element.resources.clone(),
            parts,
            world,
            mirrored: determinant < 0.0,
            casts_shadow: element.casts_shadow,
        })
    }

    /// A chunk's `<speedtree>` placed in the world with its proxy as its
    /// one part (none when no rule matches its `.spt`), or a problem when
    /// its transform is not finite or singular, or it names no `.spt`.
    fn speedtree(
        &self,
        chunk_path: &Path,
        chunk_index: usize,
        chunk_transform: DMat4,
        element: &chunk::SpeedTreeElement,
        problems: &mut Vec<Problem>,
    ) -> Option<Instance> {
        let what = || format!("{} <{}>", chunk_path.display(), element.path);
        let (world, determinant) =
            world_transform(what, chunk_transform * element.transform, problems)?;
        let spt = files::normalise(&element.spt);
        if spt.is_empty() {
            problems.push(Problem {
                what: what(),
                why: "no <spt>; speedtree left out".into(),
            });
            return None;
        }
        let parts = match proxy_model(self.speedtrees, &spt) {
            Some((name, _)) => Arc::from([self.model_names.get(&name).copied()]),
            None => Arc::from([]),
        };
        Some(Instance {
            chunk: chunk_index,
            index: element.index,
            kind: InstanceKind::SpeedTree,
            resources: Arc::from([element.spt.trim().to_string()]),
            parts,
            world,
            mirrored: determinant < 0.0,
            casts_shadow: true,
        })
    }
}

/// A chunk's world transform: an indoor chunk's own, else its place on
/// the outdoor grid (identity, and a problem, for neither).
fn chunk_transform(
    path: &Path,
    file: &ChunkFile,
    grid: Option<(i32, i32)>,
    chunk_size: f64,
    problems: &mut Vec<Problem>,
) -> DMat4 {
    match (grid, file.transform) {
        (_, Some(indoor)) => indoor,
        (Some((x, z)), None) => DMat4::from_translation(DVec3::new(
            x as f64 * chunk_size,
            0.0,
            z as f64 * chunk_size,
        )),
        (None, None) => {
            problems.push(Problem {
                what: path.display().to_string(),
                why: "indoor chunk without <transform>; identity used".into(),
            });
            DMat4::IDENTITY
        }
    }
}

/// An element's world transform and its determinant, or a problem about
/// `what` when it is not finite or singular.
fn world_transform(
    what: impl Fn() -> String,
    world: DMat4,
    problems: &mut Vec<Problem>,
) -> Option<(DMat4, f64)> {
    if !world.is_finite() {
        problems.push(Problem {
            what: what(),
            why: "transform holds NaN or infinite values; instance left out".into(),
        });
        return None;
    }
    let determinant = world.determinant();
    if determinant.abs() < SINGULAR_DETERMINANT {
        problems.push(Problem {
            what: what(),
            why: format!(
                "singular transform (determinant {determinant:e}, zero scale); instance left out"
            ),
        });
        return None;
    }
    Some((world, determinant))
}

fn chunk_name(path: &Path) -> String {
    path.file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_suffix(".chunk"))
        .unwrap_or_default()
        .to_string()
}

/// Reads a data section, notes the file in `log` and reads `parse` out of
/// it; errors carry the file and, for text XML, the line and column.
fn read_parsed<T>(
    path: &Path,
    log: &ReadLog,
    parse: impl FnOnce(&formats::Section) -> Result<T, crate::error::FormatError>,
) -> Result<T> {
    let bytes = files::read_file(path)?;
    log.record(path, &bytes);
    formats::parse_data_section(&bytes)
        .and_then(|root| parse(&root))
        .map_err(|e| e.in_source(path, &bytes))
}

/// A chunk file's items, the content key of its bytes, and where its
/// `<shadow>`s go (text XML).
struct ReadChunk {
    file: ChunkFile,
    key: Key,
    sites: Option<ShadowSites>,
    /// How many of its instances place each resource
    /// ([`resource_placements`]): counted as the chunk is read, while its
    /// items are still in the processor's cache.
    placements: BTreeMap<String, usize>,
}

impl ReadChunk {
    fn of(parsed: ParsedChunk, key: Key) -> ReadChunk {
        ReadChunk {
            placements: resource_placements(&parsed.chunk),
            file: parsed.chunk,
            key,
            sites: parsed.sites,
        }
    }
}

/// Reads a chunk, noting it in `log` with its masks zeroed: the bake
/// ignores old `<shadow>` values, so writing masks does not change the
/// chunk as an input.
fn read_chunk(path: &Path, log: &ReadLog) -> Result<ReadChunk> {
    let bytes = files::read_file(path)?;
    let parsed = parse_chunk(path, &bytes)?;
    log.record_digest(path, parsed.canonical);
    Ok(ReadChunk::of(parsed, content_key(&bytes)))
}

/// [`read_chunk`] with its items from `cache` when a bake before parsed
/// the same bytes; a file `known` vouches for is not read at all then.
fn read_chunk_cached(
    path: &Path,
    log: &ReadLog,
    cache: &Cache,
    known: &KnownFiles,
) -> Result<ReadChunk> {
    let vouched = known.key_of(path);
    if let Some(key) = vouched {
        if let Some(parsed) = cached_items(cache, &key) {
            log.record_digest(path, parsed.canonical);
            return Ok(ReadChunk::of(parsed, key));
        }
    }
    let bytes = files::read_file(path)?;
    let key = content_key(&bytes);
    // A key just looked up in vain is not looked up twice.
    let held = match vouched == Some(key) {
        true => None,
        false => cached_items(cache, &key),
    };
    let parsed = match held {
        Some(parsed) => parsed,
        None => {
            let parsed = parse_chunk(path, &bytes)?;
            let entry = chunk_cache::key(cache, &key);
            cache.put(Kind::Chunk, &entry, &chunk_cache::encode(&parsed));
            parsed
        }
    };
    log.record_digest(path, parsed.canonical);
    Ok(ReadChunk::of(parsed, key))
}

/// The items of the chunk file whose content key is `key`, when `cache`
/// holds them (a damaged entry is rejected).
fn cached_items(cache: &Cache, key: &Key) -> Option<ParsedChunk> {
    let entry = chunk_cache::key(cache, key);
    let Fetched::Value(value) = cache.fetch(Kind::Chunk, &entry) else {
        return None;
    };
    let parsed = chunk_cache::decode(&value);
    if parsed.is_none() {
        cache.reject(Kind::Chunk, &entry);
    }
    parsed
}

/// Parses chunk file `bytes` (read from `path`, which errors name).
fn parse_chunk(path: &Path, bytes: &[u8]) -> Result<ParsedChunk> {
    // Packed chunks (rare) are parsed again when written.
    let text = !bytes.starts_with(&formats::packed_xml::MAGIC);
    if let Some((chunk, sites)) = text.then(|| chunk_scan::scan(bytes)).flatten() {
        let canonical = shadow_write::digest_without_masks_at(bytes, &sites, &chunk)
            .unwrap_or_else(|_| Digest::of(bytes));
        return Ok(ParsedChunk {
            chunk,
            canonical,
            sites: Some(sites),
        });
    }
    let root = formats::parse_data_section(bytes).map_err(|e| e.in_source(path, bytes))?;
    let chunk = chunk::parse(&root).map_err(|e| e.in_source(path, bytes))?;
    let canonical = match shadow_write::without_masks(bytes, &root, &chunk) {
        Ok(canonical) => Digest::of(&canonical),
        Err(_) => Digest::of(bytes),
    };
    let sites = text.then(|| ShadowSites::find(bytes, &root).ok()).flatten();
    Ok(ParsedChunk {
        chunk,
        canonical,
        sites,
    })
}

/// Reads and parses a data section, noting the file in `log`.
fn read_logged(path: &Path, log: &ReadLog) -> Result<formats::Section> {
    read_parsed(path, log, |root| Ok(root.clone()))
}

/// [`ResPaths::read`], noting the file in `log`.
fn read_resource(
    res_paths: &ResPaths,
    name: &str,
    referenced_by: &Path,
    log: &ReadLog,
) -> Result<(PathBuf, Vec<u8>)> {
    let (path, bytes) = res_paths.read(name, referenced_by)?;
    log.record(&path, &bytes);
    Ok((path, bytes))
}

/// Leaves out the instances whose world box is not inside `region` (stray
/// placements), each a problem naming its chunk and element. `instances`
/// stays chunk by chunk in document order and every chunk's range follows.
fn drop_strays(
    chunks: &mut [Chunk],
    instances: &mut Vec<Instance>,
    models: &[Model],
    region: &SpaceRegion,
    problems: &mut Vec<Problem>,
) {
    let model_bounds: Vec<Option<(DVec3, DVec3)>> = models
        .iter()
        .map(|m| m.bounds().map(|(a, b)| (a.as_dvec3(), b.as_dvec3())))
        .collect();
    let stray: Vec<bool> = instances
        .par_iter()
        .map(|instance| {
            let (min, max) = instance_box(instance, &model_bounds);
            !region.contains(min, max)
        })
        .collect();
    if !stray.contains(&true) {
        return;
    }
    for (instance, _) in instances.iter().zip(&stray).filter(|(_, s)| **s) {
        let (min, max) = instance_box(instance, &model_bounds);
        problems.push(Problem {
            what: format!(
                "{} <{}[{}]/transform>",
                chunks[instance.chunk].file.display(),
                instance.kind.tag(),
                instance.index
            ),
            why: region.stray_reason(min, max),
        });
    }
    let mut removed = 0;
    for chunk in chunks.iter_mut() {
        let range = chunk.instances.clone();
        let before = removed;
        removed += stray[range.clone()].iter().filter(|s| **s).count();
        chunk.instances = range.start - before..range.end - removed;
    }
    let mut flags = stray.into_iter();
    instances.retain(|_| !flags.next().unwrap_or(false));
}

/// The world box of an instance's parts that loaded, or the placement's
/// origin when none did.
fn instance_box(instance: &Instance, model_bounds: &[Option<(DVec3, DVec3)>]) -> (DVec3, DVec3) {
    let world = &instance.world;
    instance
        .parts
        .iter()
        .flatten()
        .filter_map(|&m| model_bounds[m])
        .map(|(min, max)| crate::trace::transform_box(world, min, max))
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))
        .unwrap_or((world.w_axis.truncate(), world.w_axis.truncate()))
}

/// The resource name of the folder a chunk lies in: the space's, or a
/// folder below it.
fn chunk_folder(space: &str, space_dir: &Path, chunk_path: &Path) -> String {
    let space = files::normalise(space);
    let below = chunk_path
        .parent()
        .and_then(|dir| dir.strip_prefix(space_dir).ok())
        .filter(|below| !below.as_os_str().is_empty());
    match below {
        Some(below) => format!("{space}/{}", files::normalise(&below.to_string_lossy())),
        None => space,
    }
}

/// A chunk's terrain resource (`xxx.cdata/terrain2`) is relative to the
/// chunk's folder, whose resource name is `folder`: the file in the chunk's
/// own folder, else `folder/xxx.cdata` in the first res path holding it
/// (`ResPaths::beside`); like every resource it must stay inside the res
/// paths.
fn load_terrain(
    res_paths: &ResPaths,
    log: &ReadLog,
    ranges: Option<&HeightRanges>,
    job: &TerrainJob,
    folder: &str,
    chunk_size: f64,
) -> Result<TerrainBlock> {
    let (chunk_path, origin) = (&job.chunk_path, job.transform.w_axis.truncate());
    let resource = files::normalise(&job.resource);
    let Some((file, entry)) = resource
        .split_once(".cdata/")
        .map(|(stem, entry)| (format!("{stem}.cdata"), entry.to_string()))
    else {
        return Err(Error::invalid(
            chunk_path,
            format!("terrain resource `{resource}` does not name a .cdata entry (expected `NAME.cdata/terrain2`)"),
        ));
    };
    if !files::stays_inside(&file) {
        return Err(Error::invalid(
            chunk_path,
            format!("terrain resource `{resource}` climbs out of the chunk's folder (`..` or a drive prefix); refused: name the .cdata relative to the chunk"),
        ));
    }
    let dir = chunk_path.parent().unwrap_or(Path::new("."));
    let cdata_path = res_paths.beside(dir, folder, &file)?;
    let bytes = files::read_file(&cdata_path)
        .map_err(|err| cdata_not_found(err, chunk_path, &file, &cdata_path, res_paths))?;
    log.record(&cdata_path, &bytes);
    let Some(ranges) = ranges else {
        return decode_terrain(&bytes, &entry, origin, chunk_size, &cdata_path);
    };
    let source = terrain_cache::source_key(&content_key(&bytes), &entry);
    if let Some(range) = ranges.get(&source) {
        if let Some(block) = deferred_terrain(range, &bytes, &entry, origin, chunk_size) {
            return Ok(block.with_source(source));
        }
    }
    let block = decode_terrain(&bytes, &entry, origin, chunk_size, &cdata_path)?;
    Ok(block.with_source(source))
}

/// The block in `.cdata` file `bytes` (read from `path`, which errors
/// name), its heights decoded.
fn decode_terrain(
    bytes: &[u8],
    entry: &str,
    origin: DVec3,
    chunk_size: f64,
    path: &Path,
) -> Result<TerrainBlock> {
    let data = terrain_format::read_terrain(bytes, entry).map_err(|e| e.in_file(path))?;
    TerrainBlock::new(&data, origin, chunk_size).map_err(|message| Error::invalid(path, message))
}

/// The block in `.cdata` file `bytes` with its heights decoded when first
/// read, its height `range` known; `None` (the block then decoded now) for
/// a file whose decoding cannot wait.
fn deferred_terrain(
    range: HeightRange,
    bytes: &[u8],
    entry: &str,
    origin: DVec3,
    chunk_size: f64,
) -> Option<TerrainBlock> {
    let data = terrain_format::read_terrain_deferred(bytes, entry).ok()??;
    TerrainBlock::deferred(data, range, origin, chunk_size).ok()
}

/// A missing `.cdata` named as a missing model is: where it was looked
/// for, what to check, and what the bake loses.
fn cdata_not_found(
    err: Error,
    chunk_path: &Path,
    file: &str,
    looked_at: &Path,
    res_paths: &ResPaths,
) -> Error {
    match err {
        Error::Io { os_error, .. } if os_error.kind() == std::io::ErrorKind::NotFound => {
            let roots: Vec<String> = res_paths
                .roots
                .iter()
                .map(|p| p.display().to_string())
                .collect();
            Error::invalid(
                chunk_path,
                format!(
                    "terrain `{file}` not found beside the chunk or in the res paths (looked for {}); check <resPaths> ({}) and that the space's .cdata files were copied with its chunks: 1 chunk loses its terrain block (left out of the bake)",
                    looked_at.display(),
                    roots.join(", ")
                ),
            )
        }
        other => other,
    }
}

/// Loads one model resource's LOD 0 geometry: `.model` → its own visual
/// (not the `<parent>` LODs) → `.primitives`. `referenced_by` is a chunk that
/// places it, for the error when the model itself is missing.
fn load_model(
    res_paths: &ResPaths,
    name: &str,
    referenced_by: &Path,
    log: &ReadLog,
) -> Result<Model> {
    let (model_path, visual_resource, visual_path) =
        find_visual(res_paths, name, referenced_by, log)?;
    let visual = read_visual(res_paths, &visual_path, log)?;
    let mut sections = PrimitiveSections {
        res_paths,
        log,
        visual_path: &visual_path,
        primitives_file: visual::primitives_name(&visual_resource),
        containers: BTreeMap::new(),
    };
    let mut geometry_model = Model {
        resource: name.to_string(),
        file: model_path,
        ..Model::default()
    };
    for (render_set_index, render_set) in visual.render_sets.iter().enumerate() {
        // Skinned sets hold model-space vertices (static pose); the others
        // are in their first node's space.
        let node_to_model = if render_set.treat_as_world_space_object {
            DMat4::IDENTITY
        } else {
            visual
                .node_to_root_index(render_set.first_node)
                .unwrap_or(DMat4::IDENTITY)
        };
        geometry_model.layout.push(
            render_set
                .geometries
                .iter()
                .map(|g| g.groups.len())
                .collect(),
        );
        for (geometry_index, geometry) in render_set.geometries.iter().enumerate() {
            let place = GeometryPlace {
                render_set: render_set_index,
                geometry: geometry_index,
                node_to_model,
            };
            add_geometry(&mut geometry_model, &mut sections, geometry, &place)?;
        }
    }
    Ok(geometry_model)
}

/// A model's file and the visual it names that exists: the visual's
/// resource name and file.
fn find_visual(
    res_paths: &ResPaths,
    name: &str,
    referenced_by: &Path,
    log: &ReadLog,
) -> Result<(PathBuf, String, PathBuf)> {
    let (model_path, bytes) = read_resource(res_paths, name, referenced_by, log)?;
    let model_file = formats::parse_data_section(&bytes)
        .and_then(|root| model::parse_model(&root))
        .map_err(|e| e.in_source(&model_path, &bytes))?;
    let candidates = model::visual_candidates(&model_file);
    let Some((visual_resource, visual_path)) = candidates
        .iter()
        .find_map(|c| res_paths.resolve(c).map(|p| (c.clone(), p)))
    else {
        return Err(Error::NotFound {
            name: candidates.join(" or "),
            referenced_by: model_path,
            searched: res_paths.roots.clone(),
        });
    };
    Ok((model_path, visual_resource, visual_path))
}

/// A visual with its materials' flags resolved (`.mfm` files it names).
fn read_visual(res_paths: &ResPaths, visual_path: &Path, log: &ReadLog) -> Result<visual::Visual> {
    let mut visual = read_parsed(visual_path, log, visual::parse_visual)?;
    visual
        .resolve_materials(&mut |mfm| {
            let path = res_paths.resolve(mfm)?;
            read_logged(&path, log).ok()
        })
        .map_err(|e| e.in_file(visual_path))?;
    Ok(visual)
}

/// The `.primitives` sections a visual's geometries name, each container
/// file read once per model however many geometries use it.
struct PrimitiveSections<'a> {
    res_paths: &'a ResPaths,
    log: &'a ReadLog,
    visual_path: &'a Path,
    /// The visual's own `.primitives` file, for section names without one.
    primitives_file: String,
    containers: BTreeMap<String, (PathBuf, Vec<u8>)>,
}

impl PrimitiveSections<'_> {
    /// A geometry's section name split into container file and section.
    fn split(&self, geometry: &visual::Geometry, name: &str) -> Result<(String, String)> {
        visual::split_section_resource(&self.primitives_file, name).ok_or_else(|| {
            Error::invalid(
                self.visual_path,
                format!("<{}>: `{name}` names no section", geometry.path),
            )
        })
    }

    /// A section's bytes, with its container's path and the section's
    /// offset in it (for errors).
    fn section(&mut self, file: &str, section: &str) -> Result<(PathBuf, Vec<u8>, usize)> {
        if !self.containers.contains_key(file) {
            let (path, bytes) = read_resource(self.res_paths, file, self.visual_path, self.log)?;
            self.containers.insert(file.to_string(), (path, bytes));
        }
        let (path, bytes) = &self.containers[file];
        let container = binsection::parse(bytes).map_err(|e| e.in_file(path))?;
        let (data, offset) = container.get(section).ok_or_else(|| {
            Error::invalid(
                path,
                format!(
                    "no section `{section}` (named by {}); it holds: {}",
                    self.visual_path.display(),
                    container
                        .entries
                        .iter()
                        .map(|e| e.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?;
        Ok((path.clone(), data.to_vec(), offset))
    }
}

/// Where a geometry sits in its model: its render set and index there, and
/// the transform of its vertices into model space.
struct GeometryPlace {
    render_set: usize,
    geometry: usize,
    node_to_model: DMat4,
}

/// Appends a geometry's vertices (in model space) and one group per
/// primitive group to `model`.
fn add_geometry(
    model: &mut Model,
    sections: &mut PrimitiveSections<'_>,
    geometry: &visual::Geometry,
    place: &GeometryPlace,
) -> Result<()> {
    let (vertices_file, vertices_section) = sections.split(geometry, &geometry.vertices)?;
    let (indices_file, indices_section) = sections.split(geometry, &geometry.primitive)?;
    let (path, data, offset) = sections.section(&vertices_file, &vertices_section)?;
    let vertices =
        primitives::read_vertices(&data).map_err(|e| e.shifted(offset).in_file(&path))?;
    let (path, data, offset) = sections.section(&indices_file, &indices_section)?;
    let indices = primitives::read_indices(&data).map_err(|e| e.shifted(offset).in_file(&path))?;

    let base = model.positions.len() as u32;
    model.positions.extend(vertices.positions.iter().map(|p| {
        place
            .node_to_model
            .transform_point3(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .as_vec3()
    }));
    for group in &geometry.groups {
        let triangle_indices =
            primitives::group_triangles(&indices, group.index as usize, vertices.positions.len())
                .map_err(|e| e.shifted(offset).in_file(&path))?;
        let first = model.triangles.len();
        model.triangles.extend(
            triangle_indices
                .chunks_exact(3)
                .map(|t| [base + t[0], base + t[1], base + t[2]]),
        );
        model.groups.push(Group {
            render_set: place.render_set,
            geometry: place.geometry,
            primitive_group: group.index as usize,
            triangles: first..model.triangles.len(),
            alpha_tested: group.flags.alpha_tested(),
            double_sided: group.flags.double_sided(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placements_are_counted_per_normalised_name_whether_lists_are_shared_or_not() {
        let element = |resources: &[&str]| {
            let list: String = resources
                .iter()
                .map(|r| format!("<resource>{r}</resource>"))
                .collect();
            format!("<model>{list}</model>")
        };
        let elements = [
            element(&["sets/a.model"]),
            element(&["sets/b.model", "sets/a.model"]),
            element(&["sets\\a.model"]),
            element(&["sets/a.model"]),
            element(&["/sets/b.model", "sets/a.model"]),
            element(&[]),
        ];
        let text = format!("<root>{}</root>", elements.concat());
        let section = formats::parse_data_section(text.as_bytes()).unwrap();
        let file = chunk::parse(&section).unwrap();
        assert!(
            Arc::ptr_eq(&file.instances[0].resources, &file.instances[3].resources),
            "the same names share one list"
        );
        let counted = resource_placements(&file);
        let expected = BTreeMap::from([
            ("sets/a.model".to_string(), 5),
            ("sets/b.model".to_string(), 2),
        ]);
        assert_eq!(counted, expected);
    }
}
