//! The contract between preparing a light and everything that traces it.
//!
//! [`BakeWorld`] is what every light of a bake shares: the caster table,
//! the bottom levels (one BVH per distinct model, one height field per
//! terrain block, built once), the ground and the world bounds.
//! [`LightSetup`] is one light ready to trace: its grid, what lies in its
//! reach, its top level and its passes. The bake, refinement, `render`,
//! `sweep` and `xcheck` all build lights through [`LightSetup::new`] and
//! trace through [`LightSetup::rays`], so they see the same geometry and
//! apply the same rules.

use super::casters::{CasterTable, PartCasters};
use super::config::BakeConfig;
use super::geometry;
use super::ground::Ground;
use super::trace_light::{LightRays, RayRules, TileReach};
use crate::classify::Passes;
use crate::light::{GridError, TexelGrid};
use crate::progress::{Counter, Phase, Progress};
use crate::scene::Scene;
use crate::trace::{
    transform_box, BottomLevels, Extent, PartsFrom, PlacedBlock, PlacedPart, PlacedParts, TopLevel,
    TraceMode, TraceTriangle, Tracer,
};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;

/// What every light of a bake shares.
pub struct BakeWorld<'a> {
    pub scene: &'a Scene,
    pub casters: Arc<CasterTable>,
    /// Every placed part, in caster id order.
    pub parts: Vec<PartCasters>,
    pub bottom: BottomLevels<'a>,
    pub ground: Option<Ground<'a>>,
    /// World bounds of everything that can be hit, `None`: no geometry.
    pub bounds: Option<(DVec3, DVec3)>,
    /// Wall time of the bottom-level builds.
    pub bottom_seconds: f64,
}

impl<'a> BakeWorld<'a> {
    /// Builds the bottom levels (in parallel across models and blocks).
    pub fn new(scene: &'a Scene) -> BakeWorld<'a> {
        BakeWorld::build(scene, &crate::progress::Silent)
    }

    /// [`BakeWorld::new`], telling `progress`.
    pub fn build(scene: &'a Scene, progress: &dyn crate::progress::Progress) -> BakeWorld<'a> {
        BakeWorld::within(scene, geometry::world_bounds(scene), progress)
    }

    /// [`BakeWorld::build`] of a scene whose bounds
    /// (`geometry::world_bounds`) are `bounds`.
    pub fn within(
        scene: &'a Scene,
        bounds: Option<(DVec3, DVec3)>,
        progress: &dyn crate::progress::Progress,
    ) -> BakeWorld<'a> {
        let counter = crate::progress::Counter::begin(
            progress,
            crate::progress::Phase::BottomLevels,
            None,
            (scene.models.len() + scene.terrain.len()) as u64,
        );
        let started = Instant::now();
        let casters = Arc::new(CasterTable::new(scene));
        let parts = casters.par_parts(scene).collect();
        let bottom = BottomLevels::build(
            scene.models.len(),
            |m| model_space_triangles(scene, m),
            scene.terrain.iter().map(|b| b.grid()).collect(),
        );
        counter.add((scene.models.len() + scene.terrain.len()) as u64);
        counter.finish();
        BakeWorld {
            scene,
            casters,
            parts,
            bottom,
            ground: Ground::new(scene),
            bounds,
            bottom_seconds: started.elapsed().as_secs_f64(),
        }
    }
}

/// Model `m`'s triangles in model space, `caster` = group index.
fn model_space_triangles(scene: &Scene, m: usize) -> Vec<TraceTriangle> {
    let model = &scene.models[m];
    let mut out = Vec::with_capacity(model.triangles.len());
    for (group_index, group) in model.groups.iter().enumerate() {
        for triangle in model.triangles.get(group.triangles.clone()).unwrap_or(&[]) {
            let Some(vertices) = triangle
                .iter()
                .map(|&i| model.positions.get(i as usize).copied())
                .collect::<Option<Vec<_>>>()
            else {
                continue;
            };
            out.push(TraceTriangle {
                vertices: [vertices[0], vertices[1], vertices[2]],
                caster: group_index as u32,
            });
        }
    }
    out
}

/// `parts` (indices into [`BakeWorld::parts`]) as the top level places
/// them.
fn placed_parts<'w>(world: &'w BakeWorld, parts: &'w [u32]) -> impl PlacedParts + 'w {
    PartsFrom {
        count: parts.len(),
        part: move |i| {
            let part = &world.parts[parts[i] as usize];
            PlacedPart {
                model: part.model as u32,
                world: world.scene.instances[part.instance].world,
                first_caster: part.first_caster,
            }
        },
    }
}

/// Terrain `blocks` as the top level places them.
fn placed_blocks<'w>(
    world: &'w BakeWorld,
    blocks: &'w [u32],
) -> impl ExactSizeIterator<Item = PlacedBlock> + 'w {
    blocks.iter().map(|&block| PlacedBlock {
        block,
        caster: world.casters.of_block[block as usize],
    })
}

/// See [`LightSetup::top_is_small`].
const SMALL_TOP_SHARE: usize = 8;

/// What lies in one light's reach, and what was left out.
#[derive(Debug, Default, Clone)]
pub struct Reach {
    /// Into [`BakeWorld::parts`], in id order.
    pub parts: Vec<u32>,
    /// Terrain blocks, in scene order.
    pub blocks: Vec<u32>,
    pub parts_out_of_reach: usize,
    pub blocks_out_of_reach: usize,
    /// Triangles in reach that can be hit (the usable triangles of every
    /// part's model, two per visible non-hole terrain cell).
    pub triangles: u64,
    /// Triangles never traced: zero-area, non-finite or absurd in model
    /// space, or of a part whose placement is absurd.
    pub left_out_triangles: u64,
    /// Some part in reach has an alpha-tested group.
    pub reaches_alpha_tested: bool,
}

/// Why a light has no setup.
#[derive(Debug, thiserror::Error)]
pub enum NoSetup {
    #[error("the world has no geometry to cast or receive shadows")]
    NoGeometry,
    /// The grid cannot be made: [`GridError::EmptyWorld`] means nothing to
    /// trace; any other is a settings mistake and stops a bake.
    #[error(transparent)]
    Grid(#[from] GridError),
}

impl NoSetup {
    /// Nothing to trace (the bake notes it and goes on), as opposed to a
    /// settings mistake.
    pub fn is_nothing_to_trace(&self) -> bool {
        matches!(
            self,
            NoSetup::NoGeometry | NoSetup::Grid(GridError::EmptyWorld { .. })
        )
    }
}

/// One light ready to trace.
pub struct LightSetup {
    pub index: usize,
    pub grid: TexelGrid,
    pub reach: Reach,
    /// What a top level over the whole reach bounds and leaves out,
    /// whether `top` holds all of it or, for a cached bake, only what the
    /// cells it traces again can meet ([`LightSetup::build_top`]).
    pub extent: Extent,
    pub top: TopLevel,
    pub passes: Passes,
    /// The tiles of the grid whose rays can hit anything in `top`.
    pub tiles: TileReach,
    /// Wall time of finding the reach and of the top-level build.
    pub reach_seconds: f64,
    pub top_seconds: f64,
}

impl LightSetup {
    /// Light `index` of `config` over `world`.
    pub fn new(
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
    ) -> Result<LightSetup, NoSetup> {
        let mut setup = LightSetup::without_top(world, config, index)?;
        setup.build_top(world, None);
        Ok(setup)
    }

    /// Light `index`'s grid, reach and extent; its top level empty until
    /// [`LightSetup::build_top`].
    pub fn without_top(
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
    ) -> Result<LightSetup, NoSetup> {
        let light = &config.lights[index];
        let bounds = world.bounds.ok_or(NoSetup::NoGeometry)?;
        let grid = TexelGrid::new(light, bounds)?.with_offset(config.grid_offset);
        let started = Instant::now();
        let reach = reach(world, &grid);
        let reference = grid.reference_point();
        let extent = Extent::of(
            &world.bottom,
            &placed_parts(world, &reach.parts),
            placed_blocks(world, &reach.blocks),
            reference,
        );
        let reach_seconds = started.elapsed().as_secs_f64();
        let passes = if reach.reaches_alpha_tested {
            Passes::AllAndOpaque
        } else {
            Passes::AllOnly
        };
        let tiles = TileReach::of_extent(&grid, &extent);
        let top = TopLevel::build(
            &world.bottom,
            &placed_parts(world, &[]),
            placed_blocks(world, &[]),
            reference,
        );
        Ok(LightSetup {
            index,
            tiles,
            grid,
            reach,
            extent,
            top,
            passes,
            reach_seconds,
            top_seconds: 0.0,
        })
    }

    /// Builds the top level over the whole reach, or over `only` its
    /// parts (ascending indices into [`BakeWorld::parts`]) and blocks:
    /// enough for rays that can meet nothing else (a cached bake's cells
    /// traced again; `bake::cells` says what each cell can meet).
    pub fn build_top(&mut self, world: &BakeWorld, only: Option<(&[u32], &[u32])>) {
        let started = Instant::now();
        let (parts, blocks) = only.unwrap_or((&self.reach.parts, &self.reach.blocks));
        self.top = TopLevel::build(
            &world.bottom,
            &placed_parts(world, parts),
            placed_blocks(world, blocks),
            self.grid.reference_point(),
        );
        self.top_seconds = started.elapsed().as_secs_f64();
    }

    /// The top level holds at most a [`SMALL_TOP_SHARE`]th of the reach
    /// (a cached bake's few cells traced again): cheap to hold beside
    /// another light's.
    pub fn top_is_small(&self) -> bool {
        self.top.len() * SMALL_TOP_SHARE <= self.reach.parts.len() + self.reach.blocks.len()
    }

    /// Nothing in reach can be hit: no ray of the light meets anything.
    pub fn is_empty(&self) -> bool {
        self.extent.bounds.is_none()
    }

    /// [`LightSetup::new`] as [`Phase::TopLevel`] of `progress`: finding
    /// the reach and building the top level take seconds on a large world,
    /// and a phase says whose and names it if memory runs out.
    pub fn new_with_progress(
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
        progress: &dyn Progress,
    ) -> Result<LightSetup, NoSetup> {
        LightSetup::in_phase(config, index, progress, || {
            LightSetup::new(world, config, index)
        })
    }

    /// Light `index`'s setup made by `build`, as [`Phase::TopLevel`] of
    /// `progress`.
    pub fn in_phase(
        config: &BakeConfig,
        index: usize,
        progress: &dyn Progress,
        build: impl FnOnce() -> Result<LightSetup, NoSetup>,
    ) -> Result<LightSetup, NoSetup> {
        let light = Some(config.lights[index].name.as_str());
        let counter = Counter::begin(progress, Phase::TopLevel, light, 1);
        let setup = build();
        if setup.is_ok() {
            counter.add(1);
        }
        counter.finish();
        setup
    }

    /// The light's rays with `config`'s rules and this setup's passes.
    pub fn rays<'a>(&'a self, world: &'a BakeWorld, config: &BakeConfig) -> LightRays<'a> {
        LightRays {
            grid: &self.grid,
            tracer: Tracer {
                bottom: &world.bottom,
                top: &self.top,
                mode: if config.brute_force {
                    TraceMode::BruteForce
                } else {
                    TraceMode::Trees
                },
            },
            casters: &world.casters,
            ground: world.ground.as_ref(),
            rules: RayRules::new(config, self.passes),
            tiles: &self.tiles,
        }
    }

    /// Light-relative triangles of caster `id` (refinement's sample
    /// points, the occluders' images).
    pub fn caster_triangles(&self, world: &BakeWorld, id: u32) -> Vec<TraceTriangle> {
        let reference = self.grid.reference_point();
        geometry::caster_triangles(world.scene, &world.casters, id, reference)
    }

    /// Every triangle in this light's reach, light-relative, in caster id
    /// order: the raster reference draws what the rays can hit.
    pub fn reach_geometry(&self, world: &BakeWorld) -> geometry::FlatGeometry {
        geometry::parts_geometry(
            world.scene,
            &world.casters,
            &world.parts,
            &self.reach.parts,
            &self.reach.blocks,
            self.grid.reference_point(),
        )
    }
}

/// The parts and blocks some of whose box the light's grid reaches.
fn reach(world: &BakeWorld, grid: &TexelGrid) -> Reach {
    let scene = world.scene;
    let parts: Vec<u32> = (0..world.parts.len() as u32)
        .into_par_iter()
        .filter(|&index| {
            let part = &world.parts[index as usize];
            world.bottom.models[part.model]
                .bounds()
                .is_some_and(|(min, max)| {
                    let placed = &scene.instances[part.instance].world;
                    let (min, max) = transform_box(placed, min.as_dvec3(), max.as_dvec3());
                    grid.reaches(min, max)
                })
        })
        .collect();
    // Totals per model, not per part: the sun reaches millions of parts
    // of a few thousand models.
    let per_model = parts
        .par_iter()
        .fold(
            || vec![0u64; scene.models.len()],
            |mut counts, &p| {
                counts[world.parts[p as usize].model] += 1;
                counts
            },
        )
        .reduce_with(|mut a, b| {
            a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
            a
        })
        .unwrap_or_default();
    let mut reach = Reach {
        parts_out_of_reach: world.parts.len() - parts.len(),
        parts,
        ..Reach::default()
    };
    for (model, &count) in per_model.iter().enumerate().filter(|(_, &c)| c > 0) {
        reach.triangles += count * world.bottom.model_triangles(model) as u64;
        reach.left_out_triangles += count * world.bottom.model_left_out(model) as u64;
        reach.reaches_alpha_tested |= scene.models[model]
            .groups
            .iter()
            .any(|g| g.alpha_tested && !g.triangles.is_empty());
    }
    for (index, block) in scene.terrain.iter().enumerate() {
        let (min, max) = block.bounds();
        if grid.reaches(min, max) {
            reach.blocks.push(index as u32);
            reach.triangles += block.visible_triangles() as u64;
        } else {
            reach.blocks_out_of_reach += 1;
        }
    }
    reach
}
