//! Refinement (`--refine`): after the texel grid, every caster not yet
//! useful for a light gets extra rays aimed at points of its own surface.
//! The grid samples the light's view at texel centres, so a caster smaller
//! than a texel, or a thin one between centres, can be missed; rays through
//! its own triangles look where it actually is. Any ray that proves a
//! caster useful keeps it (the rays are fixed before tracing and the results
//! OR-ed, so the outcome does not depend on order or threads).

use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays};
use crate::rng::{mix, Rng};
use crate::trace::TraceTriangle;
use glam::DVec3;
use rayon::prelude::*;

/// Barycentric coordinates stay this far from the edges, so a sample lies
/// inside its triangle and its ray crosses that triangle, not a neighbour.
const EDGE_MARGIN: f64 = 0.02;

/// Extra rays for every caster in the light's reach that is neither useful
/// yet nor receiver-only: `samples` points per caster, area-weighted over its
/// triangles, deterministic per (light, caster). Returns the casters the
/// rays prove useful and how many rays were traced.
pub fn refine(
    world: &BakeWorld,
    setup: &LightSetup,
    rays_of_light: &LightRays<'_>,
    already_useful: &CasterSet,
    samples: u32,
) -> (CasterSet, u64) {
    let casters = &world.casters;
    let grid = rays_of_light.grid;
    let light_index = setup.index;
    let mut candidates: Vec<u32> = Vec::new();
    for &p in &setup.reach.parts {
        let part = &world.parts[p as usize];
        let groups = world.scene.models[part.model].groups.len() as u32;
        candidates.extend(part.first_caster..part.first_caster + groups);
    }
    candidates.extend(
        setup
            .reach
            .blocks
            .iter()
            .map(|&b| casters.of_block[b as usize]),
    );
    candidates.retain(|&caster| {
        !already_useful.contains(caster) && !casters.casters[caster as usize].receiver_only
    });
    let reference = grid.reference_point();
    candidates
        .par_iter()
        .fold(
            || (CasterSet::new(casters.len()), Vec::new(), 0u64),
            |(mut useful, mut hits, mut rays), &caster| {
                let run = setup.caster_triangles(world, caster);
                let areas: Vec<f64> = run.iter().map(area).collect();
                let total: f64 = areas.iter().sum();
                if run.is_empty() || total.is_nan() || total <= 0.0 {
                    return (useful, hits, rays);
                }
                let mut rng = Rng::new(mix(((light_index as u64) << 32) | caster as u64));
                for _ in 0..samples {
                    let pick = rng.unit() * total;
                    let mut chosen = run.len() - 1;
                    let mut sum = 0.0;
                    for (i, a) in areas.iter().enumerate() {
                        sum += a;
                        if pick < sum {
                            chosen = i;
                            break;
                        }
                    }
                    let p = reference + sample_point(&run[chosen], &mut rng);
                    if let Some(ray) = grid.ray_toward(p) {
                        rays += 1;
                        rays_of_light.trace(&ray, &mut hits, |c| useful.insert(c));
                    }
                }
                (useful, hits, rays)
            },
        )
        .map(|(useful, _, rays)| (useful, rays))
        .reduce(
            || (CasterSet::new(casters.len()), 0),
            |(a, ra), (b, rb)| (a.union(&b), ra + rb),
        )
}

fn area(triangle: &TraceTriangle) -> f64 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    0.5 * (b - a).cross(c - a).length()
}

/// A uniform point of the triangle (light-relative), away from its edges.
fn sample_point(triangle: &TraceTriangle, rng: &mut Rng) -> DVec3 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    let squeeze = |r: f64| EDGE_MARGIN + (1.0 - 2.0 * EDGE_MARGIN) * r;
    let (r1, r2) = (squeeze(rng.unit()).sqrt(), squeeze(rng.unit()));
    a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2)
}
