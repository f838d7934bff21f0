//! World-space triangles for one light: every caster's triangles inside the
//! light's reach, in f32 relative to the light's reference point (computed in
//! f64 first, so a world far from the origin loses nothing), wound so the
//! geometric normal points to the front face even for mirrored instances.

use super::casters::CasterTable;
use crate::light::TexelGrid;
use crate::scene::Scene;
use crate::trace::{TraceTriangle, MAX_COORDINATE};
use glam::{DMat4, DVec3, Vec3};
use rayon::prelude::*;

/// World bounds of everything that can be hit (instances and terrain), or
/// `None` for a world with no geometry. A box that is not finite or reaches
/// beyond [`MAX_COORDINATE`] (an absurd but finite transform, e.g. a scale
/// of 1e20 from a damaged chunk) is left out: its triangles are never
/// traced (see [`degenerate`]) and it must not stretch a directional
/// light's grid past any possible size. Nor is a box that lies entirely
/// outside the space ([`crate::scene::SpaceRegion`], horizontally): the
/// loader reports such stray placements and leaves them out.
pub fn world_bounds(scene: &Scene) -> Option<(DVec3, DVec3)> {
    let model_bounds: Vec<Option<(DVec3, DVec3)>> = scene
        .models
        .iter()
        .map(|m| m.bounds().map(|(a, b)| (a.as_dvec3(), b.as_dvec3())))
        .collect();
    let mut bounds: Option<(DVec3, DVec3)> = None;
    let region = scene.region();
    let mut add = |min: DVec3, max: DVec3| {
        let limit = f64::from(MAX_COORDINATE);
        if !(min.is_finite() && max.is_finite())
            || min.abs().max(max.abs()).max_element() > limit
            || !region.overlaps_horizontally(min, max)
        {
            return;
        }
        bounds = Some(match bounds {
            Some((a, b)) => (a.min(min), b.max(max)),
            None => (min, max),
        });
    };
    for instance in scene.instances.iter().filter(|i| i.is_complete()) {
        for model in instance.parts.iter().flatten() {
            if let Some((min, max)) = model_bounds[*model] {
                let (min, max) = transform_box(&instance.world, min, max);
                add(min, max);
            }
        }
    }
    for block in &scene.terrain {
        let (min, max) = block.bounds();
        add(min, max);
    }
    bounds
}

pub fn transform_box(m: &DMat4, min: DVec3, max: DVec3) -> (DVec3, DVec3) {
    let mut out_min = DVec3::splat(f64::INFINITY);
    let mut out_max = DVec3::splat(f64::NEG_INFINITY);
    for corner in 0..8 {
        let p = DVec3::new(
            if corner & 1 == 0 { min.x } else { max.x },
            if corner & 2 == 0 { min.y } else { max.y },
            if corner & 4 == 0 { min.z } else { max.z },
        );
        let q = m.transform_point3(p);
        out_min = out_min.min(q);
        out_max = out_max.max(q);
    }
    (out_min, out_max)
}

/// What went into one light's BVH, and what was left out.
#[derive(Debug, Default)]
pub struct LightGeometry {
    pub triangles: Vec<TraceTriangle>,
    /// Instances / terrain blocks entirely outside the light's reach.
    pub instances_out_of_reach: usize,
    pub blocks_out_of_reach: usize,
    /// Zero-area, non-finite or absurdly far (beyond [`MAX_COORDINATE`])
    /// triangles, never hit, left out.
    pub degenerate_triangles: usize,
    /// Some included triangle belongs to an alpha-tested group.
    pub reaches_alpha_tested: bool,
}

/// `relative` maps a world point into the light's f32 frame.
fn relative(p: DVec3, reference: DVec3) -> Vec3 {
    (p - reference).as_vec3()
}

/// Zero area in f32 (the triangle test would never report it), not finite,
/// or beyond [`MAX_COORDINATE`] from the light's reference point (the trace
/// would drop it silently; here it is counted).
fn degenerate(v: &[Vec3; 3]) -> bool {
    let n = (v[1] - v[0]).cross(v[2] - v[0]);
    !v.iter()
        .all(|p| p.is_finite() && p.abs().max_element() <= MAX_COORDINATE)
        || n == Vec3::ZERO
        || !n.is_finite()
}

pub fn light_geometry(scene: &Scene, casters: &CasterTable, grid: &TexelGrid) -> LightGeometry {
    geometry_in_reach(scene, casters, grid.reference_point(), |min, max| {
        grid.reaches(min, max)
    })
}

/// Every caster's triangles, with nothing left out for reach (a camera that
/// looks at the world, not a light), relative to `reference`.
pub fn all_geometry(scene: &Scene, casters: &CasterTable, reference: DVec3) -> LightGeometry {
    geometry_in_reach(scene, casters, reference, |_, _| true)
}

/// The triangles of every caster some of whose box `reaches` accepts, in
/// scene order (instances, then terrain blocks).
fn geometry_in_reach(
    scene: &Scene,
    casters: &CasterTable,
    reference: DVec3,
    reaches: impl Fn(DVec3, DVec3) -> bool + Sync,
) -> LightGeometry {
    let model_bounds: Vec<Option<(DVec3, DVec3)>> = scene
        .models
        .iter()
        .map(|m| m.bounds().map(|(a, b)| (a.as_dvec3(), b.as_dvec3())))
        .collect();

    // Instances in parallel, collected in scene order so the triangle list
    // (and so every caster id) is the same whatever the thread count.
    let per_instance: Vec<LightGeometry> = scene
        .instances
        .par_iter()
        .enumerate()
        .map(|(index, instance)| {
            let mut out = LightGeometry::default();
            let Some(first) = casters.first_of_instance[index] else {
                return out;
            };
            let in_reach = instance.parts.iter().flatten().any(|&model| {
                model_bounds[model].is_some_and(|(min, max)| {
                    let (min, max) = transform_box(&instance.world, min, max);
                    reaches(min, max)
                })
            });
            if !in_reach {
                out.instances_out_of_reach = 1;
                return out;
            }
            let mut caster = first;
            for &model in instance.parts.iter().flatten() {
                let model = &scene.models[model];
                for group in &model.groups {
                    let alpha = casters.casters[caster as usize].alpha_tested;
                    for triangle in &model.triangles[group.triangles.clone()] {
                        let mut v = triangle.map(|i| {
                            let p = model.positions[i as usize].as_dvec3();
                            relative(instance.world.transform_point3(p), reference)
                        });
                        if instance.mirrored {
                            // The engine flips the cull mode of mirrored
                            // models; flipping the winding is the same.
                            v.swap(1, 2);
                        }
                        if degenerate(&v) {
                            out.degenerate_triangles += 1;
                            continue;
                        }
                        out.reaches_alpha_tested |= alpha;
                        out.triangles.push(TraceTriangle {
                            vertices: v,
                            caster,
                        });
                    }
                    caster += 1;
                }
            }
            out
        })
        .collect();

    let per_block: Vec<LightGeometry> = scene
        .terrain
        .par_iter()
        .enumerate()
        .map(|(index, block)| {
            let mut out = LightGeometry::default();
            let (min, max) = block.bounds();
            if !reaches(min, max) {
                out.blocks_out_of_reach = 1;
                return out;
            }
            let caster = casters.of_block[index];
            for triangle in block.triangles() {
                let lo = triangle[0].min(triangle[1]).min(triangle[2]);
                let hi = triangle[0].max(triangle[1]).max(triangle[2]);
                if !reaches(lo, hi) {
                    continue;
                }
                let v = triangle.map(|p| relative(p, reference));
                if degenerate(&v) {
                    out.degenerate_triangles += 1;
                    continue;
                }
                out.triangles.push(TraceTriangle {
                    vertices: v,
                    caster,
                });
            }
            out
        })
        .collect();

    let mut all = LightGeometry {
        triangles: Vec::with_capacity(
            per_instance
                .iter()
                .chain(&per_block)
                .map(|g| g.triangles.len())
                .sum(),
        ),
        ..LightGeometry::default()
    };
    for part in per_instance.into_iter().chain(per_block) {
        all.triangles.extend(part.triangles);
        all.instances_out_of_reach += part.instances_out_of_reach;
        all.blocks_out_of_reach += part.blocks_out_of_reach;
        all.degenerate_triangles += part.degenerate_triangles;
        all.reaches_alpha_tested |= part.reaches_alpha_tested;
    }
    all
}
