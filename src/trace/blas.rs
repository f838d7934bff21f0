//! The bottom levels: one BVH per distinct model in model space and one
//! min/max pyramid per terrain block, built once per bake (in parallel) and
//! shared by every light and every placement. Memory grows with distinct
//! geometry, not with placed copies.

use super::heightfield::{HeightField, HeightGrid};
use super::{Bvh, TraceTriangle};
use glam::Vec3;
use rayon::prelude::*;
use std::sync::OnceLock;

pub struct BottomLevels<'a> {
    pub(crate) models: Vec<Bvh>,
    /// Triangles each model's input held that were left out (not finite,
    /// beyond [`super::MAX_COORDINATE`] or of zero area in model space).
    pub(crate) models_left_out: Vec<usize>,
    /// Per model, the groups (ascending) with a triangle built: the
    /// casters a ray entering a placement of it can meet, each with the
    /// box of its triangles.
    pub(crate) model_groups: Vec<Vec<ModelGroup>>,
    pub(crate) terrain: Vec<TerrainLevel<'a>>,
}

/// One terrain block's bottom level. Its pyramid is built by the first
/// ray that reaches the block: a re-bake with a cache traces a few of a
/// world's blocks, and its top levels need only the blocks' height
/// ranges.
pub(crate) struct TerrainLevel<'a> {
    pub(crate) grid: HeightGrid<'a>,
    range: (f32, f32),
    field: OnceLock<HeightField>,
}

impl<'a> TerrainLevel<'a> {
    fn new(grid: HeightGrid<'a>) -> TerrainLevel<'a> {
        TerrainLevel {
            range: HeightField::height_range_of(&grid),
            grid,
            field: OnceLock::new(),
        }
    }

    pub(crate) fn field(&self) -> &HeightField {
        self.field.get_or_init(|| HeightField::build(&self.grid))
    }

    /// [`HeightField::height_range`] of its pyramid, built or not.
    pub(crate) fn height_range(&self) -> (f32, f32) {
        self.range
    }
}

/// One group of a model's triangles: its index within the model and the
/// box of its triangles (model space): a ray that misses the box, padded
/// as the node test pads, meets none of them.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ModelGroup {
    pub(crate) group: u32,
    pub(crate) lo: Vec3,
    pub(crate) hi: Vec3,
}

impl ModelGroup {
    /// The groups of `triangles` (their `caster` is the group), ascending.
    fn of(triangles: &[TraceTriangle]) -> Vec<ModelGroup> {
        let mut groups: Vec<ModelGroup> = Vec::new();
        let mut sorted: Vec<&TraceTriangle> = triangles.iter().collect();
        sorted.sort_by_key(|t| t.caster);
        for t in sorted {
            let [a, b, c] = t.vertices;
            let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
            match groups.last_mut() {
                Some(g) if g.group == t.caster => {
                    g.lo = g.lo.min(lo);
                    g.hi = g.hi.max(hi);
                }
                _ => groups.push(ModelGroup {
                    group: t.caster,
                    lo,
                    hi,
                }),
            }
        }
        groups
    }
}

impl<'a> BottomLevels<'a> {
    /// `model_triangles(i)`: model i's triangles in model space, `caster`
    /// holding the triangle's group index within the model.
    pub fn build(
        models: usize,
        model_triangles: impl Fn(usize) -> Vec<TraceTriangle> + Sync,
        terrain: Vec<HeightGrid<'a>>,
    ) -> BottomLevels<'a> {
        let (models, models_left_out): (Vec<Bvh>, Vec<(usize, Vec<ModelGroup>)>) = (0..models)
            .into_par_iter()
            .map(|i| {
                let triangles = model_triangles(i);
                let usable: Vec<TraceTriangle> = triangles
                    .iter()
                    .filter(|t| t.is_usable() && !t.has_zero_area())
                    .copied()
                    .collect();
                let left_out = triangles.len() - usable.len();
                (Bvh::build(&usable), (left_out, ModelGroup::of(&usable)))
            })
            .unzip();
        let (models_left_out, model_groups) = models_left_out.into_iter().unzip();
        let terrain = terrain.into_par_iter().map(TerrainLevel::new).collect();
        BottomLevels {
            models,
            models_left_out,
            model_groups,
            terrain,
        }
    }

    pub fn model_count(&self) -> usize {
        self.models.len()
    }

    /// Triangles built into model `model`'s BVH.
    pub fn model_triangles(&self, model: usize) -> usize {
        self.models.get(model).map_or(0, Bvh::triangle_count)
    }

    /// Triangles of model `model` left out of its BVH (never hit).
    pub fn model_left_out(&self, model: usize) -> usize {
        self.models_left_out.get(model).copied().unwrap_or(0)
    }

    /// Heap bytes of every bottom level (BVH nodes, triangles, pyramids;
    /// the height samples themselves belong to the scene).
    pub fn heap_bytes(&self) -> usize {
        self.model_bytes() + self.terrain_bytes()
    }

    /// Heap bytes of the models' BVHs (nodes, slot tables, triangles).
    pub fn model_bytes(&self) -> usize {
        self.models.iter().map(Bvh::heap_bytes).sum()
    }

    /// Heap bytes of the terrain blocks' min/max pyramids, built or not.
    pub fn terrain_bytes(&self) -> usize {
        self.terrain
            .iter()
            .map(|level| HeightField::heap_bytes_of(&level.grid))
            .sum()
    }
}
