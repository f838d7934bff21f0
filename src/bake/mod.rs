//! The bake: for each light, its texel grid, a BVH over what it reaches,
//! one ray per texel, and the casters the rays prove useful; then the masks
//! per group, instance and terrain block. Orchestration only: the rules are
//! in `classify`, the rays in `light`, the traversal in `trace`.

pub mod casters;
pub mod geometry;
pub mod ground;
pub mod output;
pub mod refine;
pub mod setup;
pub mod shard;
pub mod trace_light;

use crate::classify::Passes;
use crate::formats::bake_settings::{FaceCulling, LightSettings};
use crate::scene::Scene;
use casters::CasterTable;
use setup::{BakeWorld, LightSetup, NoSetup};
use std::sync::atomic::AtomicU64;
use std::time::Instant;
use trace_light::{CasterSet, LightRays, RayCounter};

/// What to bake (the settings file's values after command-line overrides).
#[derive(Debug, Clone)]
pub struct BakeConfig {
    pub face_culling: FaceCulling,
    /// Metres: a non-terrain hit more than this below the terrain surface is
    /// ignored.
    pub height_bias: f64,
    /// Metres along a ray: the tie tolerance of SPEC §4.
    pub tie_epsilon: f64,
    pub lights: Vec<LightSettings>,
    /// Trace every ray against every triangle instead of the BVH (the
    /// oracle; slow).
    pub brute_force: bool,
    /// Rays per texel side: 1 traces texel centres, k a k×k pattern of
    /// sub-texel centres (the same rays as a k× denser grid).
    pub supersample: u32,
    /// Refinement: rays aimed at this many points of every caster's own
    /// surface that the grid did not prove useful (0: off).
    pub refine_samples: u32,
}

impl BakeConfig {
    /// The settings file's values; no supersampling, no refinement.
    pub fn from_settings(settings: &crate::formats::bake_settings::BakeSettings) -> BakeConfig {
        BakeConfig {
            face_culling: settings.face_culling,
            height_bias: settings.height_bias,
            tie_epsilon: settings.tie_epsilon,
            lights: settings.lights.clone(),
            brute_force: false,
            supersample: 1,
            refine_samples: 0,
        }
    }
}

impl Default for BakeConfig {
    /// SPEC §3 defaults and no lights.
    fn default() -> Self {
        BakeConfig {
            face_culling: FaceCulling::Back,
            height_bias: 0.05,
            tie_epsilon: 1e-4,
            lights: Vec::new(),
            brute_force: false,
            supersample: 1,
            refine_samples: 0,
        }
    }
}

/// Where a bake reports progress; the library never prints.
pub trait Progress: Sync {
    /// Before the bottom levels (one BVH per distinct model, one height
    /// field per terrain block) are built, once per bake.
    fn bottom_levels_building(&self, _models: usize, _terrain_blocks: usize) {}
    /// Before the rays are traced.
    fn light_started(&self, _index: usize, _light: &LightSettings, _rays: u64) {}
    /// Called from worker threads with the running total of rays traced.
    fn rays_traced(&self, _index: usize, _done: &AtomicU64) {}
    fn light_finished(&self, _report: &LightReport) {}
}

/// No progress output.
pub struct Silent;
impl Progress for Silent {}

#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LightReport {
    pub index: usize,
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
    pub trace_seconds: f64,
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
}

/// Something the bake left out, and why.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
pub struct Skipped {
    pub what: String,
    pub why: String,
}

#[derive(Debug, Clone)]
pub struct BakeResult {
    /// Wall time of building the bottom levels, once for every light.
    pub bottom_level_seconds: f64,
    /// Heap bytes of the bottom levels.
    pub bottom_level_bytes: usize,
    pub casters: CasterTable,
    /// Per caster id: bit i set = useful for light i.
    pub masks: Vec<u32>,
    pub lights: Vec<LightReport>,
    pub skipped: Vec<Skipped>,
}

#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    #[error("{count} lights: at most 32 fit the 32-bit mask; split the bake into several settings files")]
    TooManyLights { count: usize },
    /// A light whose grid cannot be made (too large, invalid values): a
    /// settings mistake, so the bake stops rather than skipping it.
    #[error(transparent)]
    Grid(#[from] crate::light::GridError),
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
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        supersample: u32,
        rays_done: &dyn RayCounter,
    ) -> CasterSet;
}

/// Traces every texel of the grid.
pub struct TraceGrid;

impl GridSource for TraceGrid {
    fn grid(
        &self,
        _setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        supersample: u32,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        rays_of_light.trace_grid(supersample, rays_done)
    }
}

pub fn bake(
    scene: &Scene,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> Result<BakeResult, BakeError> {
    check_light_count(config)?;
    progress.bottom_levels_building(scene.models.len(), scene.terrain.len());
    bake_from(BakeWorld::new(scene), config, progress, &TraceGrid)
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

/// [`bake`] over a built `world`, with the grid answers from `source`.
pub fn bake_from(
    world: BakeWorld,
    config: &BakeConfig,
    progress: &dyn Progress,
    source: &dyn GridSource,
) -> Result<BakeResult, BakeError> {
    check_light_count(config)?;
    let mut masks = vec![0u32; world.casters.len()];
    let mut skipped = world_skipped(&world);
    let mut lights = Vec::new();
    for index in 0..config.lights.len() {
        let setup = match LightSetup::new(&world, config, index) {
            Ok(setup) => setup,
            Err(nothing) if nothing.is_nothing_to_trace() => {
                skipped.push(Skipped {
                    what: light_name(config, index),
                    why: nothing.to_string(),
                });
                continue;
            }
            Err(NoSetup::Grid(err)) => return Err(err.into()),
            Err(NoSetup::NoGeometry) => unreachable!("no geometry is nothing to trace"),
        };
        let (useful, report) =
            bake_light_from(&world, &setup, config, progress, &mut skipped, source);
        for (id, mask) in masks.iter_mut().enumerate() {
            if useful.contains(id as u32) {
                *mask |= 1 << index;
            }
        }
        progress.light_finished(&report);
        lights.push(report);
    }
    skipped.sort();
    Ok(BakeResult {
        bottom_level_seconds: world.bottom_seconds,
        bottom_level_bytes: world.bottom.heap_bytes(),
        casters: world.casters,
        masks,
        lights,
        skipped,
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
        .map(|p| Skipped {
            what: p.what.clone(),
            why: p.why.clone(),
        })
        .collect();
    for (index, instance) in scene.instances.iter().enumerate() {
        if world.casters.first_of_instance[index].is_none() {
            let chunk = &scene.chunks[instance.chunk];
            skipped.push(Skipped {
                what: format!("{} instance {} ({})", chunk.name, instance.index, instance.resources.join(", ")),
                why: "a <resource> part did not load (see its problem); its <shadow> is left as it was".into(),
            });
        }
    }
    if world.ground.is_none() {
        skipped.push(Skipped {
            what: "below-ground test".into(),
            why: "the world has no terrain: no height tests".into(),
        });
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
    bake_light_from(world, setup, config, progress, skipped, &TraceGrid)
}

/// [`bake_light`] with the grid answer from `source`.
fn bake_light_from(
    world: &BakeWorld,
    setup: &LightSetup,
    config: &BakeConfig,
    progress: &dyn Progress,
    skipped: &mut Vec<Skipped>,
    source: &dyn GridSource,
) -> (CasterSet, LightReport) {
    let started = Instant::now();
    let index = setup.index;
    let light = &config.lights[index];
    let name = light_name(config, index);
    let reach = &setup.reach;
    if reach.parts_out_of_reach + reach.blocks_out_of_reach > 0 {
        skipped.push(Skipped {
            what: name.clone(),
            why: format!(
                "{} instance parts and {} terrain blocks outside its reach were left out of its top level",
                reach.parts_out_of_reach, reach.blocks_out_of_reach
            ),
        });
    }
    let left_out = reach.left_out_triangles as usize + setup.top.left_out_triangles();
    if left_out > 0 {
        skipped.push(Skipped {
            what: name.clone(),
            why: format!(
                "{left_out} zero-area, non-finite or absurdly far (> {:e} m) triangles left out (they can never be hit)",
                crate::trace::MAX_COORDINATE
            ),
        });
    }
    if setup.passes == Passes::AllOnly {
        skipped.push(Skipped {
            what: name.clone(),
            why: "reaches no alpha-tested group: one pass (All) instead of two".into(),
        });
    }
    let supersample = config.supersample.max(1);
    let mut rays = setup.grid.texel_count() * (supersample as u64).pow(2);
    let mut refine_rays = 0;
    let trace_started = Instant::now();
    let useful = if setup.top.is_empty() {
        skipped.push(Skipped {
            what: name.clone(),
            why: "its frustum holds no geometry: no rays traced".into(),
        });
        rays = 0;
        CasterSet::new(world.casters.len())
    } else {
        progress.light_started(index, light, rays);
        let rays_of_light = setup.rays(world, config);
        let done = AtomicU64::new(0);
        let reporter = ProgressRelay {
            progress,
            index,
            done: &done,
        };
        let mut useful = source.grid(setup, &rays_of_light, supersample, &reporter);
        if config.refine_samples > 0 {
            let (refined, traced) =
                refine::refine(world, setup, &rays_of_light, &useful, config.refine_samples);
            useful = useful.union(&refined);
            refine_rays = traced;
            rays += traced;
        }
        useful
    };
    let trace_seconds = trace_started.elapsed().as_secs_f64();
    let mut kept = CasterSet::new(world.casters.len());
    for (id, caster) in world.casters.casters.iter().enumerate() {
        if !caster.receiver_only && useful.contains(id as u32) {
            kept.insert(id as u32);
        }
    }
    let useful_casters = kept.len();
    let report = LightReport {
        index,
        name: light.name.clone(),
        kind: light.kind.type_name(),
        rays,
        refine_rays,
        seconds: setup.reach_seconds + setup.top_seconds + started.elapsed().as_secs_f64(),
        geometry_seconds: setup.reach_seconds,
        bvh_seconds: setup.top_seconds,
        trace_seconds,
        useful_casters,
        culled_casters: world.casters.real_casters() - useful_casters,
        triangles: reach.triangles as usize,
        instances: reach.parts.len(),
        terrain_blocks: reach.blocks.len(),
        passes: match setup.passes {
            Passes::AllOnly => 1,
            Passes::AllAndOpaque => 2,
        },
    };
    (kept, report)
}

/// Passes ray counts from the tracing threads to the caller's progress.
pub(crate) struct ProgressRelay<'a> {
    pub progress: &'a dyn Progress,
    pub index: usize,
    pub done: &'a AtomicU64,
}

impl trace_light::RayCounter for ProgressRelay<'_> {
    fn add(&self, rays: u64) {
        self.done
            .fetch_add(rays, std::sync::atomic::Ordering::Relaxed);
        self.progress.rays_traced(self.index, self.done);
    }
}
