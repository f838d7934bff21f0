//! The bottom levels: one BVH per distinct model in model space and one
//! min/max pyramid per terrain block, built once per bake (in parallel) and
//! shared by every light and every placement. Memory grows with distinct
//! geometry, not with placed copies.

use super::heightfield::{HeightField, HeightGrid};
use super::{Bvh, TraceTriangle};
use glam::Vec3;
use rayon::prelude::*;

pub struct BottomLevels<'a> {
    pub(crate) models: Vec<Bvh>,
    /// Triangles each model's input held that were left out (not finite,
    /// beyond [`super::MAX_COORDINATE`] or of zero area in model space).
    pub(crate) models_left_out: Vec<usize>,
    /// Per model, the groups (ascending) with a triangle built: the
    /// casters a ray entering a placement of it can meet, each with the
    /// box of its triangles.
    pub(crate) model_groups: Vec<Vec<ModelGroup>>,
    pub(crate) terrain: Vec<(HeightGrid<'a>, HeightField)>,
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
        let terrain = terrain
            .into_par_iter()
            .map(|grid| {
                let field = HeightField::build(&grid);
                (grid, field)
            })
            .collect();
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

    /// Heap bytes of the terrain blocks' min/max pyramids.
    pub fn terrain_bytes(&self) -> usize {
        self.terrain.iter().map(|(_, f)| f.heap_bytes()).sum()
    }
}
