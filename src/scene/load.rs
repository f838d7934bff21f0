//! Builds a [`Scene`] from a space on disk: parses every chunk, loads each
//! distinct model once, reads the terrain blocks. Bad parts of a world are
//! left out and listed in `Scene::problems` (so `inspect` can list every
//! missing resource, not just the first); only a world that cannot be read
//! at all (no settings, no chunks) is an error.

use super::{Chunk, Instance, Model, Problem, Scene, TerrainBlock};
use crate::error::{Error, Result};
use crate::formats::chunk::{self, ChunkFile};
use crate::formats::resources::{self, ResPaths};
use crate::formats::space_settings;
use crate::formats::{self, terrain as terrain_format};
use glam::{DMat4, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

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

pub fn load_scene(config: &LoadConfig) -> Result<Scene> {
    let space = resources::normalise(&config.space);
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
    let settings = read_section(&settings_path)
        .and_then(|root| space_settings::parse(&root).map_err(|e| e.in_file(&settings_path)))?;

    let chunk_files = resources::find_files(&space_dir, ".chunk")?;
    if chunk_files.is_empty() {
        return Err(Error::invalid(
            &space_dir,
            "the space holds no .chunk files: nothing to bake",
        ));
    }
    let mut problems = Vec::new();
    let parsed: Vec<(PathBuf, Result<ChunkFile>)> = chunk_files
        .par_iter()
        .map(|path| {
            let chunk = read_section(path)
                .and_then(|root| chunk::parse(&root).map_err(|e| e.in_file(path)));
            (path.clone(), chunk)
        })
        .collect();

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
    for (_, chunk) in by_name.values() {
        for instance in &chunk.instances {
            for resource in &instance.resources {
                model_names.insert(resources::normalise(resource), 0);
            }
        }
    }
    let loaded: Vec<(String, Result<Model>)> = model_names
        .keys()
        .cloned()
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|name| {
            let model = load_model(&config.res_paths, &name);
            (name, model)
        })
        .collect();
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

    let mut chunks = Vec::new();
    let mut instances = Vec::new();
    let mut terrain = Vec::new();
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
                let parts = element
                    .resources
                    .iter()
                    .map(|r| model_names.get(&resources::normalise(r)).copied())
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
                terrain: None,
            });
        }
        jobs
    };

    let blocks: Vec<(usize, Result<TerrainBlock>)> = terrain_jobs
        .into_par_iter()
        .map(|(chunk, chunk_path, resource, transform)| {
            let block = load_terrain(
                &chunk_path,
                &resource,
                transform.w_axis.truncate(),
                settings.chunk_size,
            );
            (chunk, block)
        })
        .collect();
    for (chunk, block) in blocks {
        match block {
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
    problems.sort();
    Ok(Scene {
        space_dir,
        settings,
        chunks,
        models,
        instances,
        terrain,
        problems,
    })
}

fn chunk_name(path: &Path) -> String {
    path.file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_suffix(".chunk"))
        .unwrap_or_default()
        .to_string()
}

pub(crate) fn read_section(path: &Path) -> Result<formats::Section> {
    let bytes = resources::read_file(path)?;
    formats::parse_data_section(&bytes).map_err(|e| e.in_file(path))
}

/// A chunk's terrain resource (`xxx.cdata/terrain2`) is relative to the
/// chunk's folder.
fn load_terrain(
    chunk_path: &Path,
    resource: &str,
    origin: DVec3,
    chunk_size: f64,
) -> Result<TerrainBlock> {
    let resource = resources::normalise(resource);
    let Some((file, entry)) = resource
        .split_once(".cdata/")
        .map(|(stem, entry)| (format!("{stem}.cdata"), entry.to_string()))
    else {
        return Err(Error::invalid(
            chunk_path,
            format!("terrain resource `{resource}` does not name a .cdata entry (expected `NAME.cdata/terrain2`)"),
        ));
    };
    let dir = chunk_path.parent().unwrap_or(Path::new("."));
    // Engines write the name relative to the chunk folder; some tools write
    // it with the space folder prefixed, so the bare file name is tried too.
    let mut cdata_path = dir.join(&file);
    if !cdata_path.is_file() {
        if let Some(name) = Path::new(&file).file_name() {
            cdata_path = dir.join(name);
        }
    }
    let bytes = resources::read_file(&cdata_path)?;
    let data = terrain_format::read_terrain(&bytes, &entry).map_err(|e| e.in_file(&cdata_path))?;
    TerrainBlock::new(&data, origin, chunk_size)
        .map_err(|message| Error::invalid(&cdata_path, message))
}

/// Loads one model resource's LOD 0 geometry.
fn load_model(res_paths: &ResPaths, name: &str) -> Result<Model> {
    let _ = (res_paths, name);
    Err(Error::invalid(name, "model loading not implemented yet"))
}
