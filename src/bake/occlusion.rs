//! Refinement's shortcut for hidden casters: a lattice ray need not be
//! traced when geometry already known to lie on it surely keeps the
//! refined caster out of its front set, for then that ray cannot prove the
//! caster useful. Most of refinement's rays go to casters no ray ever
//! proves (things under trees), and stop at surfaces in front of the caster
//! before they reach it.
//!
//! The known geometry is the casters that refinement's probe rays met
//! (`refine`): their triangles, projected on the light's face, are tested
//! at each lattice point with the refined caster's own. A point is
//! *hidden* when, in every pass, some occluder triangle
//! - contains it with [`INSIDE_MARGIN`] to spare from every edge (so the
//!   ray surely crosses that triangle, whatever the tie rule does on its
//!   edges and however the `f32` test rounds),
//! - faces the light's rays (face culling) and is never dropped by the
//!   below-ground test (`conservative::Light::surely_above`),
//! - belongs to a caster counted in the pass (not receiver-only; not
//!   alpha-tested in the Opaque pass),
//! - lies there within the rays' span and more than ε (plus [`ROUNDING`])
//!   nearer than every triangle of the refined caster that could be hit
//!   through the point (the caller's `target_near`: refinement takes every
//!   triangle of the caster within [`INSIDE_MARGIN`] of the point):
//!
//! then the pass's nearest caster hit lies more than ε before any hit on
//! the refined caster, which is therefore not in the front set. Directional
//! lights only: refinement traces the whole lattice only for models under
//! them, and their rays share one direction, so a triangle faces every ray
//! alike and a depth along the light orders hits on one ray as t does.

use super::config::BakeConfig;
use super::conservative::{Affine, Light};
use super::setup::{BakeWorld, LightSetup};
use super::texel_beam::{ConvexRegion, Point, Rect};
use super::trace_light::LightRays;
use crate::trace::TraceTriangle;
use std::ops::RangeInclusive;

/// How far inside (metres on the light's image plane) an occluder triangle
/// must contain a lattice point to count: far more than the `f32` ray test
/// (light-relative coordinates, about 1 mm off at 10 km) strays from the
/// exact edges.
const INSIDE_MARGIN: f64 = 0.01;

/// Beyond ε, how much nearer an occluder must be (metres, plus a part of
/// the depth): a ray's t comes from `f32` light-relative coordinates.
const ROUNDING: f64 = 1e-3;
const ROUNDING_RELATIVE: f64 = 1e-5;

/// One caster's hittable triangles as a directional light's face sees
/// them, each with the region a lattice point must lie in to count.
pub struct CasterImage {
    triangles: Vec<ImageTriangle>,
    /// The caster's (`CasterInfo`): a receiver-only caster hides nothing,
    /// an alpha-tested one only in the All pass.
    receiver_only: bool,
    alpha_tested: bool,
}

/// Only what the test reads (a caster's image may hold hundreds).
struct ImageTriangle {
    /// Depth as a function of image position (`Fragment::depth`).
    depth: Affine,
    region: ConvexRegion,
}

/// The occlusion test of one directional light.
pub struct Occlusion<'w, 'a> {
    light: Light<'w, 'a>,
    /// [`INSIDE_MARGIN`] in texels.
    inside_margin: f64,
    epsilon: f64,
    /// The depths (as the images': t plus the rays' common constant) a
    /// ray of the grid spans; an occluder outside them is not hit.
    depths: (f64, f64),
}

impl<'w, 'a> Occlusion<'w, 'a> {
    /// `None` for a spot or point light.
    pub fn new(
        world: &'w BakeWorld<'a>,
        setup: &'w LightSetup,
        rays: &'w LightRays<'w>,
        config: &BakeConfig,
    ) -> Option<Self> {
        let direction = setup.grid.direction()?;
        let texel = setup.grid.texel_size()?;
        // Every ray of a directional grid starts on one plane across the
        // light and spans the same t.
        let ray = setup.grid.ray(0, 0, 0);
        let start = ray.origin.dot(direction);
        Some(Occlusion {
            light: Light::new(world, setup, rays, config),
            inside_margin: INSIDE_MARGIN / texel,
            epsilon: config.tie_epsilon,
            depths: (start + ray.t_min, start + ray.t_max),
        })
    }

    /// [`INSIDE_MARGIN`] in texels: how far from a triangle a ray may
    /// still hit it, for the refined caster's depth at a point (every
    /// triangle whose box grown by this holds the point counts).
    pub fn margin(&self) -> f64 {
        self.inside_margin
    }

    /// Caster `caster`'s triangles on `face` that may hide others: those
    /// every ray sees the kept side of and the below-ground test never
    /// drops, each with the region (its polygon shrunk by
    /// [`INSIDE_MARGIN`]) where rays surely cross it.
    pub fn image(&self, face: usize, caster: u32) -> CasterImage {
        let light = &self.light;
        let reference = light.grid().reference_point();
        let run = light.setup().caster_triangles(light.world(), caster);
        let world_vertices = |t: &TraceTriangle| t.vertices.map(|v| reference + v.as_dvec3());
        // Asked once for the whole caster (a tree's canopy stands clear of
        // the ground); else triangle by triangle.
        let above = light.all_surely_above(caster, run.iter().flat_map(world_vertices));
        let triangles = run
            .iter()
            .filter_map(|t| {
                let fragment = light.fragment(face, caster, world_vertices(t), None)?;
                if !above && !light.surely_above(&fragment) {
                    return None;
                }
                let region = ConvexRegion::new(&fragment.polygon, -self.inside_margin)?;
                Some(ImageTriangle {
                    depth: fragment.depth,
                    region,
                })
            })
            .collect();
        let info = &light.world().casters.casters[caster as usize];
        CasterImage {
            triangles,
            receiver_only: info.receiver_only,
            alpha_tested: info.alpha_tested,
        }
    }

    /// For each point of `points` (texel units on the images' face), with
    /// the refined caster's nearest depth there (`target_near`: the
    /// least of its triangles' planes, as the images' depths, over those
    /// that may be hit through the point; infinite where none): whether
    /// `occluders` hide it (see the module docs). An alpha-tested caster
    /// (`target_alpha`) is in no Opaque pass, so only the All pass counts.
    pub fn hidden(
        &self,
        points: &[Point],
        target_near: &[f64],
        target_alpha: bool,
        occluders: &[&CasterImage],
    ) -> Vec<bool> {
        // Per point, the depth an occluder must lie nearer than, and the
        // passes (bit 0: All, bit 1: Opaque) where none found so far does:
        // a point is hidden once none is left. (The nearest such occluder
        // per pass need not be found: any one hides it.)
        let (mut open, threshold): (Vec<u8>, Vec<f64>) = target_near
            .iter()
            .map(|&near| self.test_of(near, target_alpha))
            .unzip();
        let mut active: Vec<usize> = (0..points.len()).filter(|&k| open[k] != 0).collect();
        let (first, last) = self.depths;
        for image in occluders.iter().filter(|image| !image.receiver_only) {
            if active.is_empty() {
                break;
            }
            // The passes an occluder here hides the point in.
            let left = if image.alpha_tested { !1 } else { 0 };
            covering(points, &active, image, |k, depth| {
                if hides(depth, first, last, threshold[k]) {
                    open[k] &= left;
                }
            });
            active.retain(|&k| open[k] != 0);
        }
        open.into_iter().map(|passes| passes == 0).collect()
    }

    /// [`Self::hidden`] of every point of `block`, the refined
    /// caster's nearest depth `near` at each (row by row): the same answer
    /// per point, found triangle by triangle over only the points of each
    /// row its region may hold ([`ConvexRegion::row_span`]) instead of
    /// point by point over every triangle, so a box of thousands of
    /// points costs about what the occluders' triangles cover.
    pub fn hidden_block(
        &self,
        block: LatticeBlock,
        near: f64,
        target_alpha: bool,
        occluders: &[&CasterImage],
    ) -> Vec<bool> {
        let (all_passes, threshold) = self.test_of(near, target_alpha);
        let mut state = BlockState {
            block,
            open: vec![all_passes; block.len()],
            open_in_row: vec![if all_passes == 0 { 0 } else { block.ni }; block.nj.max(0) as usize],
            depths: self.depths,
            threshold,
        };
        let area = Rect::around([
            block.point(block.i0, block.j0),
            block.point(block.i0 + block.ni - 1, block.j0 + block.nj - 1),
        ]);
        for image in occluders.iter().filter(|image| !image.receiver_only) {
            // The passes an occluder here hides a point in.
            let left = if image.alpha_tested { !1 } else { 0 };
            for t in image
                .triangles
                .iter()
                .filter(|t| t.region.bounds().meets(area))
            {
                state.cover(t, left);
            }
        }
        state.open.into_iter().map(|passes| passes == 0).collect()
    }

    /// For a point where the refined caster's nearest depth is `near`: the
    /// passes an occluder must hide it in (none where the caster is not
    /// hittable at all, `near` infinite), and the depth it must lie nearer
    /// than.
    fn test_of(&self, near: f64, target_alpha: bool) -> (u8, f64) {
        let passes = if self.light.two_passes() && !target_alpha {
            2
        } else {
            1
        };
        let open = if near == f64::INFINITY {
            0
        } else {
            (1u8 << passes) - 1
        };
        let threshold = near - (self.epsilon + ROUNDING + ROUNDING_RELATIVE * near.abs());
        (open, threshold)
    }
}

/// The points `i0..i0 + ni × j0..j0 + nj` of the lattice `density` per
/// texel side (point `(i, j)` at `((i + 0.5) / density, (j + 0.5) /
/// density)`, texel units), row by row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LatticeBlock {
    pub i0: i64,
    pub j0: i64,
    pub ni: i64,
    pub nj: i64,
    pub density: u32,
}

impl LatticeBlock {
    pub fn point(&self, i: i64, j: i64) -> Point {
        let d = f64::from(self.density);
        ((i as f64 + 0.5) / d, (j as f64 + 0.5) / d)
    }

    pub fn len(&self) -> usize {
        (self.ni.max(0) * self.nj.max(0)) as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Point `(i, j)`'s place in row-by-row order, if it is in the block.
    pub fn index(&self, i: i64, j: i64) -> Option<usize> {
        let (di, dj) = (i - self.i0, j - self.j0);
        let inside = (0..self.ni).contains(&di) && (0..self.nj).contains(&dj);
        inside.then_some((dj * self.ni + di) as usize)
    }

    /// The block's columns whose points' x (texel units) may lie in
    /// `lo..=hi` (rounded outward).
    pub fn columns(&self, lo: f64, hi: f64) -> RangeInclusive<i64> {
        self.span(lo, hi, self.i0, self.ni)
    }

    /// The block's rows whose points' y may lie in `lo..=hi`.
    pub fn rows(&self, lo: f64, hi: f64) -> RangeInclusive<i64> {
        self.span(lo, hi, self.j0, self.nj)
    }

    /// Indices `first..first + n` along one axis, those whose coordinate
    /// may lie in `lo..=hi`.
    fn span(&self, lo: f64, hi: f64, first: i64, n: i64) -> RangeInclusive<i64> {
        let d = f64::from(self.density);
        let from = ((lo * d - 0.5).floor() as i64).max(first);
        let to = ((hi * d - 0.5).ceil() as i64).min(first + n - 1);
        from..=to
    }
}

/// [`Occlusion::hidden_block`]'s answer so far: per point the passes
/// where no occluder found so far hides it, and per row how many points
/// are left open (a row with none is skipped: occluders' triangles
/// overlap, a canopy's many times).
struct BlockState {
    block: LatticeBlock,
    open: Vec<u8>,
    open_in_row: Vec<i64>,
    /// The depths the rays span, and the depth an occluder must lie
    /// nearer than.
    depths: (f64, f64),
    threshold: f64,
}

impl BlockState {
    /// Occluder triangle `t` over the block: the points it surely covers
    /// nearer than the threshold are left open only in the passes `left`.
    fn cover(&mut self, t: &ImageTriangle, left: u8) {
        let (block, (first, last)) = (self.block, self.depths);
        let b = t.region.bounds();
        let columns = block.columns(b.x0, b.x1);
        // A narrow triangle's rows are walked whole.
        let wide = columns.end() - columns.start() >= WIDE;
        for j in block.rows(b.y0, b.y1) {
            let row = (j - block.j0) as usize;
            if self.open_in_row[row] == 0 {
                continue;
            }
            let columns = if wide {
                let (lo, hi) = t.region.row_span(block.point(0, j).1, 0.0);
                block.columns(lo.max(b.x0), hi.min(b.x1))
            } else {
                columns.clone()
            };
            for i in columns {
                let at = row * block.ni as usize + (i - block.i0) as usize;
                let p = block.point(i, j);
                if self.open[at] == 0 || !t.region.contains(p) {
                    continue;
                }
                let depth = t.depth.at(p);
                if depth.is_finite() && hides(depth, first, last, self.threshold) {
                    self.open[at] &= left;
                    if self.open[at] == 0 {
                        self.open_in_row[row] -= 1;
                    }
                }
            }
        }
    }
}

/// Lattice points across a triangle's box from which
/// [`Occlusion::hidden_block`] walks only each row's span.
const WIDE: i64 = 8;

/// Whether an occluder at `depth` lies within the rays' span `first..=last`
/// (with [`ROUNDING`] to spare) and nearer than `threshold`.
fn hides(depth: f64, first: f64, last: f64, threshold: f64) -> bool {
    let margin = ROUNDING + ROUNDING_RELATIVE * depth.abs();
    depth >= first + margin && depth <= last - margin && depth < threshold
}

/// Calls `found(k, depth)` for every point `k` among `active`
/// (indices into `points`) that lies in a triangle's region, with the
/// triangle's depth there.
fn covering(
    points: &[Point],
    active: &[usize],
    image: &CasterImage,
    mut found: impl FnMut(usize, f64),
) {
    if active.is_empty() {
        return;
    }
    let all = Rect::around(active.iter().map(|&k| points[k]));
    for t in &image.triangles {
        if !t.region.bounds().meets(all) {
            continue;
        }
        for &k in active {
            let p = points[k];
            if !t.region.contains(p) {
                continue;
            }
            let depth = t.depth.at(p);
            if depth.is_finite() {
                found(k, depth);
            }
        }
    }
}
