//! The bake: for each light, its texel grid, a BVH over what it reaches,
//! one ray per texel, and the casters the rays prove useful; then the masks
//! per group, instance and terrain block. Orchestration only: the rules are
//! in `classify`, the rays in `light`, the traversal in `trace`.

pub mod casters;
pub mod geometry;
pub mod ground;
pub mod output;
pub mod refine;
pub mod trace_light;

use crate::classify::Passes;
use crate::formats::bake_settings::{FaceCulling, LightSettings};
use crate::light::TexelGrid;
use crate::scene::Scene;
use crate::trace::Bvh;
use casters::CasterTable;
use std::sync::atomic::AtomicU64;
use std::time::Instant;
use trace_light::{CasterSet, LightRays, RayRules, Tracer};

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
    /// Before the BVH build, which takes seconds on large worlds.
    fn light_preparing(&self, _index: usize, _light: &LightSettings, _triangles: usize) {}
    /// Before the rays are traced.
    fn light_started(&self, _index: usize, _light: &LightSettings, _rays: u64) {}
    /// Called from worker threads with the running total of rays traced.
    fn rays_traced(&self, _index: usize, _done: &AtomicU64) {}
    fn light_finished(&self, _report: &LightReport) {}
}

/// No progress output.
pub struct Silent;
impl Progress for Silent {}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LightReport {
    pub index: usize,
    pub name: String,
    pub kind: &'static str,
    /// Texel rays (texels × supersample²) plus refinement rays.
    pub rays: u64,
    /// Of `rays`, those aimed at casters' own surfaces (`refine`).
    pub refine_rays: u64,
    /// Wall time for the light in all: geometry + BVH + tracing.
    pub seconds: f64,
    pub geometry_seconds: f64,
    pub bvh_seconds: f64,
    pub trace_seconds: f64,
    pub useful_casters: usize,
    pub culled_casters: usize,
    /// Triangles in this light's BVH.
    pub triangles: usize,
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

pub fn bake(
    scene: &Scene,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> Result<BakeResult, BakeError> {
    if config.lights.len() > 32 {
        return Err(BakeError::TooManyLights {
            count: config.lights.len(),
        });
    }
    let casters = CasterTable::new(scene);
    let mut masks = vec![0u32; casters.len()];
    let mut skipped: Vec<Skipped> = scene
        .problems
        .iter()
        .map(|p| Skipped {
            what: p.what.clone(),
            why: p.why.clone(),
        })
        .collect();
    for (index, instance) in scene.instances.iter().enumerate() {
        if casters.first_of_instance[index].is_none() {
            let chunk = &scene.chunks[instance.chunk];
            skipped.push(Skipped {
                what: format!("{} instance {} ({})", chunk.name, instance.index, instance.resources.join(", ")),
                why: "a <resource> part did not load (see its problem); its <shadow> is left as it was".into(),
            });
        }
    }
    let ground = ground::Ground::new(scene);
    if ground.is_none() {
        skipped.push(Skipped {
            what: "below-ground test".into(),
            why: "the world has no terrain: no height tests".into(),
        });
    }
    let bounds = geometry::world_bounds(scene);
    let mut lights = Vec::new();
    for (index, light) in config.lights.iter().enumerate() {
        let started = Instant::now();
        let name = format!("light {index} ({})", light.name);
        let Some(bounds) = bounds else {
            skipped.push(Skipped {
                what: name,
                why: "the world has no geometry to cast or receive shadows".into(),
            });
            continue;
        };
        let grid = match TexelGrid::new(light, bounds) {
            Ok(grid) => grid,
            Err(err @ crate::light::GridError::EmptyWorld { .. }) => {
                skipped.push(Skipped {
                    what: name,
                    why: err.to_string(),
                });
                continue;
            }
            Err(err) => return Err(err.into()),
        };
        let geometry = geometry::light_geometry(scene, &casters, &grid);
        if geometry.instances_out_of_reach + geometry.blocks_out_of_reach > 0 {
            skipped.push(Skipped {
                what: name.clone(),
                why: format!(
                    "{} instances and {} terrain blocks outside its reach were left out of its BVH",
                    geometry.instances_out_of_reach, geometry.blocks_out_of_reach
                ),
            });
        }
        if geometry.degenerate_triangles > 0 {
            skipped.push(Skipped {
                what: name.clone(),
                why: format!(
                    "{} zero-area, non-finite or absurdly far (> {:e} m) triangles left out (they can never be hit)",
                    geometry.degenerate_triangles,
                    crate::trace::MAX_COORDINATE
                ),
            });
        }
        let passes = if geometry.reaches_alpha_tested {
            Passes::AllAndOpaque
        } else {
            skipped.push(Skipped {
                what: name.clone(),
                why: "reaches no alpha-tested group: one pass (All) instead of two".into(),
            });
            Passes::AllOnly
        };
        let supersample = config.supersample.max(1);
        let mut rays = grid.texel_count() * (supersample as u64).pow(2);
        let mut refine_rays = 0;
        let geometry_seconds = started.elapsed().as_secs_f64();
        let (mut bvh_seconds, mut trace_seconds) = (0.0, 0.0);
        let useful = if geometry.triangles.is_empty() {
            skipped.push(Skipped {
                what: name.clone(),
                why: "its frustum holds no geometry: no rays traced".into(),
            });
            CasterSet::new(casters.len())
        } else {
            progress.light_preparing(index, light, geometry.triangles.len());
            let build_started = Instant::now();
            let bvh;
            let tracer = if config.brute_force {
                Tracer::BruteForce(&geometry.triangles)
            } else {
                bvh = Bvh::build(&geometry.triangles);
                Tracer::Bvh(&bvh)
            };
            bvh_seconds = build_started.elapsed().as_secs_f64();
            progress.light_started(index, light, rays);
            let trace_started = Instant::now();
            let rays_of_light = LightRays {
                grid: &grid,
                tracer,
                casters: &casters,
                ground: ground.as_ref(),
                rules: RayRules::new(config, passes),
            };
            let done = AtomicU64::new(0);
            let reporter = ProgressRelay {
                progress,
                index,
                done: &done,
            };
            let mut useful = rays_of_light.trace_grid(supersample, &reporter);
            if config.refine_samples > 0 {
                let (refined, traced) = refine::refine(
                    &rays_of_light,
                    index,
                    &geometry.triangles,
                    &useful,
                    config.refine_samples,
                );
                useful = useful.union(&refined);
                refine_rays = traced;
                rays += traced;
            }
            trace_seconds = trace_started.elapsed().as_secs_f64();
            useful
        };
        let mut useful_casters = 0;
        for (id, caster) in casters.casters.iter().enumerate() {
            if !caster.receiver_only && useful.contains(id as u32) {
                masks[id] |= 1 << index;
                useful_casters += 1;
            }
        }
        let report = LightReport {
            index,
            name: light.name.clone(),
            kind: light.kind.type_name(),
            rays: if geometry.triangles.is_empty() {
                0
            } else {
                rays
            },
            refine_rays,
            seconds: started.elapsed().as_secs_f64(),
            geometry_seconds,
            bvh_seconds,
            trace_seconds,
            useful_casters,
            culled_casters: casters.real_casters() - useful_casters,
            triangles: geometry.triangles.len(),
            passes: match passes {
                Passes::AllOnly => 1,
                Passes::AllAndOpaque => 2,
            },
        };
        progress.light_finished(&report);
        lights.push(report);
    }
    skipped.sort();
    Ok(BakeResult {
        casters,
        masks,
        lights,
        skipped,
    })
}

/// Passes ray counts from the tracing threads to the caller's progress.
struct ProgressRelay<'a> {
    progress: &'a dyn Progress,
    index: usize,
    done: &'a AtomicU64,
}

impl trace_light::RayCounter for ProgressRelay<'_> {
    fn add(&self, rays: u64) {
        self.done
            .fetch_add(rays, std::sync::atomic::Ordering::Relaxed);
        self.progress.rays_traced(self.index, self.done);
    }
}
