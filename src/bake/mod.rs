//! The bake: for each light, its texel grid, a BVH over what it reaches,
//! one ray per texel, and the casters the rays prove useful; then the masks
//! per group, instance and terrain block. Orchestration only: the rules are
//! in `classify`, the rays in `light`, the traversal in `trace`.

pub mod cache_keys;
pub mod cached;
pub mod casters;
pub mod cells;
pub mod config;
pub mod conservative;
pub mod estimate;
pub mod filter_margin;
pub mod geometry;
pub mod grid_pass;
pub mod ground;
pub mod manifest;
pub mod memory;
pub mod occlusion;
pub mod output;
pub mod refine;
pub mod savings;
pub mod setup;
pub mod shard;
pub mod texel_beam;
pub mod trace_light;
pub mod world_record;

use crate::classify::Passes;
use crate::formats::chunk::InstanceKind;
use crate::progress::{Counter, Phase};
use crate::scene::items::plural;
use crate::scene::{Scene, Treatment};
use casters::CasterTable;
pub use config::{BakeConfig, GridMode};
use rayon::prelude::*;
use setup::{BakeWorld, LightSetup, NoSetup};
use std::sync::Arc;
use std::time::Instant;
use trace_light::{CasterSet, LightRays, RayCounter};

pub use crate::progress::{Progress, Silent};

#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LightReport {
    /// Position among the lights baked.
    pub index: usize,
    /// Its bit in the masks.
    pub bit: u32,
    pub name: String,
    pub kind: &'static str,
    /// Texel rays (texels × supersample²) plus refinement rays.
    pub rays: u64,
    /// Of `rays`, those aimed at casters' own surfaces (`refine`).
    pub refine_rays: u64,
    /// Wall time for the light in all: reach + top level + tracing.
    pub seconds: f64,
    /// Finding the parts and blocks in reach.
    pub geometry_seconds: f64,
    /// Building the light's top level (the bottom levels are shared: see
    /// [`BakeResult::bottom_level_seconds`]).
    pub bvh_seconds: f64,
    /// Tracing: the grid pass and refinement.
    pub trace_seconds: f64,
    /// Of `trace_seconds`, refinement's (`--refine`).
    pub refine_seconds: f64,
    pub useful_casters: usize,
    pub culled_casters: usize,
    /// Triangles in the light's reach (placed model triangles plus two per
    /// terrain cell), traced through instances and height fields.
    pub triangles: usize,
    /// Placed model parts in the light's top level.
    pub instances: usize,
    pub terrain_blocks: usize,
    /// Both passes (All and Opaque) or only All.
    pub passes: usize,
    /// The light's shadow pass before and after culling.
    pub savings: savings::Savings,
}

/// Something the bake left out, and why.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
pub struct Skipped {
    pub what: String,
    pub why: String,
    pub severity: Severity,
}

/// Whether a skipped entry lost something.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// Work saved or nothing that casts, nothing lost (one pass instead
    /// of two, a light that reaches nothing, geometry outside a light's
    /// reach, chunk items that draw into no shadow map).
    Info,
    /// Casters the bake cannot model, kept for every light (no shadow is
    /// lost, but they are never culled and hide nothing), or item kinds
    /// it does not know (whether they cast is unknown).
    Warning,
    /// Input the bake could not use: its verdicts may be wrong.
    Error,
}

impl Skipped {
    pub fn info(what: impl Into<String>, why: impl Into<String>) -> Skipped {
        Skipped {
            what: what.into(),
            why: why.into(),
            severity: Severity::Info,
        }
    }

    pub fn warning(what: impl Into<String>, why: impl Into<String>) -> Skipped {
        Skipped {
            what: what.into(),
            why: why.into(),
            severity: Severity::Warning,
        }
    }

    pub fn error(what: impl Into<String>, why: impl Into<String>) -> Skipped {
        Skipped {
            what: what.into(),
            why: why.into(),
            severity: Severity::Error,
        }
    }
}

#[derive(Debug, Clone)]
pub struct BakeResult {
    /// Wall time of building the bottom levels, once for every light.
    pub bottom_level_seconds: f64,
    /// Heap bytes of the bottom levels.
    pub bottom_level_bytes: usize,
    pub casters: Arc<CasterTable>,
    /// Per caster id: bit `config.bit(i)` set = useful for light i.
    pub masks: Vec<u32>,
    /// The bits this bake decided ([`BakeConfig::baked_bits`]); the others
    /// of every mask are zero here and kept from the chunk files on output.
    pub baked_bits: u32,
    pub lights: Vec<LightReport>,
    pub skipped: Vec<Skipped>,
    /// What a bake with a cache reused and computed (`None`: no cache).
    pub cache: Option<cached::CacheReport>,
}

#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    #[error("{count} lights: at most 32 fit the 32-bit mask; split the bake into several settings files")]
    TooManyLights { count: usize },
    /// A light whose grid cannot be made (too large, invalid values): a
    /// settings mistake, so the bake stops rather than skipping it.
    #[error(transparent)]
    Grid(#[from] crate::light::GridError),
    /// Every light whose grid cannot be made, found before any is traced.
    #[error("{} light(s) cannot be baked; nothing was traced:{}", .0.len(), .0.iter().map(|e| format!("\n  {e}")).collect::<String>())]
    Grids(Vec<crate::light::GridError>),
    /// A large allocation failed: the machine (or its limit) has too
    /// little memory for this phase.
    #[error("out of memory while {phase}: {bytes} bytes could not be allocated; bake fewer lights at a time (--light), coarsen <texelSize>/<resolution>, or use a machine with more memory")]
    OutOfMemory { phase: &'static str, bytes: usize },
}

/// A zeroed vector of `len` values, or [`BakeError::OutOfMemory`] naming
/// `phase` (a failed allocation must not abort the process).
pub fn try_zeroed<T: Clone + Default>(
    len: usize,
    phase: &'static str,
) -> Result<Vec<T>, BakeError> {
    let mut v = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| BakeError::OutOfMemory {
            phase,
            bytes: len.saturating_mul(std::mem::size_of::<T>()),
        })?;
    v.resize(len, T::default());
    Ok(v)
}

/// Checks every light's grid against the world's bounds before anything
/// is built or traced: a settings mistake in the last light must not cost
/// the time of the first. Lights with nothing to cover are not errors.
/// `bounds` are the world's (`geometry::world_bounds`).
pub fn validate_lights(
    bounds: Option<(glam::DVec3, glam::DVec3)>,
    config: &BakeConfig,
) -> Result<(), BakeError> {
    check_light_count(config)?;
    let Some(bounds) = bounds else {
        return Ok(());
    };
    let errors: Vec<crate::light::GridError> = config
        .lights
        .iter()
        .filter_map(|light| {
            crate::light::TexelGrid::new(light, bounds)
                .map(|grid| grid.with_offset(config.grid_offset))
                .err()
        })
        .filter(|e| !matches!(e, crate::light::GridError::EmptyWorld { .. }))
        .collect();
    if errors.is_empty() {
        Ok(())
    } else {
        Err(BakeError::Grids(errors))
    }
}

/// The world `config`'s lights are baked over, each light's grid checked
/// first ([`validate_lights`]): the world's bounds found once for both (a
/// pass over every placed part).
pub fn checked_world<'a>(
    scene: &'a Scene,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> Result<BakeWorld<'a>, BakeError> {
    let bounds = geometry::world_bounds(scene);
    validate_lights(bounds, config)?;
    Ok(BakeWorld::within(scene, bounds, progress))
}

/// Where a light's grid answer comes from: traced here ([`TraceGrid`]), or
/// the OR of a distributed bake's partial results (`shard::Merged`).
/// Everything else about a light (its notes, refinement, its report) is
/// the same either way, so a merge writes what one bake writes.
pub trait GridSource: Sync {
    /// The casters the grid's rays prove useful for the light of `setup`
    /// (receiver-only ones included; the caller drops them).
    fn grid(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        config: &BakeConfig,
        rays_done: &dyn RayCounter,
    ) -> CasterSet;

    /// Seconds already spent tracing part of light `index`'s grid before
    /// the bake (the plan's calibration tiles), counted in its report so
    /// its ray rate stays honest.
    fn seconds_before(&self, _index: usize) -> f64 {
        0.0
    }

    /// Light `index`'s setup, when the source already built it for
    /// `config` (the plan's last-built light); `None`: the bake builds it.
    fn take_setup(&self, _index: usize, _config: &BakeConfig) -> Option<LightSetup> {
        None
    }

    /// Light `index`'s setup, as [`Phase::TopLevel`] of `progress`: the
    /// whole reach under its top level unless the source traces less.
    fn build_setup(
        &self,
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
        progress: &dyn Progress,
    ) -> Result<LightSetup, NoSetup> {
        LightSetup::new_with_progress(world, config, index, progress)
    }
}

/// Traces every texel of the grid.
pub struct TraceGrid;

impl GridSource for TraceGrid {
    fn grid(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        config: &BakeConfig,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let tiles = 0..rays_of_light.tile_count();
        grid_pass::trace_tiles(world, setup, rays_of_light, config, tiles, None, rays_done)
    }
}

pub fn bake(
    scene: &Scene,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> Result<BakeResult, BakeError> {
    let world = checked_world(scene, config, progress)?;
    bake_world(&world, config, progress)
}

/// Bakes `config`'s lights over a world whose bottom levels are built
/// (`plan` and `bake` share one [`BakeWorld`], made by [`checked_world`]).
pub fn bake_world(
    world: &BakeWorld,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> Result<BakeResult, BakeError> {
    bake_from(world, config, progress, &TraceGrid)
}

/// At most 32 lights fit the mask.
pub fn check_light_count(config: &BakeConfig) -> Result<(), BakeError> {
    if config.lights.len() > 32 {
        return Err(BakeError::TooManyLights {
            count: config.lights.len(),
        });
    }
    Ok(())
}

/// [`bake_world`] with the grid answers from `source` (traced here, or a
/// distributed bake's merged partials).
pub fn bake_from(
    world: &BakeWorld,
    config: &BakeConfig,
    progress: &dyn Progress,
    source: &dyn GridSource,
) -> Result<BakeResult, BakeError> {
    bake_with(world, config, progress, source, None)
}

/// [`bake_world`] with a cache: every grid answer the union of its cells'
/// (reused or traced and stored), refinement reused or refined per chunk
/// and stored. The masks are [`bake_world`]'s (see [`cached`]).
pub fn bake_cached(
    world: &BakeWorld,
    config: &BakeConfig,
    progress: &dyn Progress,
    cache: &cached::BakeCache,
) -> Result<BakeResult, BakeError> {
    bake_with(world, config, progress, cache, Some(cache))
}

/// [`bake_from`], with refinement through `cache` when given (a merge's:
/// its grid answers are the shards').
pub fn bake_with(
    world: &BakeWorld,
    config: &BakeConfig,
    progress: &dyn Progress,
    source: &dyn GridSource,
    cache: Option<&cached::BakeCache>,
) -> Result<BakeResult, BakeError> {
    check_light_count(config)?;
    let mut masks = try_zeroed::<u32>(world.casters.len(), "making the caster masks")?;
    let mut skipped = world_skipped(world);
    let mut lights = Vec::new();
    for index in 0..config.lights.len() {
        let prepared = source.take_setup(index, config).map(Ok);
        let built = || source.build_setup(world, config, index, progress);
        let setup = match prepared.unwrap_or_else(built) {
            Ok(setup) => setup,
            Err(nothing) if nothing.is_nothing_to_trace() => {
                skipped.push(Skipped::info(
                    light_name(config, index),
                    nothing.to_string(),
                ));
                continue;
            }
            Err(NoSetup::Grid(err)) => return Err(err.into()),
            Err(NoSetup::NoGeometry) => unreachable!("no geometry is nothing to trace"),
        };
        let (useful, report) =
            bake_light_from(world, &setup, config, progress, &mut skipped, source, cache);
        let bit = 1u32.wrapping_shl(config.bit(index));
        // Word by word: a large world has millions of ids, few of them set.
        masks
            .par_chunks_mut(64)
            .zip(useful.words().par_iter())
            .for_each(|(masks, &word)| {
                let mut rest = word;
                while rest != 0 {
                    masks[rest.trailing_zeros() as usize] |= bit;
                    rest &= rest - 1;
                }
            });
        lights.push(report);
    }
    // Kept for every light the bake decides, traced or not.
    for id in world.casters.unmodelled() {
        masks[id as usize] |= config.baked_bits();
    }
    skipped.sort();
    Ok(BakeResult {
        bottom_level_seconds: world.bottom_seconds,
        bottom_level_bytes: world.bottom.heap_bytes(),
        casters: Arc::clone(&world.casters),
        masks,
        baked_bits: config.baked_bits(),
        lights,
        skipped,
        cache: cache.map(cached::BakeCache::report),
    })
}

fn light_name(config: &BakeConfig, index: usize) -> String {
    format!("light {index} ({})", config.lights[index].name)
}

/// What the world itself leaves out, whatever the light.
fn world_skipped(world: &BakeWorld) -> Vec<Skipped> {
    let scene = world.scene;
    let mut skipped: Vec<Skipped> = scene
        .problems
        .iter()
        .map(|p| Skipped::error(p.what.clone(), p.why.clone()))
        .collect();
    for (index, instance) in scene.instances.iter().enumerate() {
        if world.casters.first_of_instance[index].is_none() {
            let chunk = &scene.chunks[instance.chunk];
            let (what, part) = match instance.kind {
                InstanceKind::SpeedTree => ("speedtree", "its proxy model"),
                InstanceKind::Model | InstanceKind::Shell => ("instance", "a <resource> part"),
            };
            skipped.push(Skipped::error(
                format!(
                    "{} {what} {} ({})",
                    chunk.name,
                    instance.index,
                    instance.resources.join(", ")
                ),
                format!("{part} did not load (see its problem); its <shadow> is left as it was"),
            ));
        }
    }
    skipped.extend(items_skipped(scene));
    if world.ground.is_none() {
        skipped.push(Skipped::info(
            "below-ground test",
            "the world has no terrain: no height tests",
        ));
    }
    skipped
}

/// The chunk items the bake leaves out, per kind (docs/contract.md §2),
/// and the speedtrees it cannot model, per `.spt`.
fn items_skipped(scene: &Scene) -> Vec<Skipped> {
    let mut skipped = Vec::new();
    for item in scene.item_entries() {
        let chunks = plural(item.chunks, "chunk", "chunks");
        let what = format!("{} <{}> in {chunks}", item.count, item.kind);
        let why = format!("{}: {}", item.treatment.label(), item.why);
        match item.treatment {
            Treatment::Modelled | Treatment::ChunkData => {}
            Treatment::ReceivesOnly | Treatment::NotGeometry => {
                skipped.push(Skipped::info(what, why))
            }
            Treatment::Unknown => skipped.push(Skipped::warning(what, why)),
        }
    }
    for trees in scene.unproxied_trees() {
        skipped.push(Skipped::warning(
            format!(
                "{}: {} in {}",
                trees.spt,
                plural(trees.placements, "<speedtree> placement", "<speedtree> placements"),
                plural(trees.chunks, "chunk", "chunks")
            ),
            "no proxy in <speedtrees> matches the .spt (docs/contract.md §3): kept for every light, they occlude nothing",
        ));
    }
    skipped
}

/// Traces one prepared light: its grid (supersampled as configured) and
/// refinement. Returns the casters it proves useful (receiver-only groups
/// never count) and its report; notes what it left out in `skipped`.
pub fn bake_light(
    world: &BakeWorld,
    setup: &LightSetup,
    config: &BakeConfig,
    progress: &dyn Progress,
    skipped: &mut Vec<Skipped>,
) -> (CasterSet, LightReport) {
    bake_light_from(world, setup, config, progress, skipped, &TraceGrid, None)
}

/// [`bake_light`] with the grid answer from `source`.
fn bake_light_from(
    world: &BakeWorld,
    setup: &LightSetup,
    config: &BakeConfig,
    progress: &dyn Progress,
    skipped: &mut Vec<Skipped>,
    source: &dyn GridSource,
    cache: Option<&cached::BakeCache>,
) -> (CasterSet, LightReport) {
    let started = Instant::now();
    let index = setup.index;
    let light = &config.lights[index];
    let name = light_name(config, index);
    note_left_out(setup, &name, skipped);
    let trace_started = Instant::now();
    let traced = if setup.is_empty() {
        skipped.push(Skipped::info(
            name,
            "its frustum holds no geometry: no rays traced",
        ));
        Traced::nothing(world.casters.len())
    } else {
        trace_grid_and_refine(world, setup, config, progress, source, cache)
    };
    let trace_seconds = trace_started.elapsed().as_secs_f64() + source.seconds_before(index);
    let kept = without_receivers(world, &traced.useful);
    let useful_casters = kept.len();
    let reach = &setup.reach;
    let report = LightReport {
        index,
        bit: config.bit(index),
        name: light.name.clone(),
        kind: light.kind.type_name(),
        rays: traced.rays,
        refine_rays: traced.refine_rays,
        seconds: setup.reach_seconds
            + setup.top_seconds
            + started.elapsed().as_secs_f64()
            + source.seconds_before(index),
        geometry_seconds: setup.reach_seconds,
        bvh_seconds: setup.top_seconds,
        trace_seconds,
        refine_seconds: traced.refine_seconds,
        useful_casters,
        culled_casters: world.casters.real_casters() - useful_casters,
        triangles: reach.triangles as usize,
        instances: reach.parts.len(),
        terrain_blocks: reach.blocks.len(),
        passes: match setup.passes {
            Passes::AllOnly => 1,
            Passes::AllAndOpaque => 2,
        },
        savings: savings::of_light(world, reach, &kept),
    };
    (kept, report)
}

/// Notes in `skipped` what the light `name`'s setup left out: parts and
/// blocks out of its reach, triangles that can never be hit, and the
/// Opaque pass when nothing it reaches is alpha-tested.
fn note_left_out(setup: &LightSetup, name: &str, skipped: &mut Vec<Skipped>) {
    let reach = &setup.reach;
    if reach.parts_out_of_reach + reach.blocks_out_of_reach > 0 {
        skipped.push(Skipped::info(
            name,
            format!(
                "{} instance parts and {} terrain blocks outside its reach were left out of its top level",
                reach.parts_out_of_reach, reach.blocks_out_of_reach
            ),
        ));
    }
    let left_out = reach.left_out_triangles as usize + setup.extent.left_out_triangles;
    if left_out > 0 {
        skipped.push(Skipped::info(
            name,
            format!(
                "{left_out} zero-area, non-finite or absurdly far (> {:e} m) triangles left out (they can never be hit)",
                crate::trace::MAX_COORDINATE
            ),
        ));
    }
    if setup.passes == Passes::AllOnly {
        skipped.push(Skipped::info(
            name,
            "reaches no alpha-tested group: one pass (All) instead of two",
        ));
    }
}

/// What tracing one light found, and its rays.
struct Traced {
    useful: CasterSet,
    /// Every ray: the grid's (texels × supersample²) and refinement's.
    rays: u64,
    refine_rays: u64,
    refine_seconds: f64,
}

impl Traced {
    /// No ray traced (nothing in the light's reach).
    fn nothing(casters: usize) -> Traced {
        Traced {
            useful: CasterSet::new(casters),
            rays: 0,
            refine_rays: 0,
            refine_seconds: 0.0,
        }
    }
}

/// The light's grid answer from `source` (as the [`Phase::Tracing`] of
/// `progress`), then refinement when the config asks for it.
fn trace_grid_and_refine(
    world: &BakeWorld,
    setup: &LightSetup,
    config: &BakeConfig,
    progress: &dyn Progress,
    source: &dyn GridSource,
    cache: Option<&cached::BakeCache>,
) -> Traced {
    let light = &config.lights[setup.index];
    let supersample = config.supersample.max(1);
    let grid_rays = setup.grid.texel_count() * (supersample as u64).pow(2);
    let rays_of_light = setup.rays(world, config);
    let counter = Counter::begin(progress, Phase::Tracing, Some(&light.name), grid_rays);
    let useful = source.grid(world, setup, &rays_of_light, config, &counter);
    counter.finish();
    if let Some(report) = cache.and_then(|c| c.light_report(setup.index)) {
        let fields = serde_json::to_value(&report).unwrap_or_default();
        progress.note("cache_cells", &report.cells_line(), &fields);
    }
    let mut traced = Traced {
        useful,
        rays: grid_rays,
        refine_rays: 0,
        refine_seconds: 0.0,
    };
    if config.refines() {
        let refine_started = Instant::now();
        let (refined, refine_rays) = match cache {
            Some(cache) => cache.refine(
                world,
                setup,
                &rays_of_light,
                &traced.useful,
                config,
                progress,
            ),
            None => refine::refine(
                world,
                setup,
                &rays_of_light,
                &traced.useful,
                config,
                progress,
            ),
        };
        traced.refine_seconds = refine_started.elapsed().as_secs_f64();
        traced.useful = traced.useful.union(&refined);
        traced.refine_rays = refine_rays;
        traced.rays += refine_rays;
    }
    traced
}

/// The casters of `useful` that count: receiver-only groups never do;
/// casters the bake cannot model always do (kept for every light).
fn without_receivers(world: &BakeWorld, useful: &CasterSet) -> CasterSet {
    let casters = &world.casters;
    let words = (useful.words().par_iter())
        .zip(casters.receiver_only.par_iter())
        .zip(casters.unmodelled_bits.par_iter())
        .map(|((useful, receiver_only), unmodelled)| (useful & !receiver_only) | unmodelled)
        .collect();
    CasterSet::from_words(casters.len(), words).expect("one word per 64 ids, as `useful`'s")
}

impl trace_light::RayCounter for Counter<'_> {
    fn add(&self, rays: u64) {
        Counter::add(self, rays);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::ResPaths;
    use crate::formats::bake_settings::{BakeSettings, FaceCulling, LightKind, LightSettings};
    use crate::progress::{Call, Recorded};

    /// The `small` fixture and its settings, every light coarse (these
    /// tests are about phases, not rays).
    fn small_fixture() -> (BakeSettings, Scene) {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/worlds/small");
        let mut settings = crate::files::read_bake_settings(&root.join("bake.xml")).unwrap();
        for light in &mut settings.lights {
            match &mut light.kind {
                LightKind::Directional { texel_size, .. } => *texel_size = 2.0,
                LightKind::Spot { resolution, .. } | LightKind::Point { resolution, .. } => {
                    *resolution = 16
                }
            }
        }
        let scene = crate::scene::load_scene(&crate::scene::LoadConfig {
            res_paths: ResPaths::new(settings.res_paths.clone()),
            space: settings.space.clone(),
            speedtrees: settings.speedtrees.clone(),
        })
        .unwrap();
        (settings, scene)
    }

    /// The phases begun, in order, with their light and total.
    fn begun(recorded: &Recorded) -> Vec<(Phase, Option<String>, u64)> {
        recorded
            .calls()
            .into_iter()
            .filter_map(|call| match call {
                Call::Begin(phase, light, total) => Some((phase, light, total)),
                _ => None,
            })
            .collect()
    }

    /// Each time `phase` was begun: its total and the counts heard until
    /// its end.
    fn counts_of(recorded: &Recorded, phase: Phase) -> Vec<(u64, Vec<u64>)> {
        let calls = recorded.calls();
        let mut phases = Vec::new();
        for (at, call) in calls.iter().enumerate() {
            let Call::Begin(p, _, total) = call else {
                continue;
            };
            if *p != phase {
                continue;
            }
            let counts = calls[at + 1..].iter().map_while(|c| match c {
                Call::Advance(done) => Some(*done),
                _ => None,
            });
            phases.push((*total, counts.collect()));
        }
        phases
    }

    #[test]
    fn every_light_builds_its_top_level_in_a_phase() {
        // A bake with no plan before it builds every light's top level
        // itself: each is a phase (progress, and the out-of-memory message).
        let (settings, scene) = small_fixture();
        let config = BakeConfig::from_settings(&settings);
        let world = BakeWorld::build(&scene, &Silent);
        let recorded = Recorded::default();
        bake_world(&world, &config, &recorded).unwrap();
        let begun = begun(&recorded);
        for light in &config.lights {
            let of = |phase| {
                begun
                    .iter()
                    .position(|(p, l, _)| *p == phase && l.as_deref() == Some(&light.name))
            };
            let (top, tracing) = (of(Phase::TopLevel), of(Phase::Tracing));
            assert!(top.is_some() && top < tracing, "{}: {begun:?}", light.name);
        }
    }

    #[test]
    fn refinement_counts_every_caster_it_refines() {
        let (settings, scene) = small_fixture();
        let config = BakeConfig {
            refine_samples: 4,
            refine_density: 2,
            ..BakeConfig::from_settings(&settings)
        };
        let world = BakeWorld::build(&scene, &Silent);
        let recorded = Recorded::default();
        bake_world(&world, &config, &recorded).unwrap();
        let refining = counts_of(&recorded, Phase::Refining);
        assert_eq!(refining.len(), config.lights.len(), "{refining:?}");
        assert!(refining.iter().any(|(total, _)| *total > 0));
        for (total, counts) in &refining {
            assert_eq!(counts.iter().max().unwrap_or(&0), total, "{refining:?}");
        }
    }

    #[test]
    fn preparing_and_writing_the_output_count_every_chunk_and_file() {
        let (settings, scene) = small_fixture();
        let mut config = BakeConfig::from_settings(&settings);
        config.lights.truncate(1);
        let mut result = bake(&scene, &config, &Silent).unwrap();
        let out = tempfile::tempdir().unwrap();
        let recorded = Recorded::default();
        let res_paths = ResPaths::new(settings.res_paths.clone());
        let outputs =
            output::chunk_outputs(&scene, &mut result, &res_paths, Some(out.path()), &recorded)
                .unwrap();
        let written = output::write_outputs(&outputs, &recorded).unwrap();
        let chunks = scene.chunks.len() as u64;
        assert!(
            chunks >= 4 && written as u64 == chunks,
            "{written} of {chunks}"
        );
        assert_eq!(
            begun(&recorded),
            [
                (Phase::Output, None, chunks),
                (Phase::Writing, None, chunks)
            ]
        );
        let every = (1..=chunks).collect::<Vec<_>>();
        // Chunks in parallel: every one counted, in some order of arrival.
        let (_, mut prepared) = counts_of(&recorded, Phase::Output).remove(0);
        prepared.sort_unstable();
        assert_eq!(prepared, every);
        // Files one by one, as each is written.
        assert_eq!(counts_of(&recorded, Phase::Writing), [(chunks, every)]);
    }

    #[test]
    fn a_failed_allocation_is_an_error_naming_the_phase() {
        // More than the address space: try_reserve fails without aborting.
        let err = try_zeroed::<u64>(usize::MAX / 4, "making the caster masks").unwrap_err();
        let message = err.to_string();
        assert!(
            message.contains("out of memory while making the caster masks"),
            "{message}"
        );
        assert_eq!(try_zeroed::<u32>(3, "x").unwrap(), vec![0, 0, 0]);
    }

    #[test]
    fn selected_lights_keep_their_bits() {
        let settings = crate::formats::bake_settings::BakeSettings {
            res_paths: Vec::new(),
            space: String::new(),
            face_culling: FaceCulling::Back,
            height_bias: 0.05,
            tie_epsilon: 1e-4,
            lights: ["a", "b", "c"]
                .map(|name| LightSettings {
                    name: name.into(),
                    kind: crate::formats::bake_settings::LightKind::Directional {
                        direction: glam::DVec3::NEG_Y,
                        texel_size: 1.0,
                    },
                })
                .to_vec(),
            bits: vec![4, 0, 9],
            speedtrees: Default::default(),
            unmodelled_casters: Default::default(),
            unknown: Vec::new(),
        };
        let config = BakeConfig::from_settings(&settings);
        assert_eq!(config.baked_bits(), 1 << 4 | 1 | 1 << 9);
        let picked = config
            .select_lights(&["c".to_string(), "a".to_string()])
            .unwrap();
        assert_eq!(picked.lights.len(), 2);
        assert_eq!((picked.bit(0), picked.bit(1)), (4, 9));
        assert_eq!(picked.baked_bits(), 1 << 4 | 1 << 9);
        let err = config.select_lights(&["z".to_string()]).unwrap_err();
        assert!(
            err.contains("`z`") && err.contains("`a`, `b`, `c`"),
            "{err}"
        );
    }
}
