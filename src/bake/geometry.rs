//! Flat world geometry for the consumers that want triangles rather than a
//! traversal: the world bounds that size a directional grid, refinement's
//! per-caster sample surfaces, and the flat triangle list of the raster
//! reference (never the bake's hot path); [`placed_triangle`], how a
//! placed triangle is flattened, is shared with the camera view. Triangles are
//! light-relative f32 (computed in f64 first, so a world far from the
//! origin loses nothing), wound so the geometric normal points to the front
//! face even for mirrored instances.

use super::casters::{CasterTable, Owner, PartCasters};
use crate::scene::{Instance, Scene};
use crate::trace::{transform_box, TraceTriangle, MAX_COORDINATE};
use glam::{DVec3, Vec3};
use rayon::prelude::*;

/// World bounds of everything that can be hit (instances and terrain), or
/// `None` for a world with no geometry. A box that is not finite or reaches
/// beyond [`MAX_COORDINATE`] (an absurd but finite transform, e.g. a scale
/// of 1e20 from a damaged chunk) is left out: its triangles are never
/// traced and it must not stretch a directional
/// light's grid past any possible size. Nor is a box that lies entirely
/// outside the space ([`crate::scene::SpaceRegion`], horizontally): the
/// loader reports such stray placements and leaves them out.
pub fn world_bounds(scene: &Scene) -> Option<(DVec3, DVec3)> {
    let model_bounds: Vec<Option<(DVec3, DVec3)>> = scene
        .models
        .iter()
        .map(|m| m.bounds().map(|(a, b)| (a.as_dvec3(), b.as_dvec3())))
        .collect();
    let region = scene.region();
    let limit = f64::from(MAX_COORDINATE);
    let kept = |&(min, max): &(DVec3, DVec3)| {
        min.is_finite()
            && max.is_finite()
            && min.abs().max(max.abs()).max_element() <= limit
            && region.overlaps_horizontally(min, max)
    };
    // Instance by instance in parallel (millions on a large world): a
    // min and max, the same in any order.
    let parts = scene.instances.par_iter().filter(|i| i.is_complete());
    let parts = parts.flat_map_iter(|instance| {
        let models = instance.parts.iter().flatten();
        let boxes = models.filter_map(|model| model_bounds[*model]);
        boxes.map(|(min, max)| transform_box(&instance.world, min, max))
    });
    let blocks = scene.terrain.par_iter().map(|block| block.bounds());
    parts
        .chain(blocks)
        .filter(kept)
        .reduce_with(|(a, b), (min, max)| (a.min(min), b.max(max)))
}

/// A flat list of triangles, and what was left out.
#[derive(Debug, Default)]
pub struct FlatGeometry {
    pub triangles: Vec<TraceTriangle>,
    /// Zero-area, non-finite or absurdly far (beyond [`MAX_COORDINATE`])
    /// triangles, never hit, left out.
    pub degenerate_triangles: usize,
    /// Some triangle kept belongs to an alpha-tested group.
    pub reaches_alpha_tested: bool,
}

/// Zero area in f32 (the triangle test would never report it), not finite,
/// or beyond [`MAX_COORDINATE`] from the reference point.
fn degenerate(tri: &TraceTriangle) -> bool {
    !tri.is_usable() || tri.has_zero_area()
}

/// Group `group` of model part `part` of an instance, light-relative.
/// Every group of one placed part, each under its caster id.
fn push_part(scene: &Scene, part: &PartCasters, reference: DVec3, out: &mut FlatGeometry) {
    for group in 0..scene.models[part.model].groups.len() {
        let caster = part.first_caster + group as u32;
        push_group(
            scene,
            part.instance,
            part.model,
            group,
            caster,
            reference,
            out,
        );
    }
}

fn push_group(
    scene: &Scene,
    instance: usize,
    model: usize,
    group: usize,
    caster: u32,
    reference: DVec3,
    out: &mut FlatGeometry,
) {
    let instance = &scene.instances[instance];
    let model = &scene.models[model];
    let Some(group) = model.groups.get(group) else {
        return;
    };
    let triangles = model.triangles.get(group.triangles.clone()).unwrap_or(&[]);
    out.triangles.reserve(triangles.len());
    for triangle in triangles {
        let vertices = triangle.map(|i| {
            model
                .positions
                .get(i as usize)
                .copied()
                .unwrap_or(Vec3::NAN)
        });
        let tri = placed_triangle(instance, vertices, caster, reference);
        if degenerate(&tri) {
            out.degenerate_triangles += 1;
        } else {
            out.reaches_alpha_tested |= group.alpha_tested;
            out.triangles.push(tri);
        }
    }
}

/// A model-space triangle of `instance`, relative to `reference`: each
/// vertex through the f64 world transform, then rounded to f32; two
/// vertices swapped for a mirrored instance, whose cull mode the engine
/// flips. The one way a placed triangle is flattened, so every flat view
/// of the world (and the camera, which places triangles as it meets them)
/// holds the same values.
pub fn placed_triangle(
    instance: &Instance,
    model_space: [Vec3; 3],
    caster: u32,
    reference: DVec3,
) -> TraceTriangle {
    let mut vertices =
        model_space.map(|p| (instance.world.transform_point3(p.as_dvec3()) - reference).as_vec3());
    if instance.mirrored {
        vertices.swap(1, 2);
    }
    TraceTriangle { vertices, caster }
}

fn push_block(scene: &Scene, block: usize, caster: u32, reference: DVec3, out: &mut FlatGeometry) {
    for triangle in scene.terrain[block].triangles() {
        let tri = TraceTriangle {
            vertices: triangle.map(|p| (p - reference).as_vec3()),
            caster,
        };
        if degenerate(&tri) {
            out.degenerate_triangles += 1;
        } else {
            out.triangles.push(tri);
        }
    }
}

/// Caster `id`'s triangles, relative to `reference` (refinement's sample
/// surface).
pub fn caster_triangles(
    scene: &Scene,
    casters: &CasterTable,
    id: u32,
    reference: DVec3,
) -> Vec<TraceTriangle> {
    let mut out = FlatGeometry::default();
    match casters.casters.get(id as usize).map(|c| c.owner) {
        Some(Owner::Group {
            instance,
            part,
            group,
        }) => {
            let (instance, group) = (instance as usize, group as usize);
            let parts = scene.instances[instance].parts.iter().flatten();
            if let Some(&model) = parts.clone().nth(part as usize) {
                push_group(scene, instance, model, group, id, reference, &mut out);
            }
        }
        Some(Owner::Terrain { block }) => {
            push_block(scene, block as usize, id, reference, &mut out)
        }
        // No geometry: nothing to sample.
        Some(Owner::Unmodelled { .. }) | None => {}
    }
    out.triangles
}

/// The triangles of the placed parts `parts` (indices into `placed`, every
/// placed part in caster id order) and of the terrain `blocks`, in that
/// order, relative to `reference`: a light's reach
/// (`LightSetup::reach_geometry`).
pub fn parts_geometry(
    scene: &Scene,
    casters: &CasterTable,
    placed: &[PartCasters],
    parts: &[u32],
    blocks: &[u32],
    reference: DVec3,
) -> FlatGeometry {
    // In parallel, collected in id order so the list is the same whatever
    // the thread count.
    let per_part: Vec<FlatGeometry> = parts
        .par_iter()
        .map(|&p| {
            let mut out = FlatGeometry::default();
            push_part(scene, &placed[p as usize], reference, &mut out);
            out
        })
        .collect();
    let per_block: Vec<FlatGeometry> = blocks
        .par_iter()
        .map(|&block| {
            let mut out = FlatGeometry::default();
            let caster = casters.of_block[block as usize];
            push_block(scene, block as usize, caster, reference, &mut out);
            out
        })
        .collect();
    merge(per_part.into_iter().chain(per_block))
}

fn merge(parts: impl Iterator<Item = FlatGeometry>) -> FlatGeometry {
    let mut all = FlatGeometry::default();
    for part in parts {
        all.triangles.extend(part.triangles);
        all.degenerate_triangles += part.degenerate_triangles;
        all.reaches_alpha_tested |= part.reaches_alpha_tested;
    }
    all
}
