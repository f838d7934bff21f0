//! A distributed bake: the work split into shards that run on separate
//! machines (Slurm array tasks, Kubernetes Indexed Job pods, AWS Batch
//! array children), each writing a partial result, then merged.
//!
//! A *unit* is one light's range of texel tiles. The [`Plan`] cuts the
//! sequence of every light's tiles into `N` contiguous runs of about equal
//! *estimated* cost, a pure function of the scene, the settings and `N`, so
//! every shard computes the same plan on its own. A tile's cost is its rays,
//! weighted by how much of the tile what the light's top level holds covers
//! (placed parts and terrain blocks, by their projected boxes): a ray into
//! the world costs about the same for every light, a ray past everything
//! (the empty corners of a sun's grid, the sky of a point light) a tenth.
//!
//! Merging is an OR of caster sets (the grid pass is a union over tiles),
//! so it is order-free and a unit computed twice must agree. The [`merge`]
//! checks refuse anything that would silently give another answer than one
//! bake: partials of other inputs (the [`fingerprint`]: effective settings
//! plus the content hash of every file the load read), of another plan,
//! damaged, disagreeing duplicates, or missing shards. Refinement needs the
//! whole grid's answer, so it runs in `merge` (through
//! [`super::bake_from`]), never in a shard.

use super::cached::{BakeCache, PhaseCounts};
pub use super::config::settings_lines;
use super::config::BakeConfig;
use super::setup::{BakeWorld, LightSetup, NoSetup};
use super::trace_light::{
    tile_count, tile_rect, CasterSet, LightRays, RayCounter, TileReach, TILE,
};
use super::{grid_pass, BakeError, GridSource};
use crate::digest::Digest;
use crate::files::ResPaths;
use crate::formats::partial::{Fingerprint, Partial, PartialUnit};
use crate::light::{GridError, TexelGrid};
use crate::progress::{Counter, Phase, Progress};
use crate::scene::Scene;
use crate::trace::transform_box;
use glam::DVec3;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Estimated cost of a ray through a tile that nothing in reach covers
/// (it leaves the top level after a few boxes), relative to a ray that
/// enters the world. A ray that enters the world costs about the same
/// whatever the depth of boxes along it (the traversal stops behind the
/// front hits), so a tile's cost is its rays weighted by the fraction of
/// its texels some box covers, an empty ray counting this much of a
/// covered one (measured: see docs/performance.md). Tiles wholly outside
/// the projection of what the light reaches are not traced at all
/// ([`TileReach`]) and cost nothing; the empty rays left are those of tiles
/// at the edge of it.
const EMPTY_RAY_COST: f64 = 0.02;
/// Costs are integers (so sums do not depend on the order they are added
/// in) in these units per ray.
pub const COST_SCALE: f64 = 64.0;

/// Which shard of how many.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardIndex {
    pub index: u32,
    pub count: u32,
}

impl std::fmt::Display for ShardIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    #[error("--shard {given}: {why}")]
    Spec { given: String, why: String },
    #[error("--shard auto: {0}")]
    Auto(String),
    /// The merge refuses; nothing was written.
    #[error("merge refused, nothing written ({} problem(s)):{}", .0.len(), .0.iter().map(|p| format!("\n  {p}")).collect::<String>())]
    Refused(Vec<String>),
    #[error(transparent)]
    Bake(#[from] BakeError),
}

impl ShardIndex {
    /// `I/N` with `0 <= I < N`.
    pub fn parse(text: &str) -> Result<ShardIndex, ShardError> {
        let bad = |why: &str| ShardError::Spec {
            given: text.to_string(),
            why: why.to_string(),
        };
        let (i, n) = text
            .split_once('/')
            .ok_or_else(|| bad("give I/N (shard I of N, I from 0) or auto"))?;
        let index: u32 = i.trim().parse().map_err(|_| bad("I is not a number"))?;
        let count: u32 = n.trim().parse().map_err(|_| bad("N is not a number"))?;
        if count == 0 || index >= count {
            return Err(bad("needs N >= 1 and 0 <= I < N"));
        }
        Ok(ShardIndex { index, count })
    }
}

/// The shard an array job's task is, from its scheduler's variables, and a
/// sentence saying which variables it came from. Tried in order: Slurm
/// (`SLURM_ARRAY_TASK_ID` with `_MIN`, `_STEP`, `_COUNT`: task ids need not
/// start at 0 nor be consecutive, `--array=1-7:2` gives ids 1, 3, 5, 7 =
/// shards 0..3 of 4), Kubernetes (`JOB_COMPLETION_INDEX`, the count from
/// `shards`), AWS Batch (`AWS_BATCH_JOB_ARRAY_INDEX`, the count from
/// `AWS_BATCH_JOB_ARRAY_SIZE` or `shards`). `shards`, when given, must
/// agree with a count the scheduler gives.
pub fn shard_from_env(
    env: &dyn Fn(&str) -> Option<String>,
    shards: Option<u32>,
) -> Result<(ShardIndex, String), ShardError> {
    let number = |name: &str| -> Result<Option<i64>, ShardError> {
        env(name)
            .map(|v| {
                v.trim()
                    .parse::<i64>()
                    .map_err(|_| ShardError::Auto(format!("{name}={v} is not a whole number")))
            })
            .transpose()
    };
    let count_from = |scheduler: Option<i64>, name: &str| -> Result<u32, ShardError> {
        match (scheduler, shards) {
            (Some(c), Some(s)) if c != s as i64 => Err(ShardError::Auto(format!(
                "{name}={c} but --shards {s}; drop --shards or make them agree"
            ))),
            (Some(c), _) => u32::try_from(c)
                .ok()
                .filter(|&c| c > 0)
                .ok_or_else(|| ShardError::Auto(format!("{name}={c} is not a shard count"))),
            (None, Some(s)) => Ok(s),
            (None, None) => Err(ShardError::Auto(format!(
                "the scheduler gives no shard count ({name} is not set): add --shards N"
            ))),
        }
    };
    let make = |index: i64, count: u32, said: String| -> Result<(ShardIndex, String), ShardError> {
        if index < 0 || index >= count as i64 {
            return Err(ShardError::Auto(format!(
                "{said}: shard index {index} is not in 0..{count}"
            )));
        }
        let shard = ShardIndex {
            index: index as u32,
            count,
        };
        Ok((shard, format!("shard {shard} from {said}")))
    };
    if let Some(id) = number("SLURM_ARRAY_TASK_ID")? {
        let task_count = number("SLURM_ARRAY_TASK_COUNT")?;
        if task_count == Some(1) {
            if let Some(original) = resubmitted_array(env, shards)? {
                return make_resubmitted(id, original);
            }
        }
        let min = number("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
        let step = number("SLURM_ARRAY_TASK_STEP")?.unwrap_or(1).max(1);
        let count = count_from(task_count, "SLURM_ARRAY_TASK_COUNT")?;
        let said = format!("SLURM_ARRAY_TASK_ID={id} (min {min}, step {step}, count {count})");
        if (id - min) % step != 0 {
            return Err(ShardError::Auto(format!(
                "{said}: the id is not min + k·step; submit the array as a range --array=A-B[:S]"
            )));
        }
        return make((id - min) / step, count, said);
    }
    if let Some(index) = number("JOB_COMPLETION_INDEX")? {
        let count = count_from(None, "a Kubernetes Indexed Job's completions")?;
        return make(
            index,
            count,
            format!("JOB_COMPLETION_INDEX={index} (Kubernetes Indexed Job, --shards {count})"),
        );
    }
    if let Some(index) = number("AWS_BATCH_JOB_ARRAY_INDEX")? {
        let count = count_from(
            number("AWS_BATCH_JOB_ARRAY_SIZE")?,
            "AWS_BATCH_JOB_ARRAY_SIZE",
        )?;
        return make(
            index,
            count,
            format!("AWS_BATCH_JOB_ARRAY_INDEX={index} (AWS Batch, {count} shards)"),
        );
    }
    Err(ShardError::Auto(
        "none of SLURM_ARRAY_TASK_ID, JOB_COMPLETION_INDEX, AWS_BATCH_JOB_ARRAY_INDEX is set: run it as an array task or give --shard I/N".into(),
    ))
}

/// The variable naming a Slurm array's original ids (`A-B` or `A-B:S`),
/// for a task re-submitted alone (`sbatch --array=17`), whose own
/// `SLURM_ARRAY_TASK_*` describe a one-task array. `deploy/slurm` records
/// it beside the partials.
pub const ARRAY_VAR: &str = "SHADOWCULL_ARRAY";

/// The original ids of a Slurm array whose task was re-submitted alone: from
/// [`ARRAY_VAR`], else `0-(N-1)` when `--shards N` (N > 1) says the array
/// had more than this one task; `None` for a genuine one-task array.
fn resubmitted_array(
    env: &dyn Fn(&str) -> Option<String>,
    shards: Option<u32>,
) -> Result<Option<IdRange>, ShardError> {
    if let Some(text) = env(ARRAY_VAR) {
        let range = IdRange::parse(&text).ok_or_else(|| {
            ShardError::Auto(format!(
                "{ARRAY_VAR}={text} is not an array range A-B or A-B:S"
            ))
        })?;
        if let Some(n) = shards.filter(|&n| n != range.count()) {
            return Err(ShardError::Auto(format!(
                "{ARRAY_VAR}={text} has {} ids but --shards {n}; drop --shards or make them agree",
                range.count()
            )));
        }
        return Ok(Some(range));
    }
    Ok(shards.filter(|&n| n > 1).map(|n| IdRange {
        first: 0,
        last: n as i64 - 1,
        step: 1,
    }))
}

/// Shard of task `id`, re-submitted alone, of the array `original`.
fn make_resubmitted(id: i64, original: IdRange) -> Result<(ShardIndex, String), ShardError> {
    let said = format!(
        "SLURM_ARRAY_TASK_ID={id}, a task re-submitted alone of the array {original} ({} shards)",
        original.count()
    );
    match original.index_of(id) {
        Some(index) => {
            let shard = ShardIndex {
                index,
                count: original.count(),
            };
            Ok((shard, format!("shard {shard} from {said}")))
        }
        None => Err(ShardError::Auto(format!(
            "{said}: {id} is not one of its ids; re-submit with --array set to an id of {original}, or set {ARRAY_VAR} to the original array"
        ))),
    }
}

/// A Slurm array's ids `first..=last` every `step`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IdRange {
    first: i64,
    last: i64,
    step: i64,
}

impl IdRange {
    /// `A-B` or `A-B:S` (A ≤ B, S ≥ 1), as `sbatch --array` takes it.
    pub fn parse(text: &str) -> Option<IdRange> {
        let (range, step) = match text.trim().split_once(':') {
            Some((range, step)) => (range, step.parse().ok()?),
            None => (text.trim(), 1),
        };
        let (first, last) = range.split_once('-')?;
        let (first, last): (i64, i64) = (first.parse().ok()?, last.parse().ok()?);
        (first >= 0 && first <= last && step >= 1).then_some(IdRange { first, last, step })
    }

    /// How many ids (shards) it holds.
    pub fn count(&self) -> u32 {
        ((self.last - self.first) / self.step + 1) as u32
    }

    /// The shard index of task id `id`.
    fn index_of(&self, id: i64) -> Option<u32> {
        let inside = (self.first..=self.last).contains(&id) && (id - self.first) % self.step == 0;
        inside.then(|| ((id - self.first) / self.step) as u32)
    }
}

impl std::fmt::Display for IdRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}-{}", self.first, self.last)?;
        if self.step != 1 {
            write!(f, ":{}", self.step)?;
        }
        Ok(())
    }
}

/// One light's range of tiles.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unit {
    pub light: u32,
    pub tiles: Range<u64>,
}

/// Which units every shard bakes.
#[derive(Debug, Clone)]
pub struct Plan {
    pub shards: u32,
    /// Tiles of each light's grid (0: nothing to trace).
    pub tiles: Vec<u64>,
    /// Per shard: its units, in light then tile order.
    pub units: Vec<Vec<Unit>>,
    /// Per shard: its estimated cost (rays weighted by what they cross,
    /// ×[`COST_SCALE`]).
    pub costs: Vec<u64>,
    /// A hash of `shards`, `tiles` and `units`.
    pub digest: Digest,
}

impl Plan {
    /// The plan of `shards` shards: deterministic for a scene and settings.
    pub fn new(world: &BakeWorld, config: &BakeConfig, shards: u32) -> Result<Plan, BakeError> {
        super::check_light_count(config)?;
        let shards = shards.max(1);
        let mut light_costs = Vec::new();
        for light in &config.lights {
            let grid = match world.bounds.map(|b| TexelGrid::new(light, b)) {
                None => None,
                Some(Ok(grid)) => Some(grid.with_offset(config.grid_offset)),
                Some(Err(GridError::EmptyWorld { .. })) => None,
                Some(Err(err)) => return Err(err.into()),
            };
            light_costs.push(match grid {
                Some(grid) => tile_costs(world, config, &grid),
                None => Vec::new(),
            });
        }
        Ok(Plan::cut(shards, &light_costs))
    }

    /// Cuts the concatenation of every light's tiles into `shards`
    /// contiguous runs of about equal cost: a tile goes to the shard its
    /// cost's midpoint falls in.
    fn cut(shards: u32, light_costs: &[Vec<u64>]) -> Plan {
        let total: u128 = light_costs.iter().flatten().map(|&c| c as u128).sum();
        let mut units: Vec<Vec<Unit>> = vec![Vec::new(); shards as usize];
        let mut costs = vec![0u64; shards as usize];
        let mut before: u128 = 0;
        for (light, tile_costs) in light_costs.iter().enumerate() {
            for (tile, &cost) in tile_costs.iter().enumerate() {
                let middle = 2 * before + cost as u128;
                let shard = if total == 0 {
                    0
                } else {
                    ((middle * shards as u128) / (2 * total)).min(shards as u128 - 1) as usize
                };
                before += cost as u128;
                costs[shard] += cost;
                let tile = tile as u64;
                match units[shard].last_mut() {
                    Some(unit) if unit.light == light as u32 && unit.tiles.end == tile => {
                        unit.tiles.end = tile + 1
                    }
                    _ => units[shard].push(Unit {
                        light: light as u32,
                        tiles: tile..tile + 1,
                    }),
                }
            }
        }
        let tiles: Vec<u64> = light_costs.iter().map(|c| c.len() as u64).collect();
        let mut bytes = Vec::new();
        bytes.extend_from_slice(&shards.to_le_bytes());
        for t in &tiles {
            bytes.extend_from_slice(&t.to_le_bytes());
        }
        for (shard, list) in units.iter().enumerate() {
            for unit in list {
                for v in [
                    shard as u64,
                    unit.light as u64,
                    unit.tiles.start,
                    unit.tiles.end,
                ] {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        Plan {
            shards,
            tiles,
            units,
            costs,
            digest: Digest::of(&bytes),
        }
    }
}

/// The estimated cost of every tile of `grid` (see the module docs and
/// [`EMPTY_RAY_COST`]).
fn tile_costs(world: &BakeWorld, config: &BakeConfig, grid: &TexelGrid) -> Vec<u64> {
    let samples = (config.supersample.max(1) as f64).powi(2);
    let tiles = tile_count(grid);
    let scene = world.scene;
    let part_boxes = world.parts.par_iter().filter_map(|part| {
        let (min, max) = world.bottom.models[part.model].bounds()?;
        let placed = &scene.instances[part.instance].world;
        Some(transform_box(placed, min.as_dvec3(), max.as_dvec3()))
    });
    let block_boxes = scene.terrain.par_iter().map(|block| block.bounds());
    let boxes: Vec<(DVec3, DVec3)> = part_boxes
        .chain(block_boxes)
        .filter(|&(min, max)| grid.reaches(min, max))
        .collect();
    // The tiles the bake does not trace (`TileReach`: outside the
    // projection of the box of everything in reach) cost nothing.
    let reference = grid.reference_point();
    let union = boxes
        .iter()
        .fold(None, |acc: Option<(DVec3, DVec3)>, &(lo, hi)| {
            Some(acc.map_or((lo, hi), |(min, max)| (min.min(lo), max.max(hi))))
        });
    let reach = TileReach::of_box(
        grid,
        union.map(|(min, max)| {
            let magnitude = (min - reference)
                .abs()
                .max((max - reference).abs())
                .max_element();
            (min, max, magnitude)
        }),
    );
    let footprints: Vec<(usize, (f64, f64, f64, f64))> = boxes
        .into_par_iter()
        .flat_map_iter(|(min, max)| {
            (0..grid.faces())
                .filter_map(move |face| grid.footprint(face, min, max).map(|rect| (face, rect)))
        })
        .collect();
    // Texels covered by boxes, summed over boxes (in a fixed order: the
    // float sums are the same in every process).
    let mut covered = vec![0f64; tiles as usize];
    let tile = TILE as f64;
    let tiles_x = grid.width().div_ceil(TILE) as u64;
    let tiles_y = grid.height().div_ceil(TILE) as u64;
    for (face, (x0, y0, x1, y1)) in footprints {
        let rows = (y0 / tile) as u64..((y1 / tile).ceil() as u64).min(tiles_y);
        for ty in rows {
            let dy = y1.min((ty + 1) as f64 * tile) - y0.max(ty as f64 * tile);
            for tx in (x0 / tile) as u64..((x1 / tile).ceil() as u64).min(tiles_x) {
                let dx = x1.min((tx + 1) as f64 * tile) - x0.max(tx as f64 * tile);
                covered[((face as u64 * tiles_y + ty) * tiles_x + tx) as usize] += dx * dy;
            }
        }
    }
    // Consuming `covered` lets the costs reuse its allocation (same size
    // and alignment), so a grid at `light::MAX_TEXELS` (67 M tiles) needs
    // one 537 MB buffer here, not two.
    covered
        .into_iter()
        .enumerate()
        .map(|(t, area)| {
            let (_, x0, y0, x1, y1) = tile_rect(grid, t as u64);
            if !reach.may_hit((x0, y0, x1, y1)) {
                return 0;
            }
            let texels = ((x1 - x0) * (y1 - y0)) as f64;
            let full = (area / texels).min(1.0);
            let per_ray = EMPTY_RAY_COST + (1.0 - EMPTY_RAY_COST) * full;
            (texels * samples * per_ray * COST_SCALE).round() as u64
        })
        .collect()
}

/// The inputs of a bake, to compare between shards and the merge: the
/// settings that decide the grid's answer (supersampling, grid mode, filter
/// radius; refinement runs in the merge and is not among them) and every file the load read, by its name relative to
/// its res root (so machines mounting the roots elsewhere agree).
pub fn fingerprint(scene: &Scene, config: &BakeConfig, res_paths: &ResPaths) -> Fingerprint {
    let mut settings: String = settings_lines(config)
        .into_iter()
        .map(|(key, value)| format!("{key} = {value}\n"))
        .collect();
    if let Some(proxies) = speedtree_proxies_line(scene) {
        settings += &format!("speedtrees = {proxies}\n");
    }
    let mut files: Vec<(String, Digest)> = scene
        .inputs
        .iter()
        .map(|input| {
            let name = match res_paths.relative(&input.path) {
                Some((_, relative)) => relative.to_string_lossy().replace('\\', "/"),
                None => input.path.display().to_string(),
            };
            (name, input.digest)
        })
        .collect();
    files.sort();
    Fingerprint { settings, files }
}

/// The proxy every speedtree took, as a digest (`None`: the world has
/// none, and its fingerprint is as it was before speedtrees): the
/// `<speedtrees>` of the settings file shape the world but are no file
/// the load reads, so shards must prove they used the same.
fn speedtree_proxies_line(scene: &Scene) -> Option<String> {
    let trees = scene
        .instances
        .iter()
        .filter(|i| i.kind == crate::formats::chunk::InstanceKind::SpeedTree);
    let mut text = String::new();
    let mut count = 0;
    for tree in trees {
        let proxy = tree.parts.first().map_or("none", |part| {
            part.map_or("failed", |m| scene.models[m].resource.as_str())
        });
        text += &format!("{} {} {proxy}\n", scene.chunks[tree.chunk].name, tree.index);
        count += 1;
    }
    (count > 0).then(|| {
        format!(
            "{count} placements, proxies {}",
            Digest::of(text.as_bytes())
        )
    })
}

/// Bakes shard `shard` of `plan`: the answer of each of its units.
pub fn bake_shard(
    world: &BakeWorld,
    config: &BakeConfig,
    plan: &Plan,
    shard: u32,
    progress: &dyn Progress,
) -> Result<Vec<PartialUnit>, BakeError> {
    bake_shard_cached(world, config, plan, shard, progress, None).map(|(units, _)| units)
}

/// [`bake_shard`] with a cache when given (`BakeCache::trace_units`: each
/// unit's answer is the same); returns what the cache did too.
pub fn bake_shard_cached(
    world: &BakeWorld,
    config: &BakeConfig,
    plan: &Plan,
    shard: u32,
    progress: &dyn Progress,
    cache: Option<&BakeCache>,
) -> Result<(Vec<PartialUnit>, PhaseCounts), BakeError> {
    let mut counts = PhaseCounts::default();
    let units = plan.units.get(shard as usize).cloned().unwrap_or_default();
    let samples = config.supersample.max(1);
    let mut out = Vec::with_capacity(units.len());
    let mut by_light: BTreeMap<u32, Vec<Unit>> = BTreeMap::new();
    for unit in units {
        by_light.entry(unit.light).or_default().push(unit);
    }
    for (light, units) in by_light {
        let index = light as usize;
        let setup = match LightSetup::new_with_progress(world, config, index, progress) {
            Ok(setup) => Some(setup),
            Err(NoSetup::Grid(GridError::EmptyWorld { .. })) | Err(NoSetup::NoGeometry) => None,
            Err(NoSetup::Grid(err)) => return Err(err.into()),
        };
        let rays_of_light = setup
            .as_ref()
            .filter(|s| !s.is_empty())
            .map(|s| s.rays(world, config));
        let unit_rays = |unit: &Unit| -> u64 {
            let Some(setup) = &setup else { return 0 };
            unit.tiles
                .clone()
                .map(|t| {
                    let (_, x0, y0, x1, y1) = tile_rect(&setup.grid, t);
                    (x1 - x0) as u64 * (y1 - y0) as u64
                })
                .sum::<u64>()
                * (samples as u64).pow(2)
        };
        let total: u64 = units.iter().map(unit_rays).sum();
        let counter = Counter::begin(
            progress,
            Phase::Tracing,
            Some(&config.lights[index].name),
            total,
        );
        let mut cached: Vec<CasterSet> = Vec::new();
        if let (Some(cache), Some(setup), Some(rays)) = (cache, &setup, &rays_of_light) {
            let ranges: Vec<Range<u64>> = units.iter().map(|u| u.tiles.clone()).collect();
            let (answers, done) = cache.trace_units(world, setup, rays, config, &ranges, &counter);
            counts.add(done);
            cached = answers;
        }
        let mut cached = cached.into_iter();
        for unit in units {
            let unit_started = Instant::now();
            let useful = match (&setup, &rays_of_light, cached.next()) {
                (_, _, Some(answer)) => answer,
                (Some(setup), Some(rays), None) => grid_pass::trace_tiles(
                    world,
                    setup,
                    rays,
                    config,
                    unit.tiles.clone(),
                    None,
                    &counter,
                ),
                _ => CasterSet::new(world.casters.len()),
            };
            out.push(PartialUnit {
                light,
                start: unit.tiles.start,
                end: unit.tiles.end,
                rays: if rays_of_light.is_some() {
                    unit_rays(&unit)
                } else {
                    0
                },
                seconds: unit_started.elapsed().as_secs_f64(),
                words: useful.words().to_vec(),
            });
        }
        counter.finish();
    }
    Ok((out, counts))
}

/// The grid answers of every light, OR-ed from checked partials.
pub struct Merged {
    per_light: Vec<Option<CasterSet>>,
    /// Per light, the seconds the shards spent tracing its units (one copy
    /// of a retried shard): its report's trace time and ray rate are the
    /// shards', not the merge's.
    seconds: Vec<f64>,
    casters: usize,
}

impl GridSource for Merged {
    fn grid(
        &self,
        _world: &BakeWorld,
        setup: &LightSetup,
        _rays_of_light: &LightRays<'_>,
        _config: &BakeConfig,
        _rays_done: &dyn RayCounter,
    ) -> CasterSet {
        self.per_light
            .get(setup.index)
            .cloned()
            .flatten()
            .unwrap_or_else(|| CasterSet::new(self.casters))
    }

    fn seconds_before(&self, index: usize) -> f64 {
        self.seconds.get(index).copied().unwrap_or(0.0)
    }
}

/// Checks `partials` (file, content) against this merge's own fingerprint
/// and the plan of as many shards as they name, and ORs their units. Every
/// problem names its files; any problem refuses the whole merge. `command`
/// is how to re-run a shard, for the message about missing ones; `locate`
/// says where one of this merge's settings is set (`file:line`), when it
/// can, for the message about partials made from other settings.
pub fn merge(
    world: &BakeWorld,
    config: &BakeConfig,
    own: &Fingerprint,
    partials: &[(PathBuf, Partial)],
    command: &str,
    locate: &dyn Fn(&str) -> Option<String>,
) -> Result<(Merged, Plan), ShardError> {
    let shards = partials.first().map_or(1, |(_, p)| p.shards).max(1);
    let plan = Plan::new(world, config, shards)?;
    let expected = Expected {
        own,
        plan: &plan,
        casters: world.casters.len(),
        locate,
    };
    let (seen, mut problems) = expected.one_partial_per_shard(partials);
    // A shard whose partial was refused is not missing: its refusal says
    // what to do.
    let given: std::collections::BTreeSet<u32> = partials.iter().map(|(_, p)| p.shard).collect();
    let missing: Vec<u32> = (0..shards)
        .filter(|s| !given.contains(s) && !seen.contains_key(s))
        .filter(|s| !plan.units[*s as usize].is_empty())
        .collect();
    if !missing.is_empty() {
        problems.push(missing_shards(&missing, shards, command));
    }
    if !problems.is_empty() {
        return Err(ShardError::Refused(problems));
    }
    let merged = Merged::of(config, expected.casters, &seen)?;
    Ok((merged, plan))
}

/// What every partial of a merge must agree with.
struct Expected<'m> {
    own: &'m Fingerprint,
    /// This merge's plan, of as many shards as the first partial names.
    plan: &'m Plan,
    casters: usize,
    /// Where one of this merge's settings is set.
    locate: &'m dyn Fn(&str) -> Option<String>,
}

/// Per shard, the file and content of its first partial that agrees with
/// the merge.
type PerShard<'p> = BTreeMap<u32, (&'p PathBuf, &'p Partial)>;

impl Expected<'_> {
    /// The first partial of each shard that agrees with the merge, and the
    /// problems of the others (a retried shard agrees only if its answer
    /// is the first's).
    fn one_partial_per_shard<'p>(
        &self,
        partials: &'p [(PathBuf, Partial)],
    ) -> (PerShard<'p>, Vec<String>) {
        let shards = self.plan.shards;
        let mut problems = Vec::new();
        // Partials refused for one reason are named together, the reason
        // said once.
        let mut refused: Vec<(String, Vec<String>)> = Vec::new();
        let mut seen = PerShard::new();
        for (path, partial) in partials {
            if let Some(why) = self.refusal(partial, &partials[0].0) {
                let name = path.display().to_string();
                match refused.iter_mut().find(|(reason, _)| *reason == why) {
                    Some((_, names)) => names.push(name),
                    None => refused.push((why, vec![name])),
                }
                continue;
            }
            match seen.get(&partial.shard) {
                // A retried shard: its units must give the same answer.
                Some((first, earlier)) => {
                    let disagrees = earlier
                        .units
                        .iter()
                        .zip(&partial.units)
                        .any(|(a, b)| a.words != b.words);
                    if disagrees {
                        problems.push(format!(
                            "{} and {}: both are shard {}/{shards} but their answers differ: delete the wrong one and re-run that shard",
                            path.display(),
                            first.display(),
                            partial.shard
                        ));
                    }
                }
                None => {
                    seen.insert(partial.shard, (path, partial));
                }
            }
        }
        let refusals = refused
            .into_iter()
            .map(|(why, names)| format!("{}: {why}", names.join(", ")));
        (seen, refusals.chain(problems).collect())
    }

    /// Why `partial` cannot be merged here, if it cannot: made from other inputs, of another split than the first
    /// partial's (read from `first`), or by another plan.
    fn refusal(&self, partial: &Partial, first: &Path) -> Option<String> {
        let shards = self.plan.shards;
        if let Some(why) = fingerprint_difference(self.own, &partial.fingerprint, self.locate) {
            return Some(format!("made from other inputs than this merge: {why}"));
        }
        if partial.shards != shards {
            return Some(format!(
                "of another split ({} shards) than {} ({shards} shards): merge the partials of one split",
                partial.shards,
                first.display(),
            ));
        }
        let expected_units = self.plan.units.get(partial.shard as usize);
        let units_match = expected_units.is_some_and(|units| {
            units.len() == partial.units.len()
                && units.iter().zip(&partial.units).all(|(u, p)| {
                    u.light == p.light && u.tiles.start == p.start && u.tiles.end == p.end
                })
        });
        if partial.plan != self.plan.digest
            || !units_match
            || partial.casters != self.casters as u64
        {
            return Some(format!(
                "its plan differs from this merge's plan of {shards} shards (made by another shadowcull?)"
            ));
        }
        None
    }
}

/// The problem of shards `missing` of `shards`, with how to bake them
/// (`command`).
fn missing_shards(missing: &[u32], shards: u32, command: &str) -> String {
    format!(
        "missing shard(s) {} of {shards}: their units are in no partial given; bake each with `{command} --shard I/{shards} --partial FILE` and merge again",
        missing
            .iter()
            .map(|s| s.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    )
}

impl Merged {
    /// Every unit of the partials `seen` (one per shard) OR-ed into its
    /// light's answer, and their trace seconds summed per light.
    fn of(config: &BakeConfig, casters: usize, seen: &PerShard<'_>) -> Result<Merged, ShardError> {
        let mut per_light: Vec<Option<CasterSet>> = vec![None; config.lights.len()];
        let mut seconds = vec![0.0; config.lights.len()];
        for (path, partial) in seen.values() {
            for unit in &partial.units {
                let set = CasterSet::from_words(casters, unit.words.clone()).ok_or_else(|| {
                    ShardError::Refused(vec![format!(
                        "{}: a unit's caster bits do not fit the {casters} casters",
                        path.display()
                    )])
                })?;
                let slot = per_light.get_mut(unit.light as usize).ok_or_else(|| {
                    ShardError::Refused(vec![format!(
                        "{}: names light {} of {}",
                        path.display(),
                        unit.light,
                        config.lights.len()
                    )])
                })?;
                *slot = Some(match slot.take() {
                    Some(acc) => acc.union(&set),
                    None => set,
                });
                // A time is information, not an answer: a nonsense one counts 0.
                if unit.seconds.is_finite() && unit.seconds > 0.0 {
                    seconds[unit.light as usize] += unit.seconds;
                }
            }
        }
        Ok(Merged {
            per_light,
            seconds,
            casters,
        })
    }
}

/// Why two fingerprints differ, in a sentence, or `None` when they agree.
/// `locate` says where a setting of this merge comes from (`file:line`),
/// when it can.
fn fingerprint_difference(
    own: &Fingerprint,
    theirs: &Fingerprint,
    locate: &dyn Fn(&str) -> Option<String>,
) -> Option<String> {
    if own.settings != theirs.settings {
        return Some(settings_difference(&own.settings, &theirs.settings, locate));
    }
    if own.files == theirs.files {
        return None;
    }
    let ours: BTreeMap<&str, Digest> = own.files.iter().map(|(n, d)| (n.as_str(), *d)).collect();
    let them: BTreeMap<&str, Digest> = theirs.files.iter().map(|(n, d)| (n.as_str(), *d)).collect();
    let mut differences: Vec<String> = Vec::new();
    for (name, digest) in &ours {
        match them.get(name) {
            Some(d) if d == digest => {}
            Some(_) => differences.push(format!("{name} has other content")),
            None => differences.push(format!("{name} was not read by the shard")),
        }
    }
    for name in them.keys().filter(|n| !ours.contains_key(*n)) {
        differences.push(format!("{name} was read by the shard only"));
    }
    let count = differences.len();
    differences.truncate(5);
    Some(format!(
        "{count} input file(s) differ: {}{}; bake every shard and merge from the same files",
        differences.join(", "),
        if count > 5 { ", …" } else { "" }
    ))
}

/// The first setting that differs between this merge's `own` settings
/// lines and a partial's (`theirs`), as the element (or flag), both values
/// and where this merge's value is set.
fn settings_difference(own: &str, theirs: &str, locate: &dyn Fn(&str) -> Option<String>) -> String {
    let pairs = |text: &str| -> BTreeMap<String, String> {
        text.lines()
            .filter_map(|line| line.split_once(" = "))
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    };
    let (ours, them) = (pairs(own), pairs(theirs));
    let order = own
        .lines()
        .chain(theirs.lines())
        .filter_map(|l| l.split_once(" = "));
    let differing = order
        .map(|(key, _)| key)
        .find(|key| ours.get(*key) != them.get(*key));
    let said = match differing {
        Some(key) => {
            let value = |v: Option<&String>| match v {
                Some(v) => format!("`{v}`"),
                None => "not set".to_string(),
            };
            let element =
                if key.starts_with("--") || !key.chars().next().is_some_and(char::is_alphabetic) {
                    key.to_string()
                } else {
                    format!("<{key}>")
                };
            let place = locate(key).map(|at| format!(" ({at})")).unwrap_or_default();
            format!(
                "{element} is {} in the partial but {} in this merge{place}",
                value(them.get(key)),
                value(ours.get(key))
            )
        }
        None => "the settings are written differently (another shadowcull?)".into(),
    };
    format!("settings differ: {said}; give merge the settings file and flags the shards had")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env<'a>(vars: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |name| {
            vars.iter()
                .find(|(n, _)| *n == name)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn slurm_ids_need_not_start_at_zero() {
        // --array=1-7:2 gives ids 1, 3, 5, 7: shards 0..3 of 4.
        for (id, index) in [("1", 0), ("3", 1), ("5", 2), ("7", 3)] {
            let vars = [
                ("SLURM_ARRAY_TASK_ID", id),
                ("SLURM_ARRAY_TASK_MIN", "1"),
                ("SLURM_ARRAY_TASK_STEP", "2"),
                ("SLURM_ARRAY_TASK_COUNT", "4"),
            ];
            let (shard, said) = shard_from_env(&env(&vars), None).unwrap();
            assert_eq!(shard, ShardIndex { index, count: 4 });
            assert!(said.contains("SLURM_ARRAY_TASK_ID"), "{said}");
        }
        let between = [
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
            ("SLURM_ARRAY_TASK_STEP", "2"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ];
        assert!(shard_from_env(&env(&between), None).is_err());
        let counted = [
            ("SLURM_ARRAY_TASK_ID", "0"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ];
        assert!(
            shard_from_env(&env(&counted), Some(5)).is_err(),
            "counts disagree"
        );
        assert_eq!(
            shard_from_env(&env(&counted), Some(4)).unwrap().0,
            ShardIndex { index: 0, count: 4 }
        );
        let past = [
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ];
        assert!(shard_from_env(&env(&past), None).is_err());
        let garbage = [("SLURM_ARRAY_TASK_ID", "x")];
        assert!(shard_from_env(&env(&garbage), Some(2)).is_err());
    }

    #[test]
    fn a_slurm_task_resubmitted_alone_is_its_shard_of_the_original_array() {
        // `sbatch --array=17 shard.sbatch`: Slurm describes a one-task array.
        let alone = |id: &'static str| {
            [
                ("SLURM_ARRAY_TASK_ID", id),
                ("SLURM_ARRAY_TASK_MIN", id),
                ("SLURM_ARRAY_TASK_MAX", id),
                ("SLURM_ARRAY_TASK_STEP", "1"),
                ("SLURM_ARRAY_TASK_COUNT", "1"),
            ]
        };
        // With --shards N: the array was 0-(N-1).
        let (shard, said) = shard_from_env(&env(&alone("17")), Some(64)).unwrap();
        assert_eq!(
            shard,
            ShardIndex {
                index: 17,
                count: 64
            }
        );
        assert!(said.contains("re-submitted"), "{said}");
        // With the recorded array (ids need not start at 0).
        let mut recorded = alone("5").to_vec();
        recorded.push((ARRAY_VAR, "1-7:2"));
        let (shard, _) = shard_from_env(&env(&recorded), None).unwrap();
        assert_eq!(shard, ShardIndex { index: 2, count: 4 });
        assert!(
            shard_from_env(&env(&recorded), Some(3)).is_err(),
            "4 ids, not 3"
        );
        // An id the original array never had.
        let mut foreign = alone("4").to_vec();
        foreign.push((ARRAY_VAR, "1-7:2"));
        let err = shard_from_env(&env(&foreign), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("1-7:2"), "{err}");
        assert!(shard_from_env(&env(&alone("64")), Some(64)).is_err());
        // A genuine one-task array is one shard, as before.
        let (shard, _) = shard_from_env(&env(&alone("0")), None).unwrap();
        assert_eq!(shard, ShardIndex { index: 0, count: 1 });
    }

    #[test]
    fn array_ranges_parse_as_sbatch_writes_them() {
        let range = IdRange::parse("1-7:2").unwrap();
        assert_eq!(range.count(), 4);
        assert_eq!(range.to_string(), "1-7:2");
        assert_eq!(IdRange::parse("0-63").unwrap().count(), 64);
        for bad in ["", "7-1", "1-7:0", "a-b", "3", "-1-4"] {
            assert!(IdRange::parse(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn kubernetes_needs_the_count_and_aws_gives_it() {
        let k8s = [("JOB_COMPLETION_INDEX", "2")];
        assert!(shard_from_env(&env(&k8s), None).is_err());
        assert_eq!(
            shard_from_env(&env(&k8s), Some(3)).unwrap().0,
            ShardIndex { index: 2, count: 3 }
        );
        let aws = [
            ("AWS_BATCH_JOB_ARRAY_INDEX", "6"),
            ("AWS_BATCH_JOB_ARRAY_SIZE", "7"),
        ];
        assert_eq!(
            shard_from_env(&env(&aws), None).unwrap().0,
            ShardIndex { index: 6, count: 7 }
        );
        assert!(shard_from_env(&env(&[]), Some(3)).is_err());
    }

    #[test]
    fn shard_index_parse() {
        assert_eq!(
            ShardIndex::parse("2/7").unwrap(),
            ShardIndex { index: 2, count: 7 }
        );
        for bad in ["7/7", "-1/3", "1", "a/b", "0/0", ""] {
            assert!(ShardIndex::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_cut_partitions_every_light_and_balances_cost() {
        let rng = |i: u64| crate::rng::mix(i) % 1000;
        let lights: Vec<Vec<u64>> = vec![
            (0..500).map(rng).collect(),
            Vec::new(),
            (500..530).map(rng).collect(),
            (600..1400).map(|i| rng(i) * (i % 7)).collect(),
        ];
        for shards in [1, 2, 3, 7, 64, 2000] {
            let plan = Plan::cut(shards, &lights);
            for (light, costs) in lights.iter().enumerate() {
                let mut covered: Vec<Range<u64>> = plan
                    .units
                    .iter()
                    .flatten()
                    .filter(|u| u.light == light as u32)
                    .map(|u| u.tiles.clone())
                    .collect();
                covered.sort_by_key(|r| r.start);
                let mut next = 0;
                for range in covered {
                    assert_eq!(range.start, next, "{shards} shards, light {light}");
                    assert!(range.end > range.start);
                    next = range.end;
                }
                assert_eq!(next, costs.len() as u64, "{shards} shards, light {light}");
            }
            let total: u64 = lights.iter().flatten().sum();
            assert_eq!(plan.costs.iter().sum::<u64>(), total);
            let biggest = *lights.iter().flatten().max().unwrap();
            for cost in &plan.costs {
                assert!(
                    (*cost as f64) <= total as f64 / shards as f64 + biggest as f64,
                    "{shards} shards: {cost} vs mean {}",
                    total / shards as u64
                );
            }
            assert_eq!(Plan::cut(shards, &lights).digest, plan.digest);
        }
        assert_ne!(Plan::cut(3, &lights).digest, Plan::cut(4, &lights).digest);
    }
}
