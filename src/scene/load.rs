//! Builds a [`Scene`] from a space on disk: parses every chunk, loads each
//! distinct model once, reads the terrain blocks. Bad parts of a world are
//! left out and listed in `Scene::problems` (so `inspect` can list every
//! missing resource, not just the first); only a world that cannot be read
//! at all (no settings, no chunks) is an error. Stray placements (world
//! boxes outside the space's `SpaceRegion`) are found after the terrain is
//! read, since how high an instance may reach follows the terrain.

use super::{Chunk, Group, InputFile, Instance, Model, Problem, Scene, SpaceRegion, TerrainBlock};
use crate::digest::Digest;
use crate::error::{Error, Result};
use crate::files::{self, ResPaths};
use crate::formats::chunk::{self, ChunkFile};
use crate::formats::space_settings;
use crate::formats::{
    self, binsection, model, primitives, shadow_write, terrain as terrain_format, visual,
};
use crate::progress::{Counter, Phase, Progress};
use glam::{DMat4, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Where the world is.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    pub res_paths: ResPaths,
    /// Space folder as a resource name, e.g. `spaces/arctic`.
    pub space: String,
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
        let file = InputFile {
            path: path.to_path_buf(),
            digest: Digest::of(bytes),
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
    let log = ReadLog::default();
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
    let settings = read_parsed(&settings_path, &log, space_settings::parse)?;

    // Large spaces keep chunks in `XXXxZZZx/sep/` sub-folders unless
    // space.settings says <singleDir>.
    // Entries that are not regular files (a FIFO, a link to a device) are
    // never opened: each is a problem.
    let walk = files::walk(&space_dir, ".chunk", !settings.single_dir)?;
    let chunk_files = walk.files;
    let mut problems: Vec<Problem> = walk
        .refused
        .into_iter()
        .map(|(path, err)| Problem {
            what: path.display().to_string(),
            why: format!("{err}; ignored"),
        })
        .collect();
    if chunk_files.is_empty() {
        return Err(Error::invalid(
            &space_dir,
            match problems.first() {
                None => "the space holds no .chunk files: nothing to bake".to_string(),
                Some(p) => format!("the space holds no readable .chunk file: {}", p.why),
            },
        ));
    }
    let counter = Counter::begin(progress, Phase::Chunks, None, chunk_files.len() as u64);
    let parsed: Vec<(PathBuf, Result<ChunkFile>)> = chunk_files
        .par_iter()
        .map(|path| {
            let chunk = read_chunk(path, &log);
            counter.add(1);
            (path.clone(), chunk)
        })
        .collect();
    counter.finish();

    // Chunks sorted by name; a name seen twice (sep sub-folders and the
    // space folder both holding it) keeps the first path in sorted order.
    let mut by_name: BTreeMap<String, (PathBuf, ChunkFile)> = BTreeMap::new();
    for (path, chunk) in parsed {
        let name = chunk_name(&path);
        match chunk {
            Err(err) => problems.push(Problem {
                what: path.display().to_string(),
                why: err.to_string(),
            }),
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
            &space_dir,
            format!(
                "no readable chunk in the space ({} problems, first: {})",
                problems.len(),
                problems.first().map(|p| p.why.as_str()).unwrap_or("")
            ),
        ));
    }

    // Each distinct model resource once, in name order, loaded in parallel.
    let mut model_names: BTreeMap<String, usize> = BTreeMap::new();
    let mut first_reference: BTreeMap<String, PathBuf> = BTreeMap::new();
    for (path, chunk) in by_name.values() {
        for instance in &chunk.instances {
            for resource in &instance.resources {
                let name = files::normalise(resource);
                first_reference
                    .entry(name.clone())
                    .or_insert_with(|| path.clone());
                model_names.insert(name, 0);
            }
        }
    }
    let counter = Counter::begin(progress, Phase::Models, None, first_reference.len() as u64);
    let loaded: Vec<(String, Result<Model>)> = first_reference
        .into_iter()
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|(name, referenced_by)| {
            let model = load_model(&config.res_paths, &name, &referenced_by, &log);
            counter.add(1);
            (name, model)
        })
        .collect();
    counter.finish();
    let mut models = Vec::new();
    for (name, model) in loaded {
        match model {
            Ok(model) => {
                model_names.insert(name, models.len());
                models.push(model);
            }
            Err(err) => {
                model_names.remove(&name);
                problems.push(Problem {
                    what: name,
                    why: err.to_string(),
                });
            }
        }
    }

    let region = SpaceRegion::of(&settings);

    let mut chunks = Vec::new();
    let mut instances = Vec::new();
    let mut terrain = Vec::new();
    // Held for the whole bake: sized exactly rather than grown by doubling.
    instances.reserve_exact(by_name.values().map(|(_, f)| f.instances.len()).sum());
    let terrain_jobs: Vec<(usize, PathBuf, String, DMat4)> = {
        let mut jobs = Vec::new();
        for (name, (path, file)) in &by_name {
            let grid = space_settings::parse_outdoor_chunk_name(name);
            let transform = match (grid, file.transform) {
                (_, Some(indoor)) => indoor,
                (Some((x, z)), None) => DMat4::from_translation(DVec3::new(
                    x as f64 * settings.chunk_size,
                    0.0,
                    z as f64 * settings.chunk_size,
                )),
                (None, None) => {
                    problems.push(Problem {
                        what: path.display().to_string(),
                        why: "indoor chunk without <transform>; identity used".into(),
                    });
                    DMat4::IDENTITY
                }
            };
            let chunk_index = chunks.len();
            let first_instance = instances.len();
            for element in &file.instances {
                let what = format!("{} <{}>", path.display(), element.path);
                let world = transform * element.transform;
                if !world.is_finite() {
                    problems.push(Problem {
                        what,
                        why: "transform holds NaN or infinite values; instance left out".into(),
                    });
                    continue;
                }
                let determinant = world.determinant();
                if determinant.abs() < SINGULAR_DETERMINANT {
                    problems.push(Problem {
                        what,
                        why: format!(
                            "singular transform (determinant {determinant:e}, zero scale); instance left out"
                        ),
                    });
                    continue;
                }
                if element.resources.is_empty() {
                    problems.push(Problem {
                        what,
                        why: "no <resource>; instance left out".into(),
                    });
                    continue;
                }
                let parts: Vec<Option<usize>> = element
                    .resources
                    .iter()
                    .map(|r| model_names.get(&files::normalise(r)).copied())
                    .collect();
                instances.push(Instance {
                    chunk: chunk_index,
                    index: element.index,
                    kind: element.kind,
                    resources: element.resources.clone(),
                    parts,
                    world,
                    mirrored: determinant < 0.0,
                    casts_shadow: element.casts_shadow,
                });
            }
            if let Some(element) = &file.terrain {
                jobs.push((
                    chunk_index,
                    path.clone(),
                    element.resource.clone(),
                    transform,
                ));
            }
            chunks.push(Chunk {
                name: name.clone(),
                file: path.clone(),
                grid,
                transform,
                instances: first_instance..instances.len(),
                instance_elements: file.instances.len(),
                terrain: None,
            });
        }
        jobs
    };

    let counter = Counter::begin(progress, Phase::Terrain, None, terrain_jobs.len() as u64);
    let blocks: Vec<(usize, Result<TerrainBlock>)> = terrain_jobs
        .into_par_iter()
        .map(|(chunk, chunk_path, resource, transform)| {
            let block = load_terrain(
                &config.res_paths,
                &log,
                &chunk_path,
                &resource,
                transform.w_axis.truncate(),
                settings.chunk_size,
            );
            counter.add(1);
            (chunk, block)
        })
        .collect();
    counter.finish();
    for (chunk, block) in blocks {
        match block {
            Ok(block) if !region.contains(block.bounds().0, block.bounds().1) => {
                let (min, max) = block.bounds();
                problems.push(Problem {
                    what: format!("{} <terrain>", chunks[chunk].file.display()),
                    why: region.stray_reason(min, max),
                });
            }
            Ok(block) => {
                chunks[chunk].terrain = Some(terrain.len());
                terrain.push(block);
            }
            Err(err) => problems.push(Problem {
                what: format!("{} <terrain>", chunks[chunk].file.display()),
                why: err.to_string(),
            }),
        }
    }
    // Instances are held to the terrain's heights, known only now.
    let region = region.around_terrain(&terrain);
    drop_strays(&mut chunks, &mut instances, &models, &region, &mut problems);
    problems.sort();
    Ok(Scene {
        space_dir,
        settings,
        chunks,
        models,
        instances,
        terrain,
        problems,
        inputs: log.into_sorted(),
    })
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

/// Reads and parses a chunk, noting it in `log` with its masks zeroed: the
/// bake ignores old `<shadow>` values, so writing masks does not change the
/// chunk as an input.
fn read_chunk(path: &Path, log: &ReadLog) -> Result<ChunkFile> {
    let bytes = files::read_file(path)?;
    let root = formats::parse_data_section(&bytes).map_err(|e| e.in_source(path, &bytes))?;
    let chunk = chunk::parse(&root).map_err(|e| e.in_source(path, &bytes))?;
    match shadow_write::without_masks(&bytes, &root, &chunk) {
        Ok(canonical) => log.record(path, &canonical),
        Err(_) => log.record(path, &bytes),
    }
    Ok(chunk)
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
        .map(|(min, max)| world_box(world, min, max))
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))
        .unwrap_or((world.w_axis.truncate(), world.w_axis.truncate()))
}

/// The box around a model-space box placed by `m`.
fn world_box(m: &DMat4, min: DVec3, max: DVec3) -> (DVec3, DVec3) {
    (0..8)
        .map(|corner| {
            m.transform_point3(DVec3::new(
                if corner & 1 == 0 { min.x } else { max.x },
                if corner & 2 == 0 { min.y } else { max.y },
                if corner & 4 == 0 { min.z } else { max.z },
            ))
        })
        .fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(p), hi.max(p)),
        )
}

/// A chunk's terrain resource (`xxx.cdata/terrain2`) is relative to the
/// chunk's folder; like every resource it must stay inside the res paths.
fn load_terrain(
    res_paths: &ResPaths,
    log: &ReadLog,
    chunk_path: &Path,
    resource: &str,
    origin: DVec3,
    chunk_size: f64,
) -> Result<TerrainBlock> {
    let resource = files::normalise(resource);
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
    let cdata_path = files::in_folder_or_bare(dir, &file);
    res_paths.check_inside(&cdata_path)?;
    let bytes = files::read_file(&cdata_path)?;
    log.record(&cdata_path, &bytes);
    let data = terrain_format::read_terrain(&bytes, &entry).map_err(|e| e.in_file(&cdata_path))?;
    TerrainBlock::new(&data, origin, chunk_size)
        .map_err(|message| Error::invalid(&cdata_path, message))
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
    let mut visual = read_parsed(&visual_path, log, visual::parse_visual)?;
    visual
        .resolve_materials(&mut |mfm| {
            let path = res_paths.resolve(mfm)?;
            read_logged(&path, log).ok()
        })
        .map_err(|e| e.in_file(&visual_path))?;

    let primitives_file = visual::primitives_name(&visual_resource);
    // Each .primitives file read once per model, however many geometries use it.
    let mut containers: BTreeMap<String, (PathBuf, Vec<u8>)> = BTreeMap::new();
    let mut section = |file: &str, section: &str| -> Result<(PathBuf, Vec<u8>, usize)> {
        if !containers.contains_key(file) {
            let (path, bytes) = read_resource(res_paths, file, &visual_path, log)?;
            containers.insert(file.to_string(), (path, bytes));
        }
        let (path, bytes) = &containers[file];
        let container = binsection::parse(bytes).map_err(|e| e.in_file(path))?;
        let (data, offset) = container.get(section).ok_or_else(|| {
            Error::invalid(
                path,
                format!(
                    "no section `{section}` (named by {}); it holds: {}",
                    visual_path.display(),
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
    };

    let mut geometry_model = Model {
        resource: name.to_string(),
        file: model_path.clone(),
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
            let split = |name: &str| {
                visual::split_section_resource(&primitives_file, name).ok_or_else(|| {
                    Error::invalid(
                        &visual_path,
                        format!("<{}>: `{name}` names no section", geometry.path),
                    )
                })
            };
            let (vertices_file, vertices_section) = split(&geometry.vertices)?;
            let (indices_file, indices_section) = split(&geometry.primitive)?;
            let (path, data, offset) = section(&vertices_file, &vertices_section)?;
            let vertices =
                primitives::read_vertices(&data).map_err(|e| e.shifted(offset).in_file(&path))?;
            let (path, data, offset) = section(&indices_file, &indices_section)?;
            let indices =
                primitives::read_indices(&data).map_err(|e| e.shifted(offset).in_file(&path))?;

            let base = geometry_model.positions.len() as u32;
            geometry_model
                .positions
                .extend(vertices.positions.iter().map(|p| {
                    node_to_model
                        .transform_point3(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
                        .as_vec3()
                }));
            for group in &geometry.groups {
                let triangle_indices = primitives::group_triangles(
                    &indices,
                    group.index as usize,
                    vertices.positions.len(),
                )
                .map_err(|e| e.shifted(offset).in_file(&path))?;
                let first = geometry_model.triangles.len();
                geometry_model.triangles.extend(
                    triangle_indices
                        .chunks_exact(3)
                        .map(|t| [base + t[0], base + t[1], base + t[2]]),
                );
                geometry_model.groups.push(Group {
                    render_set: render_set_index,
                    geometry: geometry_index,
                    primitive_group: group.index as usize,
                    triangles: first..geometry_model.triangles.len(),
                    alpha_tested: group.flags.alpha_tested(),
                    double_sided: group.flags.double_sided(),
                });
            }
        }
    }
    Ok(geometry_model)
}
