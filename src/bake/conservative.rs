//! The conservative grid pass (`--conservative`): a caster is kept whenever
//! some placement of the shadow-map grid at this light's texel size could
//! make it useful, i.e. whenever SOME ray through SOME point of a texel's
//! square (its beam) makes it useful under docs/contract.md §4. Every placement of the
//! game's grid puts each of its sample rays inside one of our texels' beams,
//! so keeping what every beam could keep never loses a shadow at any offset.
//!
//! Per texel beam, per pass, for every caster triangle the beam meets (its
//! *fragment*: the triangle's projection clipped to the texel square), the
//! caster is kept unless one of these proofs holds for that fragment:
//! - **hidden**: nearer opaque casters cover the whole fragment: the union
//!   of the projections of triangles that are certainly hit, certainly
//!   counted and certainly more than ε nearer than the fragment's nearest
//!   point everywhere over it leaves nothing of it (`texel_beam::subtract`);
//! - **nothing behind**: no other triangle meeting the beam (grown by the
//!   filter radius) could be hit at or behind the fragment's nearest depth
//!   − 2ε (one ε for the front set's tie, one for "behind").
//!
//! Why that is conservative (each rule of docs/contract.md §4 taken on the safe side):
//! - *Beams and edges*: a fragment is any overlap of the grown square
//!   (1e-7 texel) with the triangle, so a ray through an edge or vertex
//!   shared by two triangles, which the tie rule gives to one of them,
//!   meets both fragments; covering, on the other side, ignores only
//!   slivers of at most `beam::SLIVER` texels² that clipping leaves along
//!   shared occluder edges (where every ray is given to one side).
//! - *Depths*: a directional ray's t is the depth along the light, affine
//!   over a triangle, so its extremes over a fragment are at the clipped
//!   polygon's vertices. A perspective ray's t is z·|D| (z the depth along
//!   the face axis, 1/z affine in image coordinates, |D| ≥ 1 the length of
//!   the unit-depth ray): comparisons use z (occluder max z < fragment min
//!   z − ε implies t_o < t_f − ε) and z·max|D| for "could be behind".
//! - *Ties within ε*: an occluder hides a fragment only when more than ε
//!   nearer everywhere (a tie keeps both in the front set).
//! - *Face culling*: for a directional light a triangle faces every ray of
//!   the light alike; for a perspective light a triangle may be hit when
//!   any corner ray of the texel sees its kept side, and counts as an
//!   occluder only when all four do (the facing sign is linear in the ray
//!   direction, so corners bound it).
//! - *near/far*: a fragment may be hit when its depth range meets
//!   [near, far] (by z and z·max|D|); an occluder counts only when wholly
//!   inside.
//! - *Alpha-tested*: the All pass counts everything; the Opaque pass drops
//!   alpha-tested groups (as candidates, occluders and behind surfaces), so
//!   an alpha-tested occluder never hides a caster there.
//! - *Receiver-only*: never a candidate, never an occluder (they are not in
//!   the shadow map), but a surface behind.
//! - *Below ground*: candidates and surfaces behind ignore the rule (a hit
//!   it might drop is kept); a non-terrain occluder counts only when its
//!   lowest point is at least the highest terrain sample of every cell
//!   under its box minus heightBias, with 5 cm to spare for the rounding
//!   of hit points (`Ground::at_most`), so no part of it can be dropped.
//!
//! Where it keeps more than a dense grid at every offset: a fragment is
//! compared with its nearest point (a steep caster partly hidden counts as
//! wholly at its nearest depth), and another triangle of the same caster
//! counts as behind when some of it lies more than ε beyond that point
//! (a lone tilted box over the void is kept). The sweep reports how many.

use super::config::BakeConfig;
use super::setup::{BakeWorld, LightSetup};
use super::texel_beam::{self as beam, Point, Rect};
use super::trace_light::{tile_rect, CasterSet, LightRays, RayCounter};
use crate::formats::bake_settings::FaceCulling;
use crate::light::{FacePolygon, TexelGrid};
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// How far (texels) a beam's square is grown before testing overlaps.
const GROW: f64 = 1e-7;

/// One caster triangle as a face of the light sees it.
pub(super) struct Fragment {
    pub(super) caster: u32,
    pub(super) polygon: FacePolygon,
    /// Depth as a function of image position: `w` (directional: t plus a
    /// constant) or `1/z` (perspective), affine.
    pub(super) depth: Affine,
    /// Light-relative geometric normal of the kept side (perspective
    /// facing per texel).
    pub(super) normal: DVec3,
    pub(super) receiver_only: bool,
    pub(super) alpha_tested: bool,
    /// The triangle (world points), for the below-ground rule.
    pub(super) vertices: [DVec3; 3],
    /// Never dropped by the below-ground rule: worked out when first asked
    /// ([`Light::surely_above`]), since it scans the terrain under it.
    pub(super) above_ground: std::cell::OnceCell<bool>,
}

/// `value(x, y) = a + bx·x + by·y`.
#[derive(Clone, Copy)]
pub(super) struct Affine {
    a: f64,
    bx: f64,
    by: f64,
}

impl Affine {
    pub(super) fn at(&self, (x, y): Point) -> f64 {
        self.a + self.bx * x + self.by * y
    }

    /// Through three points `(x, y, value)`; `None` when they are collinear.
    pub(super) fn through(p: [(f64, f64, f64); 3]) -> Option<Affine> {
        let (x1, y1) = (p[1].0 - p[0].0, p[1].1 - p[0].1);
        let (x2, y2) = (p[2].0 - p[0].0, p[2].1 - p[0].1);
        let det = x1 * y2 - x2 * y1;
        let scale = (x1.abs() + y1.abs()) * (x2.abs() + y2.abs());
        // NaN fails the comparison too.
        if det.abs().partial_cmp(&(1e-12 * scale)) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let (v1, v2) = (p[1].2 - p[0].2, p[2].2 - p[0].2);
        let bx = (v1 * y2 - v2 * y1) / det;
        let by = (x1 * v2 - x2 * v1) / det;
        Some(Affine {
            a: p[0].2 - bx * p[0].0 - by * p[0].1,
            bx,
            by,
        })
    }
}

/// The conservative pass over `tiles`: the casters some ray of some texel
/// beam could prove useful, beyond `known` (the centre rays' answer, which
/// it contains).
pub fn trace_tiles(
    world: &BakeWorld,
    setup: &LightSetup,
    rays: &LightRays<'_>,
    config: &BakeConfig,
    tiles: impl IntoParallelIterator<Item = u64>,
    known: &CasterSet,
    rays_done: &dyn RayCounter,
) -> CasterSet {
    Beams::new(world, setup, rays, config).trace_tiles(tiles, known, rays_done)
}

/// One light's conservative pass, its parts and blocks binned into tiles
/// once, for any number of tile sets (the bake cache's cells).
pub struct Beams<'w, 'a> {
    light: Light<'w, 'a>,
    sources: HashMap<u64, Vec<(usize, Source)>>,
}

impl<'w, 'a> Beams<'w, 'a> {
    pub fn new(
        world: &'w BakeWorld<'a>,
        setup: &'w LightSetup,
        rays: &'w LightRays<'w>,
        config: &BakeConfig,
    ) -> Self {
        let light = Light::new(world, setup, rays, config);
        let sources = light.sources_by_tile();
        Beams { light, sources }
    }

    /// [`trace_tiles`] over `tiles`.
    pub fn trace_tiles(
        &self,
        tiles: impl IntoParallelIterator<Item = u64>,
        known: &CasterSet,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let light = &self.light;
        let casters = light.world.casters.len();
        tiles
            .into_par_iter()
            .fold(
                || CasterSet::new(casters),
                |mut useful, tile| {
                    light.tile(
                        tile,
                        self.sources.get(&tile).map_or(&[][..], Vec::as_slice),
                        known,
                        &mut useful,
                    );
                    let (_, x0, y0, x1, y1) = tile_rect(light.grid, tile);
                    rays_done.add(((x1 - x0) * (y1 - y0)) as u64);
                    useful
                },
            )
            .reduce(|| CasterSet::new(casters), |a, b| a.union(&b))
    }
}

/// Something that puts triangles into the light: a placed part's groups or
/// a terrain block, by caster ids.
#[derive(Clone, Copy)]
struct Source {
    first_caster: u32,
    casters: u32,
}

pub(super) struct Light<'w, 'a> {
    world: &'w BakeWorld<'a>,
    setup: &'w LightSetup,
    grid: &'w TexelGrid,
    rays: &'w LightRays<'w>,
    epsilon: f64,
    face_culling: FaceCulling,
    height_bias: f64,
    two_passes: bool,
    radius: f64,
}

impl<'w, 'a> Light<'w, 'a> {
    pub(super) fn new(
        world: &'w BakeWorld<'a>,
        setup: &'w LightSetup,
        rays: &'w LightRays<'w>,
        config: &BakeConfig,
    ) -> Self {
        Light {
            world,
            setup,
            grid: &setup.grid,
            rays,
            epsilon: config.tie_epsilon,
            face_culling: config.face_culling,
            height_bias: config.height_bias,
            two_passes: setup.passes == crate::classify::Passes::AllAndOpaque,
            radius: config.filter_radius as f64,
        }
    }

    pub(super) fn grid(&self) -> &'w TexelGrid {
        self.grid
    }

    pub(super) fn setup(&self) -> &'w LightSetup {
        self.setup
    }

    pub(super) fn world(&self) -> &'w BakeWorld<'a> {
        self.world
    }

    pub(super) fn two_passes(&self) -> bool {
        self.two_passes
    }

    /// Every part and block in reach, binned into the tiles its world box
    /// covers (grown by the filter radius) on every face.
    fn sources_by_tile(&self) -> HashMap<u64, Vec<(usize, Source)>> {
        let world = self.world;
        let scene = world.scene;
        let mut boxes: Vec<(Source, (DVec3, DVec3))> = Vec::new();
        for &p in &self.setup.reach.parts {
            let part = &world.parts[p as usize];
            let Some((min, max)) = world.bottom.models[part.model].bounds() else {
                continue;
            };
            let placed = &scene.instances[part.instance].world;
            let groups = scene.models[part.model].groups.len() as u32;
            boxes.push((
                Source {
                    first_caster: part.first_caster,
                    casters: groups,
                },
                crate::trace::transform_box(placed, min.as_dvec3(), max.as_dvec3()),
            ));
        }
        for &b in &self.setup.reach.blocks {
            boxes.push((
                Source {
                    first_caster: world.casters.of_block[b as usize],
                    casters: 1,
                },
                scene.terrain[b as usize].bounds(),
            ));
        }
        let grid = self.grid;
        let tile = super::trace_light::TILE as f64;
        let tiles_x = grid.width().div_ceil(super::trace_light::TILE) as u64;
        let tiles_y = grid.height().div_ceil(super::trace_light::TILE) as u64;
        let mut bins: HashMap<u64, Vec<(usize, Source)>> = HashMap::new();
        for (source, (min, max)) in boxes {
            for face in 0..grid.faces() {
                let Some((x0, y0, x1, y1)) = grid.footprint(face, min, max) else {
                    continue;
                };
                let grow = self.radius + 1.0;
                let span = |lo: f64, hi: f64, n: u64| {
                    let first = ((lo - grow) / tile).floor().max(0.0) as u64;
                    let last = (((hi + grow) / tile).ceil().max(0.0) as u64).min(n);
                    first..last
                };
                for ty in span(y0, y1, tiles_y) {
                    for tx in span(x0, x1, tiles_x) {
                        let t = (face as u64 * tiles_y + ty) * tiles_x + tx;
                        bins.entry(t).or_default().push((face, source));
                    }
                }
            }
        }
        bins
    }

    /// The fragments of `sources` on `face` that meet `area` (texel units).
    fn fragments(&self, face: usize, sources: &[(usize, Source)], area: Rect) -> Vec<Fragment> {
        let reference = self.grid.reference_point();
        let mut out = Vec::new();
        for &(f, source) in sources {
            if f != face {
                continue;
            }
            for caster in source.first_caster..source.first_caster + source.casters {
                for t in self.setup.caster_triangles(self.world, caster) {
                    let vertices = t.vertices.map(|v| reference + v.as_dvec3());
                    if let Some(fragment) = self.fragment(face, caster, vertices, Some(area)) {
                        out.push(fragment);
                    }
                }
            }
        }
        out
    }

    /// Triangle `v` (world points) of `caster` on `face` if it meets
    /// `area` (`None` for any area) and some ray of the face could hit its
    /// kept side: a directional light's rays all see the same side, so a
    /// triangle face culling drops is left out here.
    pub(super) fn fragment(
        &self,
        face: usize,
        caster: u32,
        v: [DVec3; 3],
        area: Option<Rect>,
    ) -> Option<Fragment> {
        let info = &self.rays.casters.casters[caster as usize];
        let reference = self.grid.reference_point();
        let rel = v.map(|p| p - reference);
        let normal = (rel[1] - rel[0]).cross(rel[2] - rel[0]);
        let culled = !info.double_sided
            && self
                .grid
                .direction()
                .is_some_and(|d| !self.kept_side(normal.dot(d)));
        if culled {
            return None;
        }
        let projected = self.grid.project_triangle_with_depth(face, v)?;
        let polygon = projected.flat();
        if area.is_some_and(|area| !beam::overlaps_rect(&polygon, area)) {
            return None;
        }
        let perspective = self.grid.direction().is_none();
        // The largest triangle among the polygon's vertices fixes the
        // depth plane best (a clipped polygon has up to four).
        let n = projected.len();
        let mut best: Option<(f64, [usize; 3])> = None;
        for i in 0..n {
            for j in i + 1..n {
                for k in j + 1..n {
                    let area = beam::signed_area2(&[polygon[i], polygon[j], polygon[k]]).abs();
                    if best.is_none_or(|(a, _)| area > a) {
                        best = Some((area, [i, j, k]));
                    }
                }
            }
        }
        let (_, corners) = best?;
        let value = |i: usize| {
            let (x, y, d) = projected[i];
            (x, y, if perspective { 1.0 / d } else { d })
        };
        let depth = Affine::through(corners.map(value))?;
        Some(Fragment {
            caster,
            polygon,
            depth,
            normal: if info.double_sided {
                DVec3::ZERO
            } else {
                normal
            },
            receiver_only: info.receiver_only,
            alpha_tested: info.alpha_tested,
            vertices: v,
            above_ground: std::cell::OnceCell::new(),
        })
    }

    /// The fragments of one tile, then its texels.
    fn tile(
        &self,
        tile: u64,
        sources: &[(usize, Source)],
        known: &CasterSet,
        useful: &mut CasterSet,
    ) {
        let (face, x0, y0, x1, y1) = tile_rect(self.grid, tile);
        let area = Rect {
            x0: x0 as f64,
            y0: y0 as f64,
            x1: x1 as f64,
            y1: y1 as f64,
        }
        .grown(self.radius + GROW);
        let fragments = self.fragments(face, sources, area);
        if fragments.is_empty() {
            return;
        }
        // Per texel of the tile, the fragments whose box meets its square
        // grown by the filter radius.
        let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
        let mut near: Vec<Vec<u32>> = vec![Vec::new(); w * h];
        for (index, fragment) in fragments.iter().enumerate() {
            let (lo, hi) = beam::bounds(fragment.polygon.iter().copied());
            let reach = self.radius + GROW;
            let xs = ((lo.0 - reach).floor().max(x0 as f64) as u32)
                ..((hi.0 + reach).ceil().min(x1 as f64) as u32).max(x0);
            let ys = ((lo.1 - reach).floor().max(y0 as f64) as u32)
                ..((hi.1 + reach).ceil().min(y1 as f64) as u32).max(y0);
            for y in ys {
                for x in xs.clone() {
                    near[(y - y0) as usize * w + (x - x0) as usize].push(index as u32);
                }
            }
        }
        for y in y0..y1 {
            for x in x0..x1 {
                let list = &near[(y - y0) as usize * w + (x - x0) as usize];
                if list.iter().any(|&i| {
                    let c = fragments[i as usize].caster;
                    !fragments[i as usize].receiver_only
                        && !known.contains(c)
                        && !useful.contains(c)
                }) {
                    self.texel(face, x, y, &fragments, list, known, useful);
                }
            }
        }
    }

    /// One texel's beam: marks every caster it could prove useful.
    #[allow(clippy::too_many_arguments)]
    fn texel(
        &self,
        face: usize,
        x: u32,
        y: u32,
        fragments: &[Fragment],
        list: &[u32],
        known: &CasterSet,
        useful: &mut CasterSet,
    ) {
        let square = Rect {
            x0: x as f64,
            y0: y as f64,
            x1: x as f64 + 1.0,
            y1: y as f64 + 1.0,
        };
        let beam = Beam::new(self, face, square);
        let wide = square.grown(self.radius + GROW);
        let inner = square.grown(GROW);
        // Each fragment's part of the beam, with its depth range (None: it
        // misses the beam or cannot be hit).
        let parts: Vec<Option<Part>> = list
            .iter()
            .map(|&i| beam.part(&fragments[i as usize], wide, inner))
            .collect();
        for pass in 0..if self.two_passes { 2 } else { 1 } {
            let counts = |f: &Fragment| pass == 0 || !f.alpha_tested;
            for (k, &i) in list.iter().enumerate() {
                let f = &fragments[i as usize];
                let Some(part) = &parts[k] else { continue };
                if f.receiver_only
                    || !counts(f)
                    || known.contains(f.caster)
                    || useful.contains(f.caster)
                {
                    continue;
                }
                let Some((region, near_depth)) = &part.inner else {
                    continue;
                };
                // Something that could be hit at or behind the front set.
                let behind = list.iter().zip(&parts).enumerate().any(|(m, (&j, other))| {
                    let g = &fragments[j as usize];
                    let Some(other) = other else { return false };
                    if m == k || !counts(g) {
                        return false;
                    }
                    let reach = other.far_wide;
                    if g.caster == f.caster {
                        reach > near_depth + self.epsilon
                    } else {
                        reach >= near_depth - 2.0 * self.epsilon
                    }
                });
                if !behind {
                    continue;
                }
                // Nearer casters that certainly cover the whole region.
                let mut rest = vec![region.clone()];
                for (m, (&j, other)) in list.iter().zip(&parts).enumerate() {
                    if rest.is_empty() {
                        break;
                    }
                    let o = &fragments[j as usize];
                    let Some(other) = other else { continue };
                    if m == k || o.receiver_only || !counts(o) || !other.sure {
                        continue;
                    }
                    // Boxes apart: the clip below would be empty.
                    let bounds = Rect::around(region.iter().copied());
                    if !Rect::around(o.polygon.iter().copied()).meets(bounds) {
                        continue;
                    }
                    let over = beam::clip_to_rect(&o.polygon, bounds);
                    let Some(far) = beam.far_depth(o, &over) else {
                        continue;
                    };
                    if far < near_depth - self.epsilon && self.surely_above(o) {
                        rest = beam::subtract(rest, &o.polygon);
                    }
                }
                if !rest.is_empty() {
                    useful.insert(f.caster);
                }
            }
        }
    }
    /// Whether the kept side of a triangle faces a ray whose direction
    /// gives `normal·direction = dot`.
    fn kept_side(&self, dot: f64) -> bool {
        match self.face_culling {
            FaceCulling::Back => dot <= 0.0,
            FaceCulling::Front => dot >= 0.0,
            FaceCulling::None => true,
        }
    }

    /// Whether no hit on fragment `f` can be dropped by the below-ground
    /// test (terrain is never dropped).
    pub(super) fn surely_above(&self, f: &Fragment) -> bool {
        *f.above_ground.get_or_init(|| {
            self.rays.casters.casters[f.caster as usize].is_terrain()
                || self.surely_above_ground(f.vertices)
        })
    }

    /// Whether no hit on any triangle of caster `caster` with vertices
    /// among `vertices` (world points) can be dropped by the below-ground
    /// test, asked once for their box: then [`Self::surely_above`] holds
    /// for each (a triangle's box lies in theirs and its lowest point is
    /// no lower, and the ground test only grows more sure as the box
    /// shrinks and the level rises). `false` leaves each to be asked.
    pub(super) fn all_surely_above(
        &self,
        caster: u32,
        vertices: impl IntoIterator<Item = DVec3>,
    ) -> bool {
        self.rays.casters.casters[caster as usize].is_terrain()
            || self.surely_above_ground(vertices)
    }

    /// No point of the triangle (or triangles) with `vertices` can be
    /// dropped by the below-ground test: its lowest point is at least the
    /// highest terrain under its box minus heightBias, with
    /// [`ABOVE_GROUND_MARGIN`] to spare.
    fn surely_above_ground(&self, vertices: impl IntoIterator<Item = DVec3>) -> bool {
        let Some(ground) = &self.world.ground else {
            return true;
        };
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for p in vertices {
            (lo, hi) = (lo.min(p), hi.max(p));
        }
        let lowest = lo.y;
        if !(lo.is_finite() && hi.is_finite()) {
            return false;
        }
        let level = lowest + self.height_bias - ABOVE_GROUND_MARGIN;
        ground.at_most((lo.x, lo.z), (hi.x, hi.z), level, MOST_GROUND_CELLS)
    }
}

/// How far (metres) above "just not below ground" a triangle must lie to
/// count as surely above it: a hit point is found from an `f32` distance,
/// so it may lie a hair below the exact triangle.
const ABOVE_GROUND_MARGIN: f64 = 0.05;

/// Terrain cells a triangle's box may span before the below-ground test
/// counts it as possibly dropped (its box is scanned cell by cell).
const MOST_GROUND_CELLS: usize = 4096;

/// One fragment within one beam.
struct Part {
    /// Its polygon within the texel's square and its nearest depth there
    /// (`None`: it does not meet the square itself, only the margin).
    inner: Option<(Vec<Point>, f64)>,
    /// The farthest the fragment could be hit within the square grown by
    /// the filter radius (distance-like: t, or z·max|D|).
    far_wide: f64,
    /// Certainly hit where it lies (facing and near/far hold for every ray
    /// of the beam): it may hide what lies behind.
    sure: bool,
}

/// A texel's beam: its corner rays and the depth-to-distance factors.
struct Beam<'l, 'w, 'a> {
    light: &'l Light<'w, 'a>,
    /// Unit-depth directions through the square's corners.
    corners: [DVec3; 4],
    /// Largest |D| over the square (1 for a directional light).
    stretch: f64,
    perspective: bool,
}

impl<'l, 'w, 'a> Beam<'l, 'w, 'a> {
    fn new(light: &'l Light<'w, 'a>, face: usize, square: Rect) -> Self {
        let corners = square
            .corners()
            .map(|(cx, cy)| light.grid.unit_depth_direction(face, cx, cy));
        let perspective = light.grid.direction().is_none();
        let stretch = if perspective {
            corners.iter().map(|d| d.length()).fold(1.0, f64::max)
        } else {
            1.0
        };
        Beam {
            light,
            corners,
            stretch,
            perspective,
        }
    }

    /// Depth (w or z) of fragment `f` at image point `p`.
    fn depth_at(&self, f: &Fragment, p: Point) -> f64 {
        let value = f.depth.at(p);
        if self.perspective {
            1.0 / value
        } else {
            value
        }
    }

    /// The nearest and farthest depth of `f` over `polygon` (a part of
    /// its projection): at the vertices, where an affine (or, for 1/z,
    /// fractional-linear) function on a convex polygon has its extremes.
    fn range(&self, f: &Fragment, polygon: &[Point]) -> Option<(f64, f64)> {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for &p in polygon {
            let d = self.depth_at(f, p);
            if !d.is_finite() {
                return None;
            }
            lo = lo.min(d);
            hi = hi.max(d);
        }
        // Rounding of the plane fit: a relative hair on the safe side.
        let slack = 1e-9 * (1.0 + lo.abs().max(hi.abs()));
        (lo <= hi).then_some((lo - slack, hi + slack))
    }

    fn far_depth(&self, f: &Fragment, polygon: &[Point]) -> Option<f64> {
        if polygon.len() < 3 {
            return None;
        }
        self.range(f, polygon).map(|(_, hi)| hi)
    }

    /// `f` within this beam: `None` when no ray of it can hit `f`.
    fn part(&self, f: &Fragment, wide: Rect, inner: Rect) -> Option<Part> {
        let facing: Vec<bool> = self
            .corners
            .iter()
            .map(|d| f.normal == DVec3::ZERO || self.light.kept_side(f.normal.dot(*d)))
            .collect();
        let maybe_faced = !self.perspective || facing.iter().any(|&k| k);
        let surely_faced = facing.iter().all(|&k| k);
        if !maybe_faced {
            return None;
        }
        let wide_poly = beam::clip_to_rect(&f.polygon, wide);
        if wide_poly.is_empty() {
            return None;
        }
        let (wide_lo, wide_hi) = self.range(f, &wide_poly)?;
        let near_far = self.light.grid.near_far();
        let reachable = |lo: f64, hi: f64| {
            near_far.is_none_or(|(near, far)| lo <= far && hi * self.stretch >= near)
        };
        if !reachable(wide_lo, wide_hi) {
            return None;
        }
        let inner_poly = beam::clip_to_rect(&f.polygon, inner);
        let inner_part = if inner_poly.is_empty() {
            None
        } else {
            self.range(f, &inner_poly)
                .filter(|&(lo, hi)| reachable(lo, hi))
                .map(|(lo, _)| (inner_poly.clone(), lo))
        };
        let sure = surely_faced
            && match (near_far, self.range(f, &inner_poly)) {
                (None, _) => true,
                (Some((near, far)), Some((lo, hi))) => lo >= near && hi * self.stretch <= far,
                (Some(_), None) => false,
            };
        Some(Part {
            inner: inner_part,
            far_wide: wide_hi * self.stretch,
            sure,
        })
    }
}
