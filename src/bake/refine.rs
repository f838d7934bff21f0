//! Refinement (`--refine`): after the texel grid, every caster not yet
//! useful for a light gets extra rays where it actually is. The grid
//! samples the light's view at texel centres, so a caster smaller than a
//! texel, or one that shows only in a sliver between centres, can be
//! missed.
//!
//! Two kinds of rays, both fixed before tracing and OR-ed (the outcome does
//! not depend on order or threads):
//! - area-weighted points of the caster's own surface (`refine_samples`
//!   per caster, deterministic per (light, caster));
//! - its light-space footprint on the lattice of a grid `refine_density`
//!   times denser per side (the rays of that denser grid). The footprint is
//!   cut into cells; cells its hittable triangles miss are dropped whole and
//!   the caster's rays stop at the first that proves it useful. For a model
//!   under a directional light every lattice point on the footprint is
//!   traced, so at density 8 refinement finds every model caster the ×8
//!   grid finds among those it refines (the footprint is bounded by the
//!   model's size over the texel size). Terrain blocks (as large as a chunk)
//!   and every caster of a spot or point light (a wall a metre from a point
//!   light fills most of a face: a million lattice points) are not bounded
//!   so: there a cell that the outline of the caster's union of hittable
//!   triangles does not cross is probed at its corners and split only where
//!   the probes disagree on whether the caster is front-most (in either
//!   pass); outline cells still go down to single lattice points. Probing is
//!   a sample: on `bench`, probing models too lost five sun casters the ×8
//!   grid keeps (walls and a pillar useful only inside probed cells); the
//!   whole lattice for terrain cost 3.6× the plain bake on `village`.

use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays, PacketState};
use super::BakeConfig;
use crate::classify::{self, RayHit};
use crate::formats::bake_settings::FaceCulling;
use crate::light::TexelRay;
use crate::progress::{Counter, Phase, Progress};
use crate::rng::{mix, Rng};
use crate::trace::texel_beam::{self as beam, ConvexRegion, Point, Rect};
use crate::trace::TraceTriangle;
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// Barycentric coordinates stay this far from the edges, so a sample lies
/// inside its triangle and its ray crosses that triangle, not a neighbour.
const EDGE_MARGIN: f64 = 0.02;

/// Extra rays for every caster in the light's reach that is neither useful
/// yet nor receiver-only: `config.refine_samples` surface points and the
/// footprint lattice at `config.refine_density` (see the module docs).
/// Returns the casters the rays prove useful and how many rays were traced.
/// Each caster refined is counted in [`Phase::Refining`] of `progress`.
pub fn refine(
    world: &BakeWorld,
    setup: &LightSetup,
    rays_of_light: &LightRays<'_>,
    already_useful: &CasterSet,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> (CasterSet, u64) {
    let casters = &world.casters;
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
    let light = Some(config.lights[setup.index].name.as_str());
    let counter = Counter::begin(progress, Phase::Refining, light, candidates.len() as u64);
    let refined = candidates
        .par_iter()
        .fold(
            || Scratch::new(casters.len()),
            |mut scratch, &caster| {
                let run = setup.caster_triangles(world, caster);
                let mut sampler = Sampler {
                    rays: rays_of_light,
                    caster,
                    useful: &mut scratch.useful,
                    hits: &mut scratch.hits,
                    packet: &mut scratch.packet,
                    traced: 0,
                };
                surface_points(&mut sampler, &run, setup.index, config.refine_samples);
                if config.refine_density > 0 && !sampler.useful.contains(caster) {
                    footprint_lattice(&mut sampler, &run, config, config.refine_density);
                }
                scratch.rays += sampler.traced;
                counter.add(1);
                scratch
            },
        )
        .map(|scratch| (scratch.useful, scratch.rays))
        .reduce(
            || (CasterSet::new(casters.len()), 0),
            |(a, ra), (b, rb)| (a.union(&b), ra + rb),
        );
    counter.finish();
    refined
}

/// One refining thread's answer so far and its reused buffers.
struct Scratch {
    useful: CasterSet,
    hits: Vec<RayHit>,
    packet: PacketState,
    rays: u64,
}

impl Scratch {
    fn new(casters: usize) -> Scratch {
        Scratch {
            useful: CasterSet::new(casters),
            hits: Vec::new(),
            packet: PacketState::default(),
            rays: 0,
        }
    }
}

/// Rays traced together ([`Sampler::trace_batch`]): a packet's worth.
const BATCH: usize = 64;

/// Surface points traced before the others (see [`surface_points`]).
const FIRST_POINTS: usize = 8;

/// Traces refinement rays for one caster, recording what they prove.
struct Sampler<'r, 'a> {
    rays: &'r LightRays<'a>,
    caster: u32,
    useful: &'r mut CasterSet,
    hits: &'r mut Vec<RayHit>,
    packet: &'r mut PacketState,
    traced: u64,
}

impl Sampler<'_, '_> {
    /// Traces `rays` (at most a packet's worth, near each other: one
    /// caster's surface points or a patch of its footprint) together, each
    /// with the answer it gets alone; returns whether any proves the caster
    /// useful.
    fn trace_batch(&mut self, rays: &[TexelRay]) -> bool {
        self.traced += rays.len() as u64;
        self.packet.rays.clear();
        self.packet.rays.extend_from_slice(rays);
        let mut proven = false;
        let (caster, useful) = (self.caster, &mut *self.useful);
        self.rays.trace_packet(self.packet, |c| {
            proven |= c == caster;
            useful.insert(c);
        });
        proven
    }

    /// Traces `ray`; returns whether it proves the caster useful and, per
    /// pass, whether the caster is in the ray's front set (bit 0: All,
    /// bit 1: Opaque).
    fn trace(&mut self, ray: &TexelRay) -> (bool, u8) {
        self.traced += 1;
        let mut proven = false;
        let (caster, useful) = (self.caster, &mut *self.useful);
        self.rays.trace(ray, self.hits, |c| {
            proven |= c == caster;
            useful.insert(c);
        });
        let rules = self.rays.rules;
        let mut front = 0u8;
        for pass in 0..classify::pass_count(rules.passes) {
            classify::pass_depths(self.hits, rules.passes, pass, rules.tie_epsilon, |c| {
                if c == caster {
                    front |= 1 << pass;
                }
            });
        }
        (proven, front)
    }
}

/// The area-weighted surface points of `run` (the caster's triangles).
fn surface_points(
    sampler: &mut Sampler<'_, '_>,
    run: &[TraceTriangle],
    light: usize,
    samples: u32,
) {
    let areas: Vec<f64> = run.iter().map(area).collect();
    let total: f64 = areas.iter().sum();
    if samples == 0 || run.is_empty() || total.is_nan() || total <= 0.0 {
        return;
    }
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let mut rng = Rng::new(mix(((light as u64) << 32) | sampler.caster as u64));
    let mut points = Vec::with_capacity(samples as usize);
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
        points.extend(grid.ray_toward(p));
    }
    // Most casters the points prove are proven by one of the first few:
    // those go alone, and the rest only when they did not.
    let (first, rest) = points.split_at(points.len().min(FIRST_POINTS));
    if sampler.trace_batch(first) {
        return;
    }
    for batch in rest.chunks(BATCH) {
        if sampler.trace_batch(batch) {
            return;
        }
    }
}

/// Texels per side of the footprint's first cells.
const TOP_CELL: u32 = 4;
/// How near (texel units) a lattice point or cell must be to a footprint
/// polygon or edge to count as touching it: rays exactly on an edge may
/// hit under the tie rule.
const TOUCH: f64 = 1e-6;

/// One face's view of a caster: its hittable triangles projected, and the
/// edges of their union (`None`: a directional light, or some edge reaches
/// behind the face's plane: every cell is treated as crossed).
struct Footprint {
    face: usize,
    polygons: Vec<Vec<Point>>,
    /// `polygons` grown by [`TOUCH`], for the lattice points' tests.
    regions: Vec<Option<ConvexRegion>>,
    outline: Option<Vec<(Point, Point)>>,
    density: u32,
}

/// The footprint lattice of the caster on every face of the light.
fn footprint_lattice(
    sampler: &mut Sampler<'_, '_>,
    run: &[TraceTriangle],
    config: &BakeConfig,
    density: u32,
) {
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let caster = &sampler.rays.casters.casters[sampler.caster as usize];
    let kept: Vec<[DVec3; 3]> = run
        .iter()
        .filter(|t| hittable(t, grid.direction(), caster.double_sided, config))
        .map(|t| t.vertices.map(|v| reference + v.as_dvec3()))
        .collect();
    // A model under a directional light traces the whole lattice (no
    // outline, every cell crossed); terrain blocks and perspective lights,
    // whose footprints can be as large as the world, probe cells inside the
    // outline.
    let outline = match grid.direction() {
        Some(_) if !caster.is_terrain() => None,
        direction => Some(outline_edges(run, direction, caster.double_sided, config)),
    };
    for face in 0..grid.faces() {
        let polygons: Vec<Vec<Point>> = kept
            .iter()
            .filter_map(|&t| grid.project_triangle(face, t))
            .collect();
        let outline = outline.as_ref().and_then(|edges| {
            edges
                .iter()
                .map(|&(a, b)| {
                    Some((
                        grid.project_point(face, reference + a)?,
                        grid.project_point(face, reference + b)?,
                    ))
                })
                .collect::<Option<Vec<_>>>()
        });
        let footprint = Footprint {
            face,
            regions: polygons
                .iter()
                .map(|p| ConvexRegion::new(p, TOUCH))
                .collect(),
            polygons,
            outline,
            density,
        };
        if footprint.sample(sampler) {
            return;
        }
    }
}

/// Whether rays of the light can hit triangle `t` under the face-culling
/// rule: a directional light's rays share one direction, so a culled face
/// is culled for all of them; a perspective light's may see either side.
fn hittable(
    t: &TraceTriangle,
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> bool {
    let Some(direction) = direction else {
        return true;
    };
    let [a, b, c] = t.vertices.map(|v| v.as_dvec3());
    let back = (b - a).cross(c - a).dot(direction) > 0.0;
    double_sided
        || match config.face_culling {
            FaceCulling::Back => !back,
            FaceCulling::Front => back,
            FaceCulling::None => true,
        }
}

/// The edges (light-relative) of the union of the caster's hittable
/// triangles: edges that exactly one hittable triangle uses.
fn outline_edges(
    run: &[TraceTriangle],
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> Vec<(DVec3, DVec3)> {
    let key = |v: glam::Vec3| v.to_array().map(f32::to_bits);
    // Edge (its vertices' bits, ordered) → uses and its two ends.
    type Uses = HashMap<([u32; 3], [u32; 3]), (u32, DVec3, DVec3)>;
    let mut uses = Uses::new();
    for t in run
        .iter()
        .filter(|t| hittable(t, direction, double_sided, config))
    {
        for i in 0..3 {
            let (a, b) = (t.vertices[i], t.vertices[(i + 1) % 3]);
            let (ka, kb) = (key(a), key(b));
            let k = if ka <= kb { (ka, kb) } else { (kb, ka) };
            uses.entry(k).or_insert((0, a.as_dvec3(), b.as_dvec3())).0 += 1;
        }
    }
    let mut edges: Vec<(DVec3, DVec3)> = uses
        .into_values()
        .filter(|(n, _, _)| *n == 1)
        .map(|(_, a, b)| (a, b))
        .collect();
    // Hash order is not deterministic; the answer does not depend on it,
    // but a fixed order keeps the work the same run to run.
    edges.sort_by(|x, y| {
        (x.0.to_array(), x.1.to_array())
            .partial_cmp(&(y.0.to_array(), y.1.to_array()))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    edges
}

/// The polygons and outline edges (indices) near one cell.
struct Near<'f> {
    polygons: &'f [u32],
    edges: &'f [u32],
}

impl Footprint {
    /// Whether lattice point `p` lies on polygon `index` (within [`TOUCH`]).
    #[inline]
    fn touches(&self, index: u32, p: Point) -> bool {
        self.regions[index as usize]
            .as_ref()
            .is_some_and(|region| region.contains(p))
    }

    /// Samples the footprint cell by cell; true once the caster is proven
    /// useful.
    fn sample(&self, sampler: &mut Sampler<'_, '_>) -> bool {
        let grid = sampler.rays.grid;
        let d = self.density as i64;
        let (width, height) = (grid.width() as i64 * d, grid.height() as i64 * d);
        let top = TOP_CELL as i64 * d;
        let (cells_x, cells_y) = ((width + top - 1) / top, (height + top - 1) / top);
        // Top cells a box (texel units) may touch, clipped to the face.
        let span = |lo: f64, hi: f64, cells: i64| {
            let first = ((lo * d as f64 - 1.0) / top as f64)
                .floor()
                .clamp(0.0, cells as f64) as i64;
            let last = ((hi * d as f64 + 1.0) / top as f64)
                .ceil()
                .clamp(0.0, cells as f64) as i64;
            first..last
        };
        let mut bins: std::collections::BTreeMap<(i64, i64), (Vec<u32>, Vec<u32>)> =
            std::collections::BTreeMap::new();
        for (index, polygon) in self.polygons.iter().enumerate() {
            let (lo, hi) = bounds(polygon.iter().copied());
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    bins.entry((cy, cx)).or_default().0.push(index as u32);
                }
            }
        }
        for (index, &(a, b)) in self.outline.iter().flatten().enumerate() {
            let (lo, hi) = bounds([a, b].into_iter());
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    if let Some(bin) = bins.get_mut(&(cy, cx)) {
                        bin.1.push(index as u32);
                    }
                }
            }
        }
        for ((cy, cx), (polygons, edges)) in &bins {
            let (i0, j0) = (cx * top, cy * top);
            let cell = (i0, j0, top.min(width - i0), top.min(height - j0));
            let near = Near { polygons, edges };
            if cell.2 > 0 && cell.3 > 0 && self.cell(sampler, &near, cell) {
                return true;
            }
        }
        false
    }

    /// Every lattice point of a small cell on one of `polygons`, traced as
    /// one batch (whole-lattice mode: a model under a directional light,
    /// whose lattice rays are parallel and a fraction of a texel apart);
    /// true if any proves the caster useful.
    fn whole_cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        polygons: &[u32],
        (i0, j0, ni, nj): (i64, i64, i64, i64),
    ) -> bool {
        let d = self.density as f64;
        let grid = sampler.rays.grid;
        let mut batch = Vec::with_capacity(BATCH);
        for j in j0..j0 + nj {
            for i in i0..i0 + ni {
                let p = ((i as f64 + 0.5) / d, (j as f64 + 0.5) / d);
                if polygons.iter().any(|&k| self.touches(k, p)) {
                    batch.push(grid.ray_through(self.face, p.0, p.1));
                }
            }
        }
        sampler.trace_batch(&batch)
    }

    /// Lattice points `i0..i0+ni × j0..j0+nj`; true once proven useful.
    fn cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        near: &Near<'_>,
        (i0, j0, ni, nj): (i64, i64, i64, i64),
    ) -> bool {
        let d = self.density as f64;
        let rect = Rect {
            x0: i0 as f64 / d,
            y0: j0 as f64 / d,
            x1: (i0 + ni) as f64 / d,
            y1: (j0 + nj) as f64 / d,
        };
        let point = |i: i64, j: i64| ((i as f64 + 0.5) / d, (j as f64 + 0.5) / d);
        let grid = sampler.rays.grid;
        if ni == 1 && nj == 1 {
            let p = point(i0, j0);
            let inside = near.polygons.iter().any(|&i| self.touches(i, p));
            return inside && sampler.trace(&grid.ray_through(self.face, p.0, p.1)).0;
        }
        // What meets this cell, handed down so smaller cells test less.
        let grown = rect.grown(TOUCH);
        let polygons: Vec<u32> = near
            .polygons
            .iter()
            .copied()
            .filter(|&i| beam::overlaps_rect(&self.polygons[i as usize], grown))
            .collect();
        if polygons.is_empty() {
            return false;
        }
        if self.outline.is_none() && ni * nj <= BATCH as i64 {
            return self.whole_cell(sampler, &polygons, (i0, j0, ni, nj));
        }
        let edges: Vec<u32> = match &self.outline {
            None => Vec::new(),
            Some(all) => near
                .edges
                .iter()
                .copied()
                .filter(|&e| {
                    let (a, b) = all[e as usize];
                    beam::segment_meets_rect(a, b, grown)
                })
                .collect(),
        };
        let crossed = self.outline.is_none() || !edges.is_empty();
        let near = &Near {
            polygons: &polygons,
            edges: &edges,
        };
        if !crossed {
            let mut fronts = Vec::with_capacity(4);
            let last = (i0 + ni - 1, j0 + nj - 1);
            for (i, j) in [(i0, j0), (last.0, j0), (i0, last.1), last] {
                let p = point(i, j);
                let (proven, front) = sampler.trace(&grid.ray_through(self.face, p.0, p.1));
                if proven {
                    return true;
                }
                fronts.push(front);
            }
            if fronts.iter().all(|&f| f == fronts[0]) {
                return false;
            }
        }
        let (hi, hj) = ((ni + 1) / 2, (nj + 1) / 2);
        for (a, b, na, nb) in [
            (i0, j0, hi, hj),
            (i0 + hi, j0, ni - hi, hj),
            (i0, j0 + hj, hi, nj - hj),
            (i0 + hi, j0 + hj, ni - hi, nj - hj),
        ] {
            if na > 0 && nb > 0 && self.cell(sampler, near, (a, b, na, nb)) {
                return true;
            }
        }
        false
    }
}

/// The smallest and largest coordinates of `points`.
fn bounds(points: impl Iterator<Item = Point>) -> (Point, Point) {
    points.fold(
        (
            (f64::INFINITY, f64::INFINITY),
            (f64::NEG_INFINITY, f64::NEG_INFINITY),
        ),
        |(lo, hi), (x, y)| ((lo.0.min(x), lo.1.min(y)), (hi.0.max(x), hi.1.max(y))),
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
