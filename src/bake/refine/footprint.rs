//! A caster's footprint on the lattice: its hittable triangles projected
//! on each face of the light, walked top cell by top cell. A model under a
//! directional light traces every lattice point on it (whole-lattice mode:
//! its footprint is bounded by its size over the texel size); terrain
//! blocks and perspective lights, whose footprints can be as large as the
//! world, probe the cells inside the outline at their corners and trace
//! only the small cells the outline crosses (outline mode).

use super::lattice::{LatticeCell, TopCellPoints, TOUCH};
use super::outline::{hittable, outline_edges};
use super::sampler::{Sampler, BATCH, FEW_POINTS};
use crate::bake::config::BakeConfig;
use crate::bake::conservative::Affine;
use crate::bake::texel_beam::{self as beam, bounds, ConvexRegion, Point, Rect};
use crate::bake::trace_light::PacketState;
use crate::light::{FacePolygon, ProjectedPolygon, TexelGrid, TexelRay};
use crate::trace::TraceTriangle;
use glam::DVec3;
use rayon::prelude::*;

/// Texels per side of the footprint's first cells.
const TOP_CELL: u32 = 4;

/// Outline cells traced at once per thread ([`Footprint::outline_cells`]):
/// enough to share out, few to trace in vain past the cell that proves
/// the caster.
const OUTLINE_WAVE: usize = 4;

/// One face's view of a caster: its hittable triangles projected, and the
/// edges of their union (`None`: a directional light, or some edge reaches
/// behind the face's plane: every cell is treated as crossed).
struct Footprint {
    face: usize,
    /// Whole-lattice mode under occlusion tests: `Occlusion::margin`, and
    /// per polygon its box grown by it and its depth plane (`None`: it has
    /// none, the caster counts as nearest everywhere near it).
    margin: f64,
    planes: Vec<(Rect, Option<Affine>)>,
    polygons: Vec<FacePolygon>,
    /// `polygons` grown by [`TOUCH`], for the lattice points' tests.
    regions: Vec<Option<ConvexRegion>>,
    outline: Option<Vec<(Point, Point)>>,
    density: u32,
}

/// The footprint lattice of the caster on every face of the light.
pub(super) fn footprint_lattice(
    sampler: &mut Sampler<'_, '_>,
    run: &[TraceTriangle],
    config: &BakeConfig,
) {
    let density = config.refine_density;
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let caster = &sampler.rays.casters.casters[sampler.caster as usize];
    let is_hittable =
        |t: &TraceTriangle| hittable(t, grid.direction(), caster.double_sided, config);
    // A model under a directional light traces the whole lattice (no
    // outline, every cell crossed); terrain blocks and perspective lights,
    // whose footprints can be as large as the world, probe cells inside the
    // outline.
    let outline = match grid.direction() {
        Some(_) if !caster.is_terrain() => None,
        direction => Some(outline_edges(run, direction, caster.double_sided, config)),
    };
    let margin = sampler.occlusion_margin();
    for face in 0..grid.faces() {
        // Every triangle, once: the box of all for the occlusion test, the
        // hittable ones for the lattice.
        let projected: Vec<Option<ProjectedPolygon>> = run
            .iter()
            .map(|t| {
                grid.project_triangle_with_depth(face, t.vertices.map(|v| reference + v.as_dvec3()))
            })
            .collect();
        if face == 0 && sampler.mask_lattice(run, &projected, density) {
            return;
        }
        // A polygon the mask hides whole is left out before its setup.
        let mask = sampler.mask();
        let reach = margin.unwrap_or(0.0).max(1.0 / f64::from(density));
        let masked = |p: &ProjectedPolygon| mask.is_some_and(|m| m.holds_polygon(p, reach));
        let projected: Vec<&ProjectedPolygon> = projected
            .iter()
            .zip(run)
            .filter_map(|(p, t)| p.as_ref().filter(|p| is_hittable(t) && !masked(p)))
            .collect();
        if !projected
            .iter()
            .any(|p| near_face(grid, p, margin, density))
        {
            // No top cell of this face is near it: nothing to trace here.
            continue;
        }
        let planes = match margin.filter(|_| outline.is_none()) {
            None => Vec::new(),
            Some(margin) => projected.iter().map(|p| depth_plane(p, margin)).collect(),
        };
        let polygons: Vec<FacePolygon> = projected.iter().map(|p| p.flat()).collect();
        let footprint = Footprint {
            face,
            margin: margin.unwrap_or(0.0),
            planes,
            regions: polygons
                .iter()
                .map(|p| ConvexRegion::new(p, TOUCH))
                .collect(),
            polygons,
            outline: outline
                .as_ref()
                .and_then(|edges| project_outline(grid, face, reference, edges)),
            density,
        };
        if footprint.sample(sampler) {
            return;
        }
    }
}

/// The outline `edges` (relative to `reference`) projected on `face`;
/// `None` when an end does not project (it lies behind the face's plane).
fn project_outline(
    grid: &TexelGrid,
    face: usize,
    reference: DVec3,
    edges: &[(DVec3, DVec3)],
) -> Option<Vec<(Point, Point)>> {
    edges
        .iter()
        .map(|&(a, b)| {
            Some((
                grid.project_point(face, reference + a)?,
                grid.project_point(face, reference + b)?,
            ))
        })
        .collect()
}

/// Whether polygon `p` (projected on a face of `grid`) may lie near a top
/// cell of the face ([`Footprint::sample`] bins it only there): its box,
/// grown by the depth `margin` (if any), by two lattice points and by a top
/// cell (the face's last top cell may reach past its edge), meets the
/// face. A perspective light's caster often shows on one or two of six.
fn near_face(grid: &TexelGrid, p: &ProjectedPolygon, margin: Option<f64>, density: u32) -> bool {
    let slack = margin.unwrap_or(0.0) + 2.0 / f64::from(density.max(1)) + f64::from(TOP_CELL);
    let (lo, hi) = bounds(p.iter().map(|&(x, y, _)| (x, y)));
    let (width, height) = (f64::from(grid.width()), f64::from(grid.height()));
    hi.0 > -slack && hi.1 > -slack && lo.0 < width + slack && lo.1 < height + slack
}

/// A projected triangle's box grown by `margin` and the plane of its
/// depths (a directional light's: t plus a constant), if it has one.
fn depth_plane(projected: &[(f64, f64, f64)], margin: f64) -> (Rect, Option<Affine>) {
    let rect = Rect::around(projected.iter().map(|&(x, y, _)| (x, y))).grown(margin);
    let plane = match projected {
        [a, b, c] => Affine::through([*a, *b, *c]),
        _ => None,
    };
    (rect, plane)
}

/// A probed lattice point and the passes whose front set holds the caster
/// there ([`Footprint::probe`]).
type Probed = ((i64, i64), u8);

/// A small cell of lattice points the outline crosses, and the polygons
/// (indices) near it.
type OutlineCell = (LatticeCell, Vec<u32>);

/// A polygon or outline edge (index) near a top cell (row, column).
type Binned = ((i64, i64), u32);

/// The top cells that polygons are near, in order (row by row), each with
/// the polygons and the outline edges near it (indices, in order), from
/// lists of [`Binned`] sorted.
struct Bins<'b> {
    polygons: &'b [Binned],
    edges: &'b [Binned],
}

impl Iterator for Bins<'_> {
    type Item = ((i64, i64), Vec<u32>, Vec<u32>);

    fn next(&mut self) -> Option<Self::Item> {
        let &(cell, _) = self.polygons.first()?;
        let take = |list: &mut &[Binned]| {
            // Those of cells before this one (edges of cells without
            // polygons) are skipped.
            let skip = list.partition_point(|&(c, _)| c < cell);
            let near = list[skip..].partition_point(|&(c, _)| c == cell);
            let indices = list[skip..skip + near].iter().map(|&(_, i)| i).collect();
            *list = &list[skip + near..];
            indices
        };
        let polygons = take(&mut self.polygons);
        Some((cell, polygons, take(&mut self.edges)))
    }
}

/// The polygons and outline edges (indices) near one cell.
struct Near<'f> {
    polygons: &'f [u32],
    edges: &'f [u32],
}

impl Footprint {
    /// Lattice point `(i, j)` in texel units: the centre of that texel of
    /// the grid `density` times denser.
    #[inline]
    fn point(&self, i: i64, j: i64) -> Point {
        let d = self.density as f64;
        ((i as f64 + 0.5) / d, (j as f64 + 0.5) / d)
    }

    /// Whether lattice point `p` lies on polygon `index` (within [`TOUCH`]).
    #[inline]
    fn touches(&self, index: u32, p: Point) -> bool {
        self.regions[index as usize]
            .as_ref()
            .is_some_and(|region| region.contains(p))
    }

    /// Samples the footprint top cell by top cell (in whole-lattice mode
    /// each traced as it comes, in outline mode its inside first, then the
    /// small cells the outline crosses); true once the caster is proven
    /// useful.
    fn sample(&self, sampler: &mut Sampler<'_, '_>) -> bool {
        let grid = sampler.rays.grid;
        let d = self.density as i64;
        let (width, height) = (grid.width() as i64 * d, grid.height() as i64 * d);
        let top = TOP_CELL as i64 * d;
        let (polygon_bins, edge_bins) = self.bins(width, height, top);
        let bins = Bins {
            polygons: &polygon_bins,
            edges: &edge_bins,
        };
        let mut lattice = TopCellPoints::default();
        let mut outline_cells = Vec::new();
        for ((cy, cx), polygons, edges) in bins {
            let (i0, j0) = (cx * top, cy * top);
            let cell = LatticeCell {
                i0,
                j0,
                ni: top.min(width - i0),
                nj: top.min(height - j0),
            };
            if cell.is_empty() {
                continue;
            }
            let proven = match self.outline {
                // Every point here that may be on the footprint is surely
                // hidden.
                None if sampler.mask().is_some_and(|m| m.holds_cell(cell)) => false,
                None => {
                    self.fill_top_cell(&polygons, cell, &mut lattice);
                    self.lattice_batches(sampler, &lattice, cell)
                }
                Some(_) => {
                    let near = &Near {
                        polygons: &polygons,
                        edges: &edges,
                    };
                    self.cell(sampler, near, cell, &[], &mut outline_cells)
                }
            };
            if proven {
                return true;
            }
        }
        self.outline_cells(sampler, &outline_cells)
    }

    /// (top cell, index) of every polygon and of every outline edge near a
    /// top cell of the face (`width` × `height` lattice points, top cells
    /// `top` points a side), each list sorted by cell (row by row), then
    /// index.
    fn bins(&self, width: i64, height: i64, top: i64) -> (Vec<Binned>, Vec<Binned>) {
        let d = self.density as i64;
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
        let mut polygon_bins: Vec<Binned> = Vec::new();
        for (index, polygon) in self.polygons.iter().enumerate() {
            // Grown by the depth margin: a cell's list must hold every
            // polygon whose depth may count at its points.
            let (lo, hi) = bounds(polygon.iter().copied());
            let (lo, hi) = (
                (lo.0 - self.margin, lo.1 - self.margin),
                (hi.0 + self.margin, hi.1 + self.margin),
            );
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    polygon_bins.push(((cy, cx), index as u32));
                }
            }
        }
        polygon_bins.sort_unstable();
        let mut edge_bins: Vec<Binned> = Vec::new();
        for (index, &(a, b)) in self.outline.iter().flatten().enumerate() {
            let (lo, hi) = bounds([a, b]);
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    edge_bins.push(((cy, cx), index as u32));
                }
            }
        }
        edge_bins.sort_unstable();
        (polygon_bins, edge_bins)
    }

    /// [`Self::outline_rays`] of each of `cells` in order until one proves
    /// the caster, a wave of cells at a time traced in parallel: a large
    /// caster's outline (a spot light's wall) can be most of a light's
    /// refinement and would leave the other threads idle. In outline mode
    /// a cell's rays and answer do not depend on the cells before it, and
    /// only the cells up to the first that proves the caster count (their
    /// proofs and rays), so the answer and the rays counted are the walk's
    /// one cell at a time, whatever the threads.
    fn outline_cells(&self, sampler: &mut Sampler<'_, '_>, cells: &[OutlineCell]) -> bool {
        debug_assert!(
            cells.is_empty() || !sampler.has_occlusion(),
            "no occlusion test in outline mode"
        );
        let (rays, caster) = (sampler.rays, sampler.caster);
        let wave = OUTLINE_WAVE * rayon::current_num_threads();
        for cells in cells.chunks(wave) {
            let outcomes: Vec<(bool, Vec<u32>, usize)> = cells
                .par_iter()
                .map_init(PacketState::default, |packet, (cell, polygons)| {
                    packet.rays.clear();
                    packet
                        .rays
                        .extend(self.outline_rays(rays.grid, polygons, *cell));
                    let (mut proven, mut found) = (false, Vec::new());
                    rays.trace_packet(packet, |c| {
                        proven |= c == caster;
                        found.push(c);
                    });
                    (proven, found, packet.rays.len())
                })
                .collect();
            for (proven, found, traced) in outcomes {
                sampler.record(found, traced);
                if proven {
                    return true;
                }
            }
        }
        false
    }

    /// Whole-lattice mode (no outline): which lattice points of a top
    /// `cell` lie on one of `polygons` (the cell's bin), and the caster's
    /// nearest depth at each, worked out once for the cell; its batches
    /// read them.
    fn fill_top_cell(&self, polygons: &[u32], cell: LatticeCell, lattice: &mut TopCellPoints) {
        // The cell's points a box may hold (rounded outward; every point
        // in the range is tested).
        let block = cell.block(self.density);
        // Without planes nothing is hidden: every point counts as nearest.
        let unknown = if self.planes.is_empty() {
            f64::NEG_INFINITY
        } else {
            f64::INFINITY
        };
        lattice.reset(cell, unknown);
        for &k in polygons {
            let region = &self.regions[k as usize];
            let Some((b, plane)) = self.planes.get(k as usize) else {
                // No depths: only whether points lie on it.
                let Some(region) = region else { continue };
                let b = region.bounds();
                for j in block.rows(b.y0, b.y1) {
                    for i in block.columns(b.x0, b.x1) {
                        let at = lattice.index(i, j);
                        lattice.on[at] |= region.contains(self.point(i, j));
                    }
                }
                continue;
            };
            // One walk of both boxes: the points on the polygon (within
            // [`TOUCH`]), and the points within the depth margin of it (in
            // its box grown by the margin and within the margin of every
            // edge's line), whose depth counts wherever some polygon puts
            // them on the footprint (`near` is read only there).
            let walk = region.as_ref().map_or(*b, |r| b.union(r.bounds()));
            for j in block.rows(walk.y0, walk.y1) {
                for i in block.columns(walk.x0, walk.x1) {
                    let (p, at) = (self.point(i, j), lattice.index(i, j));
                    let on = region.as_ref().is_some_and(|r| r.contains(p));
                    lattice.on[at] |= on;
                    let outside = p.0 < b.x0 || p.0 > b.x1 || p.1 < b.y0 || p.1 > b.y1;
                    // A point on the polygon is within the margin of it.
                    let near_it = on
                        || region
                            .as_ref()
                            .is_none_or(|r| r.contains_grown(p, self.margin));
                    if outside || !near_it {
                        continue;
                    }
                    let depth = plane.map_or(f64::NEG_INFINITY, |plane| plane.at(p));
                    let near = &mut lattice.near[at];
                    *near = near.min(if depth.is_nan() {
                        f64::NEG_INFINITY
                    } else {
                        depth
                    });
                }
            }
        }
    }

    /// The batches of a top cell in whole-lattice mode: quartered down to
    /// at most [`BATCH`] lattice points, each traced by
    /// [`Self::whole_cell`]; true once one proves the caster useful.
    fn lattice_batches(
        &self,
        sampler: &mut Sampler<'_, '_>,
        lattice: &TopCellPoints,
        cell: LatticeCell,
    ) -> bool {
        if cell.count() <= BATCH as i64 {
            return self.whole_cell(sampler, lattice, cell);
        }
        cell.quarters()
            .any(|quarter| self.lattice_batches(sampler, lattice, quarter))
    }

    /// Every lattice point of a small cell (within the top cell
    /// `lattice`) on the footprint, traced as one batch (whole-lattice
    /// mode: a model under a directional light, whose lattice rays are
    /// parallel and a fraction of a texel apart); true if any proves the
    /// caster useful.
    fn whole_cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        lattice: &TopCellPoints,
        cell: LatticeCell,
    ) -> bool {
        let mut points: Vec<(Point, f64)> = Vec::new();
        let mask = sampler.mask();
        let masked = |i: i64, j: i64| mask.is_some_and(|m| m.holds(i, j));
        for (i, j) in cell.points() {
            let at = lattice.index(i, j);
            if lattice.on[at] && !masked(i, j) {
                points.push((self.point(i, j), lattice.near[at]));
            }
        }
        let ray = |(p, _): (Point, f64)| sampler.rays.grid.ray_through(self.face, p.0, p.1);
        if sampler.has_occlusion() && points.len() > FEW_POINTS {
            // The points the occluders met so far surely hide need no ray,
            // nor a probe: often they are all of them.
            points = sampler.unhidden(points);
            if points.is_empty() {
                return false;
            }
            // A probe: the middle point alone, for the casters in front of
            // the caster here.
            let probe = points.remove(points.len() / 2);
            if sampler.trace(&ray(probe)).0 {
                return true;
            }
            // Else the rest were tested against these occluders already.
            if sampler.note_last_hits() && points.len() > FEW_POINTS {
                points = sampler.unhidden(points);
            }
        }
        let batch: Vec<TexelRay> = points.into_iter().map(ray).collect();
        sampler.trace_batch(&batch)
    }

    /// The rays of an outline cell: every lattice point of a small cell the
    /// outline crosses that lies on one of `polygons` (those near it),
    /// traced as one batch: the points a quartering down to single points
    /// would trace (and the corners it would probe inside the footprint),
    /// as one packet of a fraction of a texel instead of single rays.
    fn outline_rays<'g>(
        &'g self,
        grid: &'g TexelGrid,
        polygons: &'g [u32],
        cell: LatticeCell,
    ) -> impl Iterator<Item = TexelRay> + 'g {
        cell.points()
            .map(move |(i, j)| self.point(i, j))
            .filter(|&p| polygons.iter().any(|&k| self.touches(k, p)))
            .map(|p| grid.ray_through(self.face, p.0, p.1))
    }

    /// The lattice points of `cell` of an outlined footprint (terrain
    /// blocks, perspective lights), but for the small cells the outline
    /// crosses: those are added to `outline_cells` (with the polygons near
    /// each) for [`Self::outline_cells`] after the inside (a caster is
    /// proven there more often, and sooner); true once proven useful.
    fn cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        near: &Near<'_>,
        cell: LatticeCell,
        probed: &[Probed],
        outline_cells: &mut Vec<OutlineCell>,
    ) -> bool {
        let grid = sampler.rays.grid;
        if cell.is_point() {
            let (i0, j0) = (cell.i0, cell.j0);
            // A corner of the cell it was split from (whose probe proved
            // nothing): the same ray would again.
            if probed.iter().any(|&(at, _)| at == (i0, j0)) {
                return false;
            }
            let p = self.point(i0, j0);
            let inside = near.polygons.iter().any(|&i| self.touches(i, p));
            return inside && sampler.trace(&grid.ray_through(self.face, p.0, p.1)).0;
        }
        // What meets this cell, handed down so smaller cells test less.
        let grown = cell.rect(self.density).grown(TOUCH);
        let polygons: Vec<u32> = near
            .polygons
            .iter()
            .copied()
            .filter(|&i| beam::overlaps_rect(&self.polygons[i as usize], grown))
            .collect();
        if polygons.is_empty() {
            return false;
        }
        let all = self.outline.as_deref().unwrap_or_default();
        let edges: Vec<u32> = near
            .edges
            .iter()
            .copied()
            .filter(|&e| {
                let (a, b) = all[e as usize];
                beam::segment_meets_rect(a, b, grown)
            })
            .collect();
        let crossed = !edges.is_empty();
        let near = &Near {
            polygons: &polygons,
            edges: &edges,
        };
        if crossed && cell.count() <= BATCH as i64 {
            outline_cells.push((cell, polygons));
            return false;
        }
        let mut corners: [Probed; 4] = Default::default();
        if !crossed {
            let at = cell.corners();
            let (proven, fronts) = self.probe(sampler, at, probed);
            if proven {
                return true;
            }
            if fronts.iter().all(|&f| f == fronts[0]) {
                return false;
            }
            corners = [0, 1, 2, 3].map(|k| (at[k], fronts[k]));
        }
        // A crossed cell probed nothing.
        let probed = if crossed { &[][..] } else { &corners[..] };
        cell.quarters()
            .any(|quarter| self.cell(sampler, near, quarter, probed, outline_cells))
    }

    /// The probes of a cell: per corner (`at`, lattice points), the passes
    /// whose front set holds the caster ([`Sampler::front_passes`]), and
    /// whether one proves it useful. A corner already `probed` (one of the
    /// corners of the cell this one was split from, which proved nothing)
    /// is not traced again, nor is a corner twice (a cell one point wide):
    /// the same ray gives the same answer. The others go together.
    fn probe(
        &self,
        sampler: &mut Sampler<'_, '_>,
        at: [(i64, i64); 4],
        probed: &[Probed],
    ) -> (bool, [u8; 4]) {
        let grid = sampler.rays.grid;
        let mut fronts = [0u8; 4];
        // The corners to trace (index into `at`), each point once.
        let mut fresh: Vec<usize> = Vec::with_capacity(4);
        for (k, &corner) in at.iter().enumerate() {
            if let Some(&(_, front)) = probed.iter().find(|&&(p, _)| p == corner) {
                fronts[k] = front;
            } else if !fresh.iter().any(|&f| at[f] == corner) {
                fresh.push(k);
            }
        }
        let rays: Vec<TexelRay> = fresh
            .iter()
            .map(|&k| {
                let p = self.point(at[k].0, at[k].1);
                grid.ray_through(self.face, p.0, p.1)
            })
            .collect();
        let proven = sampler.trace_batch(&rays);
        for (&k, hits) in fresh.iter().zip(sampler.batch_hits(rays.len())) {
            fronts[k] = sampler.front_passes(hits);
        }
        // A corner met twice takes its first's answer.
        for k in 0..4 {
            if let Some(&first) = fresh.iter().find(|&&f| at[f] == at[k]) {
                fronts[k] = fronts[first];
            }
        }
        (proven, fronts)
    }
}
