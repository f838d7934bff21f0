//! `shadowcull xcheck`: the ray-cast bake against the rasterized method,
//! pair by pair (caster × light), with a cause for every disagreement found
//! by re-testing that caster.
//!
//! Causes (the only ones SPEC §4 allows):
//! - the ray cast finds a caster useful at no more than [`EDGE_TEXELS`]
//!   texel centres and the raster at none: a triangle edge or vertex on a
//!   texel centre (the ray test's tie rule and the rasterizer's top-left
//!   rule give such a centre to different triangles) or an ε tie the depth
//!   test does not see;
//! - the raster finds it useful at no more than [`EDGE_TEXELS`] samples, or
//!   4×4 supersampled rays over the light's texels find it useful too: an
//!   edge or depth quantization near a texel centre (the two methods
//!   sample the same surface a hair apart).
//!
//! Anything else stays unexplained.

use super::RasterResult;
use crate::bake::casters::{CasterTable, Owner};
use crate::bake::ground::Ground;
use crate::bake::trace_light::{LightRays, RayRules, Tracer};
use crate::bake::{geometry, BakeConfig};
use crate::classify::Passes;
use crate::light::TexelGrid;
use crate::scene::Scene;
use crate::trace::Bvh;
use rayon::prelude::*;

/// Texels (or samples) at or below which a one-sided answer is an edge.
pub const EDGE_TEXELS: u64 = 3;

#[derive(Debug, Clone, serde::Serialize)]
pub struct Disagreement {
    pub chunk: String,
    pub kind: &'static str,
    /// The instance's index in its chunk (terrain: none).
    pub index: Option<usize>,
    pub group: Option<usize>,
    pub light: usize,
    pub ray_cast: bool,
    pub raster: bool,
    pub ray_texels: u64,
    pub raster_texels: u64,
    /// `None`: unexplained.
    pub cause: Option<String>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct LightTexels {
    pub light: usize,
    /// Σ over casters of texels where the caster is useful (All pass).
    pub ray_cast: u64,
    pub raster: u64,
    pub ray_seconds: f64,
    pub raster_seconds: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct XcheckReport {
    pub pairs: u64,
    pub agreeing: u64,
    pub unexplained: u64,
    pub disagreements: Vec<Disagreement>,
    pub lights: Vec<LightTexels>,
    pub renderer: String,
    pub notes: Vec<String>,
}

/// The ray-cast side: per light, per caster, the texels (centre rays) at
/// which it is useful, in the All pass (`all`) and in any pass (`any`).
pub struct RayCounts {
    pub all: Vec<Vec<u64>>,
    pub any: Vec<Vec<u64>>,
    pub seconds: Vec<f64>,
}

/// Traces every texel centre of every light like the bake does, counting.
pub fn ray_counts(
    scene: &Scene,
    config: &BakeConfig,
    casters: &CasterTable,
    samples: u32,
) -> RayCounts {
    let ground = Ground::new(scene);
    let bounds = geometry::world_bounds(scene);
    let mut out = RayCounts {
        all: Vec::new(),
        any: Vec::new(),
        seconds: Vec::new(),
    };
    for light in &config.lights {
        let started = std::time::Instant::now();
        let empty = vec![0u64; casters.len()];
        let grid = bounds.and_then(|b| TexelGrid::new(light, b).ok());
        let Some(grid) = grid else {
            out.all.push(empty.clone());
            out.any.push(empty);
            out.seconds.push(0.0);
            continue;
        };
        let geo = geometry::light_geometry(scene, casters, &grid);
        let bvh = Bvh::build(&geo.triangles);
        let passes = if geo.reaches_alpha_tested {
            Passes::AllAndOpaque
        } else {
            Passes::AllOnly
        };
        let rays_of_light = LightRays {
            grid: &grid,
            tracer: Tracer::Bvh(&bvh),
            casters,
            ground: ground.as_ref(),
            rules: RayRules::new(config, passes),
        };
        // The All pass alone, for the per-light texel counts.
        let all_pass = LightRays {
            rules: RayRules::new(config, Passes::AllOnly),
            ..rays_of_light
        };
        let rows = grid.faces() as u64 * grid.height() as u64;
        let (all, any) = (0..rows)
            .into_par_iter()
            .fold(
                || {
                    (
                        vec![0u64; casters.len()],
                        vec![0u64; casters.len()],
                        Vec::new(),
                        Vec::new(),
                    )
                },
                |(mut all, mut any, mut hits, mut seen), row| {
                    let face = (row / grid.height() as u64) as usize;
                    let y = (row % grid.height() as u64) as u32;
                    for x in 0..grid.width() {
                        seen.clear();
                        for ray in grid.texel_rays(face, x, y, samples) {
                            rays_of_light.trace(&ray, &mut hits, |c| seen.push(c));
                            if samples <= 1 {
                                all_pass.trace(&ray, &mut hits, |c| {
                                    if let Some(n) = all.get_mut(c as usize) {
                                        *n += 1;
                                    }
                                });
                            }
                        }
                        seen.sort_unstable();
                        seen.dedup();
                        for &c in &seen {
                            if let Some(n) = any.get_mut(c as usize) {
                                *n += 1;
                            }
                        }
                    }
                    (all, any, hits, seen)
                },
            )
            .map(|(a, b, _, _)| (a, b))
            .reduce(
                || (vec![0u64; casters.len()], vec![0u64; casters.len()]),
                |(mut a, mut b), (c, d)| {
                    a.iter_mut().zip(c).for_each(|(x, y)| *x += y);
                    b.iter_mut().zip(d).for_each(|(x, y)| *x += y);
                    (a, b)
                },
            );
        out.all.push(all);
        out.any.push(any);
        out.seconds.push(started.elapsed().as_secs_f64());
    }
    out
}

/// Compares the two methods; `raster` must come from the same scene and
/// config.
pub fn compare(scene: &Scene, config: &BakeConfig, raster: &RasterResult) -> XcheckReport {
    let casters = &raster.casters;
    let rays = ray_counts(scene, config, casters, 1);
    let mut report = XcheckReport {
        pairs: 0,
        agreeing: 0,
        unexplained: 0,
        disagreements: Vec::new(),
        lights: Vec::new(),
        renderer: raster.renderer.clone(),
        notes: raster.ground_note.iter().cloned().collect(),
    };
    let mut supersampled: Vec<Option<Vec<u64>>> = vec![None; config.lights.len()];
    #[allow(clippy::needless_range_loop)]
    for light in 0..config.lights.len() {
        report.lights.push(LightTexels {
            light,
            ray_cast: rays.all[light].iter().sum(),
            raster: raster.texels.get(light).map_or(0, |t| t.iter().sum()),
            ray_seconds: rays.seconds[light],
            raster_seconds: raster.seconds.get(light).copied().unwrap_or(0.0),
        });
        for (id, caster) in casters.casters.iter().enumerate() {
            if caster.receiver_only {
                continue;
            }
            report.pairs += 1;
            let ray_n = rays.any[light][id];
            let ray = ray_n > 0;
            let ras = raster.masks[id] & (1 << light) != 0;
            if ray == ras {
                report.agreeing += 1;
                continue;
            }
            let ras_n = raster.texels.get(light).map_or(0, |t| t[id]);
            let cause = if ray && ray_n <= EDGE_TEXELS {
                Some(format!(
                    "edge or tie: the ray cast finds it useful at only {ray_n} texel centre(s), the raster at none"
                ))
            } else if ras && ras_n <= EDGE_TEXELS {
                Some(format!(
                    "edge or depth quantization: the raster passes {ras_n} sample(s), the texel-centre rays none"
                ))
            } else if ras {
                let fine = supersampled[light].get_or_insert_with(|| {
                    let one = BakeConfig {
                        lights: vec![config.lights[light].clone()],
                        ..config.clone()
                    };
                    ray_counts(scene, &one, casters, 4).any.remove(0)
                });
                (fine[id] > 0).then(|| {
                    format!(
                        "sub-texel: 4×4 rays per texel find it useful at {} texel(s); the centre rays miss it",
                        fine[id]
                    )
                })
            } else {
                None
            };
            if cause.is_none() {
                report.unexplained += 1;
            }
            let (chunk, kind, index, group) = describe(scene, casters, id);
            report.disagreements.push(Disagreement {
                chunk,
                kind,
                index,
                group,
                light,
                ray_cast: ray,
                raster: ras,
                ray_texels: ray_n,
                raster_texels: ras_n,
                cause,
            });
        }
    }
    report
}

fn describe(
    scene: &Scene,
    casters: &CasterTable,
    id: usize,
) -> (String, &'static str, Option<usize>, Option<usize>) {
    match casters.casters[id].owner {
        Owner::Group {
            instance, group, ..
        } => {
            let inst = &scene.instances[instance];
            (
                scene.chunks[inst.chunk].name.clone(),
                "model",
                Some(inst.index),
                Some(group),
            )
        }
        Owner::Terrain { block } => {
            let chunk = scene
                .chunks
                .iter()
                .find(|c| c.terrain == Some(block))
                .map_or_else(|| format!("terrain block {block}"), |c| c.name.clone());
            (chunk, "terrain", None, None)
        }
    }
}
