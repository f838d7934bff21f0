//! One light's rays: texel tiles in parallel, each ray's hits filtered by
//! face culling and the below-ground test, then classified (SPEC §4). The
//! result is a set of useful casters, the same for any thread count (tiles
//! are OR-ed, and each ray's answer does not depend on traversal order).

use super::casters::CasterTable;
use super::ground::Ground;
use crate::classify::{self, Passes, RayHit};
use crate::formats::bake_settings::FaceCulling;
use crate::light::{TexelGrid, TexelRay};
use crate::trace::{Bvh, Hit, TraceRay, TraceTriangle};
use glam::DVec3;
use rayon::prelude::*;

/// Receives the number of rays traced, tile by tile, from worker threads.
pub trait RayCounter: Sync {
    fn add(&self, rays: u64);
}

/// Texels per tile side: big enough to amortise scheduling, small enough
/// to balance 2–64 threads and to report progress often.
pub const TILE: u32 = 32;

/// The rules a ray applies to its hits.
#[derive(Debug, Clone, Copy)]
pub struct RayRules {
    pub face_culling: FaceCulling,
    pub height_bias: f64,
    pub tie_epsilon: f32,
    pub passes: Passes,
}

/// A set of caster ids as bits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CasterSet(Vec<u64>);

impl CasterSet {
    pub fn new(casters: usize) -> Self {
        CasterSet(vec![0; casters.div_ceil(64)])
    }

    pub fn insert(&mut self, caster: u32) {
        self.0[caster as usize / 64] |= 1 << (caster % 64);
    }

    pub fn contains(&self, caster: u32) -> bool {
        self.0[caster as usize / 64] & (1 << (caster % 64)) != 0
    }

    pub fn union(mut self, other: &CasterSet) -> Self {
        for (a, b) in self.0.iter_mut().zip(&other.0) {
            *a |= b;
        }
        self
    }

    pub fn len(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// How rays find their hits: the BVH, or (for the oracle) every triangle.
pub enum Tracer<'a> {
    Bvh(&'a Bvh),
    BruteForce(&'a [TraceTriangle]),
}

impl Tracer<'_> {
    fn for_each_hit(&self, ray: &TraceRay, on_hit: impl FnMut(Hit) -> f32) {
        match self {
            Tracer::Bvh(bvh) => bvh.for_each_hit(ray, on_hit),
            Tracer::BruteForce(triangles) => crate::trace::brute_force_hits(triangles, ray, on_hit),
        }
    }
}

/// Traces every texel of `grid` with `samples`² rays each (1: the texel
/// centre; k: a k×k pattern of sub-texel centres); `rays_done` hears of
/// every finished tile so a caller can show progress.
pub fn trace_light(
    grid: &TexelGrid,
    tracer: &Tracer<'_>,
    casters: &CasterTable,
    ground: Option<&Ground<'_>>,
    rules: RayRules,
    samples: u32,
    rays_done: &dyn RayCounter,
) -> CasterSet {
    let samples = samples.max(1);
    let step = 1.0 / samples as f64;
    let tiles_x = grid.width().div_ceil(TILE);
    let tiles_y = grid.height().div_ceil(TILE);
    let tiles = grid.faces() as u64 * tiles_x as u64 * tiles_y as u64;
    (0..tiles)
        .into_par_iter()
        .fold(
            || (CasterSet::new(casters.len()), Vec::new()),
            |(mut useful, mut hits), tile| {
                let face = (tile / (tiles_x as u64 * tiles_y as u64)) as usize;
                let within = tile % (tiles_x as u64 * tiles_y as u64);
                let x0 = (within % tiles_x as u64) as u32 * TILE;
                let y0 = (within / tiles_x as u64) as u32 * TILE;
                let x1 = (x0 + TILE).min(grid.width());
                let y1 = (y0 + TILE).min(grid.height());
                for y in y0..y1 {
                    for x in x0..x1 {
                        for sy in 0..samples {
                            for sx in 0..samples {
                                let ray = grid.ray_through(
                                    face,
                                    x as f64 + (sx as f64 + 0.5) * step,
                                    y as f64 + (sy as f64 + 0.5) * step,
                                );
                                trace_ray(
                                    &ray,
                                    grid.reference_point(),
                                    tracer,
                                    casters,
                                    ground,
                                    rules,
                                    &mut hits,
                                    &mut useful,
                                );
                            }
                        }
                    }
                }
                rays_done.add(((x1 - x0) * (y1 - y0)) as u64 * (samples as u64).pow(2));
                (useful, hits)
            },
        )
        .map(|(useful, _)| useful)
        .reduce(|| CasterSet::new(casters.len()), |a, b| a.union(&b))
}

/// One ray of the light: its hits filtered by face culling and the
/// below-ground test, classified, and the useful casters added to `useful`.
/// `reference` is the light's f32 frame origin (`TexelGrid::reference_point`).
#[allow(clippy::too_many_arguments)]
pub fn trace_ray(
    ray: &TexelRay,
    reference: DVec3,
    tracer: &Tracer<'_>,
    casters: &CasterTable,
    ground: Option<&Ground<'_>>,
    rules: RayRules,
    hits: &mut Vec<RayHit>,
    useful: &mut CasterSet,
) {
    trace_ray_each(ray, reference, tracer, casters, ground, rules, hits, |c| {
        useful.insert(c)
    });
}

/// [`trace_ray`] handing each useful caster to `on_useful` (a caster useful
/// in both passes is handed twice): the cross-check counts texels per caster.
#[allow(clippy::too_many_arguments)]
pub fn trace_ray_each(
    ray: &TexelRay,
    reference: DVec3,
    tracer: &Tracer<'_>,
    casters: &CasterTable,
    ground: Option<&Ground<'_>>,
    rules: RayRules,
    hits: &mut Vec<RayHit>,
    on_useful: impl FnMut(u32),
) {
    let traced = to_trace_ray(ray, reference);
    hits.clear();
    let mut limit = traced.t_max;
    tracer.for_each_hit(&traced, |hit| {
        if hit.t > limit {
            return limit;
        }
        let Some(kept) = filter_hit(&hit, ray, casters, ground, rules) else {
            return limit;
        };
        hits.push(kept);
        classify::sort_hits(hits);
        limit = limit.min(classify::cutoff(hits, rules.tie_epsilon, rules.passes));
        limit
    });
    hits.retain(|h| h.t <= limit);
    classify::classify_ray(hits, rules.tie_epsilon, rules.passes, on_useful);
}

/// A texel's ray in the tracer's light-relative f32 frame.
fn to_trace_ray(ray: &TexelRay, reference: DVec3) -> TraceRay {
    TraceRay {
        origin: (ray.origin - reference).as_vec3(),
        direction: ray.direction.as_vec3(),
        t_min: ray.t_min as f32,
        t_max: if ray.t_max.is_finite() {
            ray.t_max as f32
        } else {
            f32::INFINITY
        },
    }
}

/// The per-hit rules every consumer of a light's rays applies before
/// classification: face culling (double-sided groups exempt; mirrored
/// instances were re-wound when the geometry was built) and the below-ground
/// test for non-terrain hits. `None`: the hit does not count.
fn filter_hit(
    hit: &Hit,
    ray: &TexelRay,
    casters: &CasterTable,
    ground: Option<&Ground<'_>>,
    rules: RayRules,
) -> Option<RayHit> {
    let caster = casters.casters.get(hit.caster as usize)?;
    let culled = !caster.double_sided
        && match rules.face_culling {
            FaceCulling::Back => hit.back_facing,
            FaceCulling::Front => !hit.back_facing,
            FaceCulling::None => false,
        };
    if culled {
        return None;
    }
    if let Some(ground) = ground.filter(|_| !caster.is_terrain()) {
        let p = ray.origin + ray.direction * hit.t as f64;
        if ground
            .height(p.x, p.z)
            .is_some_and(|h| p.y < h - rules.height_bias)
        {
            return None;
        }
    }
    Some(RayHit {
        t: hit.t,
        caster: hit.caster,
        receiver_only: caster.receiver_only,
        alpha_tested: caster.alpha_tested,
    })
}

/// The front surface of texel `(face, x, y)` as the bake's All pass sees it:
/// the nearest hit that survives the same filter as the bake's rays (face
/// culling, double-sided, mirrored, below ground), whatever its caster —
/// receiver-only and alpha-tested groups included. Equal distances go to
/// the lowest caster id, the bake's canonical hit order. `None`: the ray
/// meets nothing that counts. `t` is metres from the ray's origin.
#[allow(clippy::too_many_arguments)]
pub fn front_hit(
    grid: &TexelGrid,
    tracer: &Tracer<'_>,
    casters: &CasterTable,
    ground: Option<&Ground<'_>>,
    rules: RayRules,
    face: usize,
    x: u32,
    y: u32,
) -> Option<RayHit> {
    let ray = grid.ray(face, x, y);
    let trace_ray = to_trace_ray(&ray, grid.reference_point());
    let mut best: Option<RayHit> = None;
    tracer.for_each_hit(&trace_ray, |hit| {
        let limit = best.map_or(trace_ray.t_max, |b| b.t);
        if hit.t > limit {
            return limit;
        }
        if let Some(kept) = filter_hit(&hit, &ray, casters, ground, rules) {
            if best.is_none_or(|b| (kept.t, kept.caster) < (b.t, b.caster)) {
                best = Some(kept);
            }
        }
        best.map_or(trace_ray.t_max, |b| b.t)
    });
    best
}
