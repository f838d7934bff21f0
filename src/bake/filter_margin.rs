//! The filter margin (`--filter-radius K`): with percentage-closer
//! filtering the game compares a receiver against the shadow map's depths
//! at every texel of a (2K+1)² neighbourhood, so a caster front-most at
//! texel A also shadows surfaces behind its depth at texels up to K away.
//! Such a caster is useful even when nothing lies behind it at A itself.
//!
//! Each tile is traced with a K-texel halo (the halo's rays are traced
//! again by the neighbouring tile: a tile's answer depends on no other
//! tile, so tiles still OR together, in any order and over any shards).
//! Per sample and pass we keep the shadow map's depth (the nearest caster
//! hit) and the farthest surface of the ray; a sample's front set is useful
//! when the K = 0 rule holds at the sample itself, or when some other sample
//! of its neighbourhood has a surface farther than its depth + ε. With k×k
//! supersampling the neighbourhood is K·k samples (K texels) wide.
//!
//! Rules at the edges: the neighbourhood is clipped to the face (a
//! directional grid already covers the whole world; a spot light's map ends
//! at its cone; a point light's faces are filtered each on its own, as a
//! cube map sampled per face does). A surface of the caster itself counts
//! as a receiver at a neighbouring texel, as it does in the game
//! (self-shadowing under PCF is what slope-scaled bias fights; the bake
//! keeps the caster rather than guess the game's bias).

use super::trace_light::{tile_rect, CasterSet, LightRays, RayCounter};
use crate::classify::{self, PassDepths, RayHit};
use rayon::prelude::*;

/// One sample of a tile with its halo: per pass its depths and where its
/// front set lies in the tile's shared list.
#[derive(Clone, Copy)]
struct Sample {
    depths: [PassDepths; 2],
    fronts: [(u32, u32); 2],
}

/// The grid pass with the filter margin: tiles `tiles` of `rays`' grid at
/// `samples`² rays per texel, neighbourhoods `radius` texels wide.
pub fn trace_tiles(
    rays: &LightRays<'_>,
    tiles: impl IntoParallelIterator<Item = u64>,
    samples: u32,
    radius: u32,
    rays_done: &dyn RayCounter,
) -> CasterSet {
    let casters = rays.casters.len();
    let samples = samples.max(1);
    tiles
        .into_par_iter()
        .fold(
            || CasterSet::new(casters),
            |mut useful, tile| {
                let traced = trace_tile(rays, tile, samples, radius, &mut useful);
                rays_done.add(traced);
                useful
            },
        )
        .reduce(|| CasterSet::new(casters), |a, b| a.union(&b))
}

/// One tile: traces its samples and halo, then marks what the margin
/// proves useful. Returns the tile's own rays (the halo's are the
/// neighbours' own: progress counts each ray of the grid once).
fn trace_tile(
    rays: &LightRays<'_>,
    tile: u64,
    samples: u32,
    radius: u32,
    useful: &mut CasterSet,
) -> u64 {
    let grid = rays.grid;
    let (face, x0, y0, x1, y1) = tile_rect(grid, tile);
    let s = samples as i64;
    let halo = radius as i64 * s;
    // The tile's samples, in sample units of the face.
    let (sx0, sy0, sx1, sy1) = (x0 as i64 * s, y0 as i64 * s, x1 as i64 * s, y1 as i64 * s);
    let (face_w, face_h) = (grid.width() as i64 * s, grid.height() as i64 * s);
    let (hx0, hy0) = ((sx0 - halo).max(0), (sy0 - halo).max(0));
    let (hx1, hy1) = ((sx1 + halo).min(face_w), (sy1 + halo).min(face_h));
    let width = (hx1 - hx0) as usize;
    let epsilon = rays.rules.tie_epsilon;
    let passes = classify::pass_count(rays.rules.passes);
    let mut hits: Vec<RayHit> = Vec::new();
    let mut fronts: Vec<u32> = Vec::new();
    let mut region: Vec<Sample> = Vec::with_capacity(width * (hy1 - hy0) as usize);
    for sy in hy0..hy1 {
        for sx in hx0..hx1 {
            let ray = grid.ray_through(
                face,
                (sx as f64 + 0.5) / samples as f64,
                (sy as f64 + 0.5) / samples as f64,
            );
            rays.all_hits(&ray, &mut hits);
            let own = (sx0..sx1).contains(&sx) && (sy0..sy1).contains(&sy);
            if own {
                classify::classify_ray(&hits, epsilon, rays.rules.passes, |c| useful.insert(c));
            }
            let mut sample = Sample {
                depths: [PassDepths::NONE; 2],
                fronts: [(0, 0); 2],
            };
            for pass in 0..passes {
                let start = fronts.len() as u32;
                sample.depths[pass] =
                    classify::pass_depths(&hits, rays.rules.passes, pass, epsilon, |c| {
                        if own {
                            fronts.push(c)
                        }
                    });
                sample.fronts[pass] = (start, fronts.len() as u32);
            }
            region.push(sample);
        }
    }
    let at = |sx: i64, sy: i64| &region[(sy - hy0) as usize * width + (sx - hx0) as usize];
    for sy in sy0..sy1 {
        for sx in sx0..sx1 {
            let sample = at(sx, sy);
            for pass in 0..passes {
                let depth = sample.depths[pass].front;
                let (start, end) = sample.fronts[pass];
                if start == end || !depth.is_finite() {
                    continue;
                }
                let behind = (sy - halo).max(hy0)..(sy + halo + 1).min(hy1);
                let shadowed = behind.clone().any(|ny| {
                    ((sx - halo).max(hx0)..(sx + halo + 1).min(hx1)).any(|nx| {
                        (nx, ny) != (sx, sy) && at(nx, ny).depths[pass].far > depth + epsilon
                    })
                });
                if shadowed {
                    for &c in &fronts[start as usize..end as usize] {
                        useful.insert(c);
                    }
                }
            }
        }
    }
    ((sx1 - sx0) * (sy1 - sy0)) as u64
}
