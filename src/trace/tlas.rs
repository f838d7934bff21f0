//! The top level: per light, a BVH over the placed model parts and terrain
//! blocks in its reach, in the light-relative frame. A leaf enters an
//! instance by its inverse transform ([`ToModel`]) and traverses the
//! model's bottom level, or walks a block's height field.
//!
//! Instance boxes come from the model's bounds and the f64 world transform,
//! relative to the light's reference point, rounded outward: a model-space
//! hit lies inside its instance's box up to the rounding of the mapped ray,
//! which the node padding (hundreds of ulps of the magnitude) covers.

use super::blas::{BottomLevels, ModelGroup};
use super::boxtree::BoxRay;
use super::boxtree::BoxTree;
use super::heightfield::HeightGrid;
use super::instance::ToModel;
use super::triangle::{report_hit, PreparedRay};
use super::{DropsRepeat, Hit, TraceRay, TraceTriangle, MAX_COORDINATE};
use glam::{DMat4, DVec3, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use rayon::prelude::*;

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
        /// The part's coincident copies (see [`TopLevel::placements`]).
        copies: CopyRange,
    },
    Block {
        block: u32,
        caster: u32,
    },
}

/// Where an entry's coincident copies' first caster ids lie in
/// [`TopLevel::copy_casters`] (none: `count` 0).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct CopyRange {
    start: u32,
    count: u32,
}

/// Parts whose boxes one parallel step of [`TopLevel::build`] makes: a
/// few megabytes of them at a time.
const PARTS_PER_WAVE: usize = 1 << 16;

/// The first caster ids of a part entry and of its coincident copies:
/// parts placed with the same model at the bit-identical transform (an
/// editor's duplicate key leaves such stacks), which are one entry of the
/// tree. A ray meets every copy where it meets the first, with the same
/// arithmetic (the same inverse transform maps it to the same model-space
/// ray), so the traversals walk the model once and report each hit for
/// every copy: a stack costs one traversal, not one per copy.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Placements<'t> {
    pub(crate) first: u32,
    pub(crate) copies: &'t [u32],
}

impl Placements<'_> {
    /// Every first caster id, the entry's own first.
    #[inline]
    pub(crate) fn iter(&self) -> impl Iterator<Item = u32> + '_ {
        std::iter::once(self.first).chain(self.copies.iter().copied())
    }

    /// A hit of the first placement with its caster id (`hit.caster`:
    /// the group within the model).
    #[inline]
    pub(crate) fn first_hit(&self, hit: Hit) -> Hit {
        Hit {
            caster: self.first + hit.caster,
            ..hit
        }
    }

    /// The hits `found` of the first placement (each with its ray's lane
    /// and the group within the model as its caster) reported again for
    /// each copy in turn, with the copy's ids, those still within their
    /// lane's `t_max`, which takes what `on_hit` returns (a larger or NaN
    /// value is ignored). Exact: a copy's hits are the first placement's,
    /// and one the first placement's traversal passed over lay beyond a
    /// t_max that has only shrunk since. Copy by copy, so the rays' t_max
    /// shrink to what the first copies settle, and a hit beyond its ray's
    /// t_max leaves `found` (it stays beyond): each copy after those costs
    /// about its hits at the front.
    ///
    /// `repeated`: the groups (bits, groups 0 to 63) whose hits the caller
    /// drops from the third placement on ([`super::DropsRepeat`]): once the
    /// second is replayed, those hits leave `found`.
    pub(crate) fn replay(
        &self,
        found: &mut Vec<(usize, Hit)>,
        t_max: &mut [f32],
        repeated: u64,
        mut on_hit: impl FnMut(usize, Hit) -> f32,
    ) {
        for (k, &first) in self.copies.iter().enumerate() {
            if k == 1 && repeated != 0 {
                found.retain(|(_, hit)| hit.caster >= 64 || repeated & (1 << hit.caster) == 0);
            }
            found.retain(|&(lane, hit)| {
                if hit.t > t_max[lane] {
                    return false;
                }
                let caster = first + hit.caster;
                let next = on_hit(lane, Hit { caster, ..hit });
                if next < t_max[lane] {
                    t_max[lane] = next;
                }
                true
            });
        }
    }
}

/// One light's top level.
#[derive(Debug, Default)]
pub struct TopLevel {
    pub(crate) tree: BoxTree,
    /// In tree order.
    pub(crate) entries: Vec<Entry>,
    /// The first caster ids of the entries' coincident copies, entry by
    /// entry ([`CopyRange`]).
    copy_casters: Vec<u32>,
    pub(crate) reference: DVec3,
    /// Triangles of parts that could not be placed (a box that is not
    /// finite or beyond [`MAX_COORDINATE`], a transform that cannot be
    /// inverted).
    left_out_triangles: usize,
    /// The box holding every entry's box (light-relative), `None` when
    /// there is none.
    bounds: Option<(Vec3, Vec3)>,
}

/// World box of a model-space box under `world`: the box around its eight
/// corners placed by `DMat4::transform_point3`, bit for bit.
///
/// A placed corner's coordinate is `w + (z + (y + x))`, one of two terms
/// per axis (the axis column times the box's low or high coordinate), in
/// `transform_point3`'s order. Rounded addition never decreases when an
/// operand grows, so the lowest corner takes the lower term of each axis
/// and the highest the higher: six products instead of eight transforms,
/// on the hot path of every pass over the placed parts. Where a product
/// or sum is not finite the corners are placed one by one, as before.
pub fn transform_box(world: &DMat4, min: DVec3, max: DVec3) -> (DVec3, DVec3) {
    let terms = |axis: DVec3, low: f64, high: f64| {
        let (a, b) = (axis * low, axis * high);
        (a.min(b), a.max(b), a.is_finite() && b.is_finite())
    };
    let (x_low, x_high, x_finite) = terms(world.x_axis.truncate(), min.x, max.x);
    let (y_low, y_high, y_finite) = terms(world.y_axis.truncate(), min.y, max.y);
    let (z_low, z_high, z_finite) = terms(world.z_axis.truncate(), min.z, max.z);
    let w = world.w_axis.truncate();
    let low = w + (z_low + (y_low + x_low));
    let high = w + (z_high + (y_high + x_high));
    if x_finite && y_finite && z_finite && low.is_finite() && high.is_finite() {
        (low, high)
    } else {
        transform_corners(world, min, max)
    }
}

/// [`transform_box`] corner by corner.
fn transform_corners(world: &DMat4, min: DVec3, max: DVec3) -> (DVec3, DVec3) {
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

/// What a top level over some parts and blocks would bound: the
/// light-relative box of every entry ([`TopLevel::bounds`]) and the
/// triangles it would leave out ([`TopLevel::left_out_triangles`]),
/// without building it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Extent {
    pub bounds: Option<(Vec3, Vec3)>,
    pub left_out_triangles: usize,
}

impl Extent {
    /// The extent of the parts and blocks a [`TopLevel::build`] with the
    /// same arguments would place (coincident copies share their box).
    pub fn of(
        bottom: &BottomLevels,
        parts: &(impl PlacedParts + Sync + ?Sized),
        blocks: impl Iterator<Item = PlacedBlock>,
        reference: DVec3,
    ) -> Extent {
        // In parallel: a whole world's parts each need an inverse, and
        // bounds and counts come out the same in any order.
        let mut extent = (0..parts.count())
            .into_par_iter()
            .fold(Extent::default, |mut extent, index| {
                let part = parts.part(index);
                match part_box(bottom, &part, reference) {
                    Some(b) => extent.add(Vec3::from(b.min), Vec3::from(b.max)),
                    None => {
                        extent.left_out_triangles += bottom.model_triangles(part.model as usize)
                    }
                }
                extent
            })
            .reduce(Extent::default, |mut a, b| {
                if let Some((lo, hi)) = b.bounds {
                    a.add(lo, hi);
                }
                a.left_out_triangles += b.left_out_triangles;
                a
            });
        for placed in blocks {
            let Some(level) = bottom.terrain.get(placed.block as usize) else {
                continue;
            };
            match block_box(&level.grid, level.height_range(), reference) {
                Some((lo, hi)) => extent.add(lo, hi),
                None => extent.left_out_triangles += 2 * level.grid.cells_x * level.grid.cells_z,
            }
        }
        extent
    }

    fn add(&mut self, lo: Vec3, hi: Vec3) {
        self.bounds = Some(
            self.bounds
                .map_or((lo, hi), |(min, max)| (min.min(lo), max.max(hi))),
        );
    }
}

impl TopLevel {
    pub fn build(
        bottom: &BottomLevels,
        parts: &(impl PlacedParts + Sync + ?Sized),
        blocks: impl ExactSizeIterator<Item = PlacedBlock>,
        reference: DVec3,
    ) -> TopLevel {
        let mut boxes = Vec::with_capacity(parts.count() + blocks.len());
        let mut sources = Vec::with_capacity(parts.count() + blocks.len());
        let mut placements = Vec::with_capacity(parts.count());
        let mut left_out_triangles = 0;
        // Each part's box and inverse in parallel, a wave at a time, so
        // the lists fill in index order without a second copy of them.
        for wave in (0..parts.count()).step_by(PARTS_PER_WAVE) {
            let found: Vec<Option<(Aabb, u64)>> = (wave..parts.count().min(wave + PARTS_PER_WAVE))
                .into_par_iter()
                .map(|index| {
                    let part = parts.part(index);
                    part_box(bottom, &part, reference).map(|b| (b, placement_hash(&part)))
                })
                .collect();
            for (index, found) in (wave..).zip(found) {
                match found {
                    Some((b, hash)) => {
                        boxes.push(b);
                        sources.push(Source::Part(index as u32));
                        placements.push((hash, index as u32));
                    }
                    None => {
                        let model = parts.part(index).model as usize;
                        left_out_triangles += bottom.model_triangles(model);
                    }
                }
            }
        }
        let coincident = Coincident::find(parts, placements);
        if !coincident.copies.is_empty() {
            let mut kept = sources.iter().map(|s| match s {
                Source::Part(index) => !coincident.is_copy(*index),
                Source::Block(_) => true,
            });
            boxes.retain(|_| kept.next() == Some(true));
            sources.retain(|s| !matches!(s, Source::Part(index) if coincident.is_copy(*index)));
        }
        for placed in blocks {
            let Some(level) = bottom.terrain.get(placed.block as usize) else {
                continue;
            };
            let Some(b) = block_box(&level.grid, level.height_range(), reference) else {
                left_out_triangles += 2 * level.grid.cells_x * level.grid.cells_z;
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
        // The entries in parallel (an inverse each), straight into their
        // vector; their copies' ranges after, in slot order.
        let mut entries: Vec<Entry> = tree
            .order()
            .par_iter()
            .map(|&i| match sources[i as usize] {
                Source::Part(index) => {
                    part_entry(&parts.part(index as usize), reference, CopyRange::default())
                }
                Source::Block(placed) => Entry::Block {
                    block: placed.block,
                    caster: placed.caster,
                },
            })
            .collect();
        let mut copy_casters = Vec::new();
        if !coincident.copies.is_empty() {
            for (entry, &i) in entries.iter_mut().zip(tree.order()) {
                let (Entry::Part { copies: range, .. }, Source::Part(index)) =
                    (entry, sources[i as usize])
                else {
                    continue;
                };
                let copies = coincident.copies.get(&index).map_or(&[][..], |c| &c[..]);
                *range = CopyRange {
                    start: copy_casters.len() as u32,
                    count: copies.len() as u32,
                };
                copy_casters.extend(copies.iter().map(|&c| parts.part(c as usize).first_caster));
            }
        }
        TopLevel {
            tree,
            entries,
            copy_casters,
            reference,
            left_out_triangles,
            bounds,
        }
    }

    /// The first caster ids of a part entry `first_caster` with `copies`.
    #[inline]
    pub(crate) fn placements(&self, first_caster: u32, copies: CopyRange) -> Placements<'_> {
        let start = copies.start as usize;
        Placements {
            first: first_caster,
            copies: &self.copy_casters[start..start + copies.count as usize],
        }
    }

    /// Placed parts (each coincident copy counted) and blocks in the tree.
    pub fn len(&self) -> usize {
        self.entries.len() + self.copy_casters.len()
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
        self.tree.heap_bytes()
            + self.entries.capacity() * std::mem::size_of::<Entry>()
            + self.copy_casters.capacity() * 4
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
                t_max = self.entry_hits(bottom, entry, ray, t_max, EntryTest::Oracle, &mut on_hit);
                if t_max < ray.t_min {
                    return;
                }
            }
        } else {
            self.for_each_hit_dropping(bottom, ray, None, on_hit);
        }
    }

    /// [`Self::for_each_hit`] through the trees, leaving out the hits of
    /// a stack's third and later placements that `repeats` drops
    /// ([`DropsRepeat`]).
    pub(crate) fn for_each_hit_dropping(
        &self,
        bottom: &BottomLevels,
        ray: &TraceRay,
        repeats: Option<&DropsRepeat>,
        mut on_hit: impl FnMut(Hit) -> f32,
    ) {
        self.tree.visit(ray, |slot, t_max, node_test| {
            let entry = &self.entries[slot];
            let test = EntryTest::Trees(node_test, repeats);
            self.entry_hits(bottom, entry, ray, t_max, test, &mut on_hit)
        });
    }

    /// Every hit of `ray` on the triangles a flat list of the placed world
    /// would hold, tested where that list holds them, without holding it:
    /// `place(first_caster, triangle)` puts a part's model-space triangle
    /// (its `caster` the group) into the light-relative frame as that list
    /// would (its `caster` the id); a coincident copy's triangles are its
    /// first part's with the copy's ids. Terrain is tested where it always
    /// is.
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
                    copies,
                } => {
                    let bvh = &bottom.models[model as usize];
                    let placements = self.placements(first_caster, copies);
                    let mut found = Vec::new();
                    let model_ray = to_model.ray(ray);
                    let t_max = bvh.visit_triangles(&model_ray, t_max, |triangle, index, t_max| {
                        let placed = place(first_caster, triangle);
                        if !placed.is_usable() {
                            return t_max;
                        }
                        report_hit(&prepared, &placed, index, t_max, &mut |hit| {
                            if !placements.copies.is_empty() {
                                found.push((hit, placed, triangle.caster));
                            }
                            on_hit(hit, &placed)
                        })
                    });
                    // A copy's triangles are the first placement's, with its ids.
                    let mut t_max = t_max;
                    for &copy in placements.copies {
                        for &(hit, placed, group) in &found {
                            if hit.t <= t_max {
                                let caster = copy + group;
                                let triangle = TraceTriangle { caster, ..placed };
                                t_max = t_max.min(on_hit(Hit { caster, ..hit }, &triangle));
                            }
                        }
                    }
                    t_max
                }
                Entry::Block { block, caster } => {
                    let level = &bottom.terrain[block as usize];
                    let (grid, field) = (&level.grid, level.field());
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
        test: EntryTest,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        match *entry {
            Entry::Part {
                model,
                first_caster,
                to_model,
                copies,
            } => {
                let bvh = &bottom.models[model as usize];
                let model_ray = to_model.ray(ray);
                let placements = self.placements(first_caster, copies);
                match test {
                    // The oracle tests each copy's triangles on their own.
                    EntryTest::Oracle => placements.iter().fold(t_max, |t_max, first| {
                        let mut relay = |hit: Hit| {
                            on_hit(Hit {
                                caster: first + hit.caster,
                                ..hit
                            })
                        };
                        super::brute::bvh_triangles_hits(bvh, &model_ray, t_max, &mut relay)
                    }),
                    EntryTest::Trees(..) if placements.copies.is_empty() => {
                        let mut relay = |hit: Hit| on_hit(placements.first_hit(hit));
                        bvh.hits_within(&model_ray, t_max, &mut relay)
                    }
                    EntryTest::Trees(_, repeats) => {
                        let mut found = Vec::new();
                        let mut relay = |hit: Hit| {
                            found.push((0, hit));
                            on_hit(placements.first_hit(hit))
                        };
                        let mut t_max = [bvh.hits_within(&model_ray, t_max, &mut relay)];
                        if !found.is_empty() {
                            let groups = &bottom.model_groups[model as usize];
                            let repeated = repeated_groups(repeats, &placements, groups);
                            placements
                                .replay(&mut found, &mut t_max, repeated, |_, hit| on_hit(hit));
                        }
                        t_max[0]
                    }
                }
            }
            Entry::Block { block, caster } => {
                let level = &bottom.terrain[block as usize];
                let (grid, field) = (&level.grid, level.field());
                match test {
                    EntryTest::Oracle => {
                        grid.brute_force_hits(self.reference, ray, caster, t_max, on_hit)
                    }
                    EntryTest::Trees(boxes, _) => {
                        field.hits(grid, self.reference, boxes, ray, caster, t_max, on_hit)
                    }
                }
            }
        }
    }
}

/// How [`TopLevel::entry_hits`] finds an entry's hits: testing every
/// triangle and cell (the oracle), or through its trees with the node
/// test the top level's walk made, leaving out the repeats a caller drops.
#[derive(Clone, Copy)]
enum EntryTest<'a> {
    Oracle,
    Trees(&'a BoxRay, Option<&'a DropsRepeat<'a>>),
}

/// The groups (bits, groups 0 to 63) whose hits `drops` drops on every
/// placement from the third on, given the first two's ([`DropsRepeat`]);
/// asked once an entry a packet or ray, not a hit.
pub(crate) fn repeated_groups(
    drops: Option<&DropsRepeat>,
    placements: &Placements,
    groups: &[ModelGroup],
) -> u64 {
    let (Some(drops), [second, rest @ ..]) = (drops, placements.copies) else {
        return 0;
    };
    if rest.is_empty() {
        return 0;
    }
    let first = placements.first;
    groups
        .iter()
        .filter(|g| g.group < 64)
        .filter(|g| {
            let anchors = [first + g.group, second + g.group];
            rest.iter().all(|&copy| drops(copy + g.group, anchors))
        })
        .fold(0, |bits, g| bits | 1 << g.group)
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
fn part_entry(part: &PlacedPart, reference: DVec3, copies: CopyRange) -> Entry {
    Entry::Part {
        model: part.model,
        first_caster: part.first_caster,
        to_model: ToModel::new(&part.world, reference)
            .expect("the same inverse succeeded when the part's box was made"),
        copies,
    }
}

/// A hash of a part's model and transform bits (FxHash's mixing).
fn placement_hash(part: &PlacedPart) -> u64 {
    let bits = part.world.to_cols_array().map(f64::to_bits);
    bits.iter().fold(u64::from(part.model), |h, &b| {
        (h.rotate_left(5) ^ b).wrapping_mul(0x517c_c1b7_2722_0a95)
    })
}

/// Whether two parts place one model at bit-identical transforms.
fn same_placement(a: &PlacedPart, b: &PlacedPart) -> bool {
    let bits = |p: &PlacedPart| p.world.to_cols_array().map(f64::to_bits);
    a.model == b.model && bits(a) == bits(b)
}

/// The coincident copies among the parts: per part with later copies
/// (its lowest index), the copies' indices, ascending.
struct Coincident {
    copies: std::collections::HashMap<u32, Vec<u32>>,
    /// Bits of the parts that are a copy of an earlier one.
    copy_bits: Vec<u64>,
}

impl Coincident {
    /// From `(placement_hash, index)` of every placed part.
    fn find(parts: &(impl PlacedParts + ?Sized), mut placements: Vec<(u64, u32)>) -> Coincident {
        placements.sort_unstable();
        let mut found = Coincident {
            copies: Default::default(),
            copy_bits: Vec::new(),
        };
        for run in placements
            .chunk_by(|a, b| a.0 == b.0)
            .filter(|r| r.len() > 1)
        {
            // Usually one placement a hash: compare with each distinct one
            // of the run so far.
            let mut firsts: Vec<(u32, PlacedPart)> = Vec::new();
            for &(_, index) in run {
                let part = parts.part(index as usize);
                match firsts
                    .iter()
                    .find(|(_, first)| same_placement(first, &part))
                {
                    Some(&(first, _)) => found.add(first, index, parts.count()),
                    None => firsts.push((index, part)),
                }
            }
        }
        found
    }

    fn add(&mut self, first: u32, copy: u32, parts: usize) {
        self.copies.entry(first).or_default().push(copy);
        if self.copy_bits.is_empty() {
            self.copy_bits = vec![0; parts.div_ceil(64)];
        }
        self.copy_bits[copy as usize / 64] |= 1 << (copy % 64);
    }

    fn is_copy(&self, index: u32) -> bool {
        self.copy_bits
            .get(index as usize / 64)
            .is_some_and(|w| w & (1 << (index % 64)) != 0)
    }
}

/// A block's light-relative box, as the top level holds it.
pub(crate) fn block_box(
    grid: &HeightGrid,
    height_range: (f32, f32),
    reference: DVec3,
) -> Option<(Vec3, Vec3)> {
    let (lo, hi) = grid_bounds(grid, height_range);
    relative_box(lo, hi, reference)
}

/// World box of a block's visible vertices, chunk-local heights within
/// `(lo, hi)`.
fn grid_bounds(grid: &HeightGrid, (lo, hi): (f32, f32)) -> (DVec3, DVec3) {
    let o = grid.origin;
    let min = DVec3::new(o.x, o.y + f64::from(lo), o.z);
    let max = DVec3::new(
        o.x + grid.chunk_size,
        o.y + f64::from(hi),
        o.z + grid.chunk_size,
    );
    (min, max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use glam::DQuat;

    /// Same bits as placing the eight corners: rotated, scaled (mirrored
    /// too), far-off and degenerate boxes, and a transform that overflows.
    #[test]
    fn a_box_is_placed_as_its_corners_are() {
        let mut rng = Rng::new(0x7b0c);
        let same = |a: DVec3, b: DVec3| {
            a.to_array().map(f64::to_bits) == b.to_array().map(f64::to_bits) || a == b
        };
        for _ in 0..20_000 {
            let scale = DVec3::new(
                rng.range(-3.0, 3.0),
                rng.range(-3.0, 3.0),
                rng.range(-3.0, 3.0),
            );
            let rotation = DQuat::from_axis_angle(rng.unit_vector(), rng.range(-4.0, 4.0));
            let far = 10f64.powi(rng.below(8) as i32);
            let offset = DVec3::new(
                rng.range(-far, far),
                rng.range(-far, far),
                rng.range(-far, far),
            );
            let world = DMat4::from_scale_rotation_translation(scale, rotation, offset);
            let a = DVec3::new(
                rng.range(-50.0, 50.0),
                rng.range(-50.0, 50.0),
                rng.range(-50.0, 50.0),
            );
            let b = if rng.chance(0.1) {
                a
            } else {
                a + rng.unit_vector().abs() * rng.range(0.0, 80.0)
            };
            let (fast, corners) = (transform_box(&world, a, b), transform_corners(&world, a, b));
            assert!(
                same(fast.0, corners.0) && same(fast.1, corners.1),
                "{world:?} {a} {b}"
            );
        }
        let huge = DMat4::from_scale(DVec3::splat(1e300));
        let (a, b) = (DVec3::splat(-1e10), DVec3::splat(1e10));
        assert_eq!(transform_box(&huge, a, b), transform_corners(&huge, a, b));
    }
}
