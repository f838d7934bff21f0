//! The top level: per light, a BVH over the placed model parts and terrain
//! blocks in its reach, in the light-relative frame. A leaf enters an
//! instance by its inverse transform ([`ToModel`]) and traverses the
//! model's bottom level, or walks a block's height field.
//!
//! Instance boxes come from the model's bounds and the f64 world transform,
//! relative to the light's reference point, rounded outward: a model-space
//! hit lies inside its instance's box up to the rounding of the mapped ray,
//! which the node padding (hundreds of ulps of the magnitude) covers.

use super::blas::BottomLevels;
use super::boxtree::BoxRay;
use super::boxtree::BoxTree;
use super::heightfield::{HeightField, HeightGrid};
use super::instance::ToModel;
use super::triangle::{report_hit, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle, MAX_COORDINATE};
use glam::{DMat4, DVec3, Vec3, Vec3A};
use obvhs::aabb::Aabb;

/// One model part of a placed instance, as the bake hands it over.
#[derive(Clone, Copy, Debug)]
pub struct PlacedPart {
    /// Index into the bottom levels' models.
    pub model: u32,
    /// Model to world (f64).
    pub world: DMat4,
    /// The caster id of the part's group 0; group g is `first_caster + g`.
    pub first_caster: u32,
}

/// The placed parts a top level is built over, read by index. The build
/// reads each part twice (its box, then its entry in tree order) so it never
/// holds every inverse transform beside the tree's build temporaries (a copy
/// that would add to the bake's peak memory).
pub trait PlacedParts {
    fn count(&self) -> usize;
    fn part(&self, index: usize) -> PlacedPart;
}

impl PlacedParts for [PlacedPart] {
    fn count(&self) -> usize {
        self.len()
    }

    fn part(&self, index: usize) -> PlacedPart {
        self[index]
    }
}

/// Parts made on demand by a function of their index.
pub struct PartsFrom<F: Fn(usize) -> PlacedPart> {
    pub count: usize,
    pub part: F,
}

impl<F: Fn(usize) -> PlacedPart> PlacedParts for PartsFrom<F> {
    fn count(&self) -> usize {
        self.count
    }

    fn part(&self, index: usize) -> PlacedPart {
        (self.part)(index)
    }
}

/// What a top-level box was made from, until the tree fixes the order.
#[derive(Clone, Copy)]
enum Source {
    Part(u32),
    Block(PlacedBlock),
}

/// One terrain block and its caster id.
#[derive(Clone, Copy, Debug)]
pub struct PlacedBlock {
    pub block: u32,
    pub caster: u32,
}

#[derive(Clone, Copy, Debug)]
pub(crate) enum Entry {
    Part {
        model: u32,
        first_caster: u32,
        to_model: ToModel,
    },
    Block {
        block: u32,
        caster: u32,
    },
}

/// One light's top level.
#[derive(Debug, Default)]
pub struct TopLevel {
    pub(crate) tree: BoxTree,
    /// In tree order.
    pub(crate) entries: Vec<Entry>,
    pub(crate) reference: DVec3,
    /// Triangles of parts that could not be placed (a box that is not
    /// finite or beyond [`MAX_COORDINATE`], a transform that cannot be
    /// inverted).
    left_out_triangles: usize,
    /// The box holding every entry's box (light-relative), `None` when
    /// there is none.
    bounds: Option<(Vec3, Vec3)>,
}

/// World box of a model-space box under `world`.
pub fn transform_box(world: &DMat4, min: DVec3, max: DVec3) -> (DVec3, DVec3) {
    let mut out_min = DVec3::splat(f64::INFINITY);
    let mut out_max = DVec3::splat(f64::NEG_INFINITY);
    for corner in 0..8 {
        let p = DVec3::new(
            if corner & 1 == 0 { min.x } else { max.x },
            if corner & 2 == 0 { min.y } else { max.y },
            if corner & 4 == 0 { min.z } else { max.z },
        );
        let q = world.transform_point3(p);
        out_min = out_min.min(q);
        out_max = out_max.max(q);
    }
    (out_min, out_max)
}

/// A world box in the light-relative f32 frame, rounded outward; `None`
/// when it is not finite or reaches beyond [`MAX_COORDINATE`].
fn relative_box(min: DVec3, max: DVec3, reference: DVec3) -> Option<(Vec3, Vec3)> {
    let (lo, hi) = (min - reference, max - reference);
    let limit = f64::from(MAX_COORDINATE);
    if !(lo.is_finite() && hi.is_finite()) || lo.abs().max(hi.abs()).max_element() > limit {
        return None;
    }
    let down = |v: f64| {
        let f = v as f32;
        if f64::from(f) > v {
            f.next_down()
        } else {
            f
        }
    };
    let up = |v: f64| {
        let f = v as f32;
        if f64::from(f) < v {
            f.next_up()
        } else {
            f
        }
    };
    Some((
        Vec3::new(down(lo.x), down(lo.y), down(lo.z)),
        Vec3::new(up(hi.x), up(hi.y), up(hi.z)),
    ))
}

impl TopLevel {
    pub fn build(
        bottom: &BottomLevels,
        parts: &(impl PlacedParts + ?Sized),
        blocks: impl ExactSizeIterator<Item = PlacedBlock>,
        reference: DVec3,
    ) -> TopLevel {
        let mut boxes = Vec::with_capacity(parts.count() + blocks.len());
        let mut sources = Vec::with_capacity(parts.count() + blocks.len());
        let mut left_out_triangles = 0;
        for index in 0..parts.count() {
            let part = parts.part(index);
            match part_box(bottom, &part, reference) {
                Some(b) => {
                    boxes.push(b);
                    sources.push(Source::Part(index as u32));
                }
                None => left_out_triangles += bottom.model_triangles(part.model as usize),
            }
        }
        for placed in blocks {
            let Some((grid, field)) = bottom.terrain.get(placed.block as usize) else {
                continue;
            };
            let Some(b) = block_box(grid, field, reference) else {
                left_out_triangles += 2 * grid.cells_x * grid.cells_z;
                continue;
            };
            boxes.push(Aabb::new(Vec3A::from(b.0), Vec3A::from(b.1)));
            sources.push(Source::Block(placed));
        }
        let bounds = boxes.iter().fold(None, |acc: Option<(Vec3, Vec3)>, b| {
            let (lo, hi) = (Vec3::from(b.min), Vec3::from(b.max));
            Some(acc.map_or((lo, hi), |(min, max)| (min.min(lo), max.max(hi))))
        });
        let tree = BoxTree::build(&boxes, 1);
        drop(boxes);
        let entries = tree
            .order()
            .iter()
            .map(|&i| match sources[i as usize] {
                Source::Part(index) => part_entry(&parts.part(index as usize), reference),
                Source::Block(placed) => Entry::Block {
                    block: placed.block,
                    caster: placed.caster,
                },
            })
            .collect();
        TopLevel {
            tree,
            entries,
            reference,
            left_out_triangles,
            bounds,
        }
    }

    /// Placed parts and blocks in the tree.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Triangles of parts and blocks that could not be placed.
    /// The light-relative box holding everything a ray can hit (every
    /// entry's box, each rounded outward), `None` when nothing can be hit.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.bounds
    }

    pub fn left_out_triangles(&self) -> usize {
        self.left_out_triangles
    }

    pub fn heap_bytes(&self) -> usize {
        self.tree.heap_bytes() + self.entries.capacity() * std::mem::size_of::<Entry>()
    }

    /// Every hit, through the trees (`brute_force` false) or by testing every
    /// triangle and cell of every entry (the oracle), with the same
    /// instance-space and height-field arithmetic.
    pub(crate) fn for_each_hit(
        &self,
        bottom: &BottomLevels,
        ray: &TraceRay,
        brute_force: bool,
        mut on_hit: impl FnMut(Hit) -> f32,
    ) {
        if brute_force {
            let mut t_max = ray.t_max;
            for entry in &self.entries {
                t_max = self.entry_hits(bottom, entry, ray, t_max, None, &mut on_hit);
                if t_max < ray.t_min {
                    return;
                }
            }
        } else {
            self.tree.visit(ray, |slot, t_max, node_test| {
                let entry = &self.entries[slot];
                self.entry_hits(bottom, entry, ray, t_max, Some(node_test), &mut on_hit)
            });
        }
    }

    /// Every hit of `ray` on the triangles a flat list of the placed world
    /// would hold, tested where that list holds them, without holding it:
    /// `place(first_caster, triangle)` puts a part's model-space triangle
    /// (its `caster` the group) into the light-relative frame as that list
    /// would (its `caster` the id); terrain is tested where it always is.
    /// The trees only choose the triangles to test, padded for the distance
    /// between the frames, so the hits are those of a BVH over the placed
    /// triangles (unusable ones left out). `on_hit` gets each hit with its
    /// triangle and returns the new t_max. For pictures, whose pixels must
    /// not depend on how the world is instanced.
    pub fn for_each_placed_hit(
        &self,
        bottom: &BottomLevels,
        ray: &TraceRay,
        place: impl Fn(u32, &TraceTriangle) -> TraceTriangle,
        mut on_hit: impl FnMut(Hit, &TraceTriangle) -> f32,
    ) {
        let prepared = PreparedRay::new(ray);
        if !prepared.is_valid() {
            return;
        }
        let reference = self.reference;
        self.tree
            .visit(ray, |slot, t_max, node_test| match self.entries[slot] {
                Entry::Part {
                    model,
                    first_caster,
                    to_model,
                } => {
                    let bvh = &bottom.models[model as usize];
                    bvh.visit_triangles(&to_model.ray(ray), t_max, |triangle, index, t_max| {
                        let placed = place(first_caster, triangle);
                        if !placed.is_usable() {
                            return t_max;
                        }
                        report_hit(&prepared, &placed, index, t_max, &mut |hit| {
                            on_hit(hit, &placed)
                        })
                    })
                }
                Entry::Block { block, caster } => {
                    let (grid, field) = &bottom.terrain[block as usize];
                    let mut relay =
                        |hit: Hit| match grid.hit_triangle(hit.triangle, reference, caster) {
                            Some(triangle) => on_hit(hit, &triangle),
                            None => t_max,
                        };
                    field.hits(grid, reference, node_test, ray, caster, t_max, &mut relay)
                }
            });
    }

    #[inline]
    fn entry_hits(
        &self,
        bottom: &BottomLevels,
        entry: &Entry,
        ray: &TraceRay,
        t_max: f32,
        node_test: Option<&BoxRay>,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        match *entry {
            Entry::Part {
                model,
                first_caster,
                to_model,
            } => {
                let bvh = &bottom.models[model as usize];
                let model_ray = to_model.ray(ray);
                let mut relay = |hit: Hit| {
                    on_hit(Hit {
                        caster: first_caster + hit.caster,
                        ..hit
                    })
                };
                match node_test {
                    None => super::brute::bvh_triangles_hits(bvh, &model_ray, t_max, &mut relay),
                    Some(_) => bvh.hits_within(&model_ray, t_max, &mut relay),
                }
            }
            Entry::Block { block, caster } => {
                let (grid, field) = &bottom.terrain[block as usize];
                match node_test {
                    None => grid.brute_force_hits(self.reference, ray, caster, t_max, on_hit),
                    Some(boxes) => {
                        field.hits(grid, self.reference, boxes, ray, caster, t_max, on_hit)
                    }
                }
            }
        }
    }
}

/// A part's light-relative box; `None` when the part cannot be placed (no
/// bounds, a box that is not finite or too far, a transform that cannot be
/// inverted).
fn part_box(bottom: &BottomLevels, part: &PlacedPart, reference: DVec3) -> Option<Aabb> {
    let (min, max) = bottom.models.get(part.model as usize)?.bounds()?;
    let (min, max) = transform_box(&part.world, min.as_dvec3(), max.as_dvec3());
    ToModel::new(&part.world, reference)?;
    let (lo, hi) = relative_box(min, max, reference)?;
    Some(Aabb::new(Vec3A::from(lo), Vec3A::from(hi)))
}

/// The entry of a part [`part_box`] placed.
fn part_entry(part: &PlacedPart, reference: DVec3) -> Entry {
    Entry::Part {
        model: part.model,
        first_caster: part.first_caster,
        to_model: ToModel::new(&part.world, reference)
            .expect("the same inverse succeeded when the part's box was made"),
    }
}

/// A block's light-relative box, as the top level holds it.
pub(crate) fn block_box(
    grid: &HeightGrid,
    field: &HeightField,
    reference: DVec3,
) -> Option<(Vec3, Vec3)> {
    let (lo, hi) = grid_bounds(grid, field);
    relative_box(lo, hi, reference)
}

/// World box of a block's visible vertices.
fn grid_bounds(grid: &HeightGrid, field: &HeightField) -> (DVec3, DVec3) {
    let (lo, hi) = field.height_range();
    let o = grid.origin;
    let min = DVec3::new(o.x, o.y + f64::from(lo), o.z);
    let max = DVec3::new(
        o.x + grid.chunk_size,
        o.y + f64::from(hi),
        o.z + grid.chunk_size,
    );
    (min, max)
}
