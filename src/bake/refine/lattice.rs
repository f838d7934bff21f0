//! Cells of refinement's lattice (the rays of a grid `refine_density` times
//! denser than the light's): the rectangles a footprint is cut into and
//! quartered, a top cell's points on the footprint, and the mask of the
//! points a caster's occluders surely hide. Named here so the footprint's
//! walk reads in cells rather than in tuples of indices.

use crate::bake::occlusion::LatticeBlock;
use crate::bake::texel_beam::{bounds, Point, Rect};
use crate::light::ProjectedPolygon;

/// How near (texel units) a lattice point or cell must be to a footprint
/// polygon or edge to count as touching it: rays exactly on an edge may
/// hit under the tie rule.
pub(super) const TOUCH: f64 = 1e-6;

/// Most lattice points in the box of a caster's footprint for which a
/// [`Mask`] is made (a big caster is seldom hidden whole).
const MOST_BOX_POINTS: f64 = 4096.0;

/// A rectangle of lattice points: columns `i0..i0 + ni`, rows
/// `j0..j0 + nj` (point `(i, j)` is the centre of that texel of the denser
/// grid).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct LatticeCell {
    pub(super) i0: i64,
    pub(super) j0: i64,
    pub(super) ni: i64,
    pub(super) nj: i64,
}

impl LatticeCell {
    /// How many points it holds (`ni · nj`).
    pub(super) fn count(self) -> i64 {
        self.ni * self.nj
    }

    /// Whether a side holds no point (a top cell past the face's edge).
    pub(super) fn is_empty(self) -> bool {
        self.ni <= 0 || self.nj <= 0
    }

    /// Whether it is one point.
    pub(super) fn is_point(self) -> bool {
        self.ni == 1 && self.nj == 1
    }

    /// Its points, row by row.
    pub(super) fn points(self) -> impl Iterator<Item = (i64, i64)> {
        let LatticeCell { i0, j0, ni, nj } = self;
        (j0..j0 + nj).flat_map(move |j| (i0..i0 + ni).map(move |i| (i, j)))
    }

    /// Its corners: the first row's first and last points, then the last
    /// row's (the same point more than once when a side holds one).
    pub(super) fn corners(self) -> [(i64, i64); 4] {
        let LatticeCell { i0, j0, ni, nj } = self;
        let last = (i0 + ni - 1, j0 + nj - 1);
        [(i0, j0), (last.0, j0), (i0, last.1), last]
    }

    /// Its non-empty quarters, in the order cells are visited (the first
    /// ones the larger).
    pub(super) fn quarters(self) -> impl Iterator<Item = LatticeCell> {
        let LatticeCell { i0, j0, ni, nj } = self;
        let (hi, hj) = ((ni + 1) / 2, (nj + 1) / 2);
        let cell = |i0, j0, ni, nj| LatticeCell { i0, j0, ni, nj };
        [
            cell(i0, j0, hi, hj),
            cell(i0 + hi, j0, ni - hi, hj),
            cell(i0, j0 + hj, hi, nj - hj),
            cell(i0 + hi, j0 + hj, ni - hi, nj - hj),
        ]
        .into_iter()
        .filter(|q| q.ni > 0 && q.nj > 0)
    }

    /// The texels of the denser grid (`density` per texel side) whose
    /// centres its points are, as one rectangle in texel units.
    pub(super) fn rect(self, density: u32) -> Rect {
        let d = density as f64;
        Rect {
            x0: self.i0 as f64 / d,
            y0: self.j0 as f64 / d,
            x1: (self.i0 + self.ni) as f64 / d,
            y1: (self.j0 + self.nj) as f64 / d,
        }
    }

    /// The same points as a block of the lattice `density` per texel side
    /// (the occlusion test's).
    pub(super) fn block(self, density: u32) -> LatticeBlock {
        LatticeBlock {
            i0: self.i0,
            j0: self.j0,
            ni: self.ni,
            nj: self.nj,
            density,
        }
    }
}

/// A top cell's points in whole-lattice mode (`Footprint::fill_top_cell`):
/// per point, row by row, whether it lies on the footprint and the
/// caster's nearest depth there (`-∞` where a polygon without a plane may
/// be hit, or without planes at all; `+∞` where none may). Reused from
/// cell to cell.
#[derive(Default)]
pub(super) struct TopCellPoints {
    cell: LatticeCell,
    pub(super) on: Vec<bool>,
    pub(super) near: Vec<f64>,
}

impl TopCellPoints {
    /// Starts over for `cell`: no point on the footprint, every depth
    /// `unknown`.
    pub(super) fn reset(&mut self, cell: LatticeCell, unknown: f64) {
        self.cell = cell;
        self.on.clear();
        self.on.resize(cell.count() as usize, false);
        self.near.clear();
        self.near.resize(cell.count() as usize, unknown);
    }

    /// Point `(i, j)`'s place in `on` and `near`.
    pub(super) fn index(&self, i: i64, j: i64) -> usize {
        let LatticeCell { i0, j0, ni, .. } = self.cell;
        ((j - j0) * ni + (i - i0)) as usize
    }
}

/// Which lattice points of the box of a caster's footprint its occluders
/// surely hide from it (`Occlusion::hidden_block` at its least depth
/// anywhere). Points outside the box are not on the footprint.
pub(super) struct Mask {
    block: LatticeBlock,
    hidden: Vec<bool>,
}

impl Mask {
    /// The mask of `block`, `hidden` per point row by row.
    pub(super) fn new(block: LatticeBlock, hidden: Vec<bool>) -> Mask {
        Mask { block, hidden }
    }

    /// Whether every point of the box is surely hidden.
    pub(super) fn holds_all(&self) -> bool {
        self.hidden.iter().all(|&h| h)
    }

    /// Whether lattice point `(i, j)` is surely hidden.
    pub(super) fn holds(&self, i: i64, j: i64) -> bool {
        self.block.index(i, j).is_some_and(|at| self.hidden[at])
    }

    /// Whether every point of `cell` in the box is surely hidden: then
    /// none of the cell that may be on the footprint is traced.
    pub(super) fn holds_cell(&self, cell: LatticeCell) -> bool {
        let b = &self.block;
        let i1 = (cell.i0 + cell.ni).min(b.i0 + b.ni);
        let j1 = (cell.j0 + cell.nj).min(b.j0 + b.nj);
        (cell.j0.max(b.j0)..j1).all(|j| (cell.i0.max(b.i0)..i1).all(|i| self.holds(i, j)))
    }

    /// Whether every lattice point within `reach` of the box of polygon
    /// `p` is surely hidden: where its region (grown by [`TOUCH`]) and its
    /// depth margin may reach, when `reach` is at least the margin and
    /// the lattice step (a mask is made only when [`footprint_box`] found
    /// every region within a step of its box). Then the polygon changes
    /// no point that is traced.
    pub(super) fn holds_polygon(&self, p: &ProjectedPolygon, reach: f64) -> bool {
        let (lo, hi) = bounds(p.iter().map(|&(x, y, _)| (x, y)));
        let columns = self.block.columns(lo.0 - reach, hi.0 + reach);
        let mut rows = self.block.rows(lo.1 - reach, hi.1 + reach);
        rows.all(|j| columns.clone().all(|i| self.holds(i, j)))
    }
}

/// The lattice points (`density` per texel side) in the box of every point
/// the lattice may take as on the footprint of `projected` (a caster's
/// triangles on a directional light's face; `None`: a vertex not finite):
/// the block a [`Mask`] is made of, when [`footprint_box`] answers and the
/// box holds from one to [`MOST_BOX_POINTS`] points.
pub(super) fn footprint_block(
    projected: &[Option<ProjectedPolygon>],
    density: u32,
) -> Option<LatticeBlock> {
    let d = f64::from(density);
    let projected = projected.iter().map(|p| match p.as_deref() {
        Some(&[a, b, c]) => Some([a, b, c].map(|(x, y, _)| (x, y))),
        _ => None,
    });
    let (lo, hi) = footprint_box(projected, 1.0 / d)?;
    // Lattice point i lies at (i + 0.5) / d.
    let index = |x: f64, round: fn(f64) -> f64| round(x * d - 0.5);
    let (i0, i1) = (index(lo.0, f64::ceil), index(hi.0, f64::floor));
    let (j0, j1) = (index(lo.1, f64::ceil), index(hi.1, f64::floor));
    let (ni, nj) = (i1 - i0 + 1.0, j1 - j0 + 1.0);
    if density == 0 || ni < 1.0 || nj < 1.0 || ni * nj > MOST_BOX_POINTS {
        return None;
    }
    Some(LatticeBlock {
        i0: i0 as i64,
        j0: j0 as i64,
        ni: ni as i64,
        nj: nj as i64,
        density,
    })
}

/// The box (texel units) of every point the lattice may take as on the
/// footprint of `triangles` (projected on a directional light's face;
/// `None`: a corner not finite): their box grown by `grow`, which holds
/// each triangle grown by [`TOUCH`] (as `ConvexRegion` grows it, with
/// its box's slack for rounding) when no corner is so sharp that the
/// grown triangle reaches further than half of it (`TOUCH /
/// sin(angle / 2)`); `None` then, or for a corner not finite.
fn footprint_box(
    triangles: impl Iterator<Item = Option<[Point; 3]>>,
    grow: f64,
) -> Option<(Point, Point)> {
    let (mut lo, mut hi) = (
        (f64::INFINITY, f64::INFINITY),
        (f64::NEG_INFINITY, f64::NEG_INFINITY),
    );
    for triangle in triangles {
        let [a, b, c] = triangle?;
        for v in [a, b, c] {
            if !(v.0.is_finite() && v.1.is_finite()) {
                return None;
            }
            lo = (lo.0.min(v.0), lo.1.min(v.1));
            hi = (hi.0.max(v.0), hi.1.max(v.1));
        }
        // sin(angle) at a corner is 2·area over the product of its sides'
        // lengths, and sin(angle / 2) ≥ sin(angle) / 2. (A triangle without
        // area has no least angle to go by: `ConvexRegion` still makes a
        // region of it, unbounded.)
        let area2 = ((b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)).abs();
        let side = |p: Point, q: Point| ((q.0 - p.0).powi(2) + (q.1 - p.1).powi(2)).sqrt();
        let (ab, bc, ca) = (side(a, b), side(b, c), side(c, a));
        let longest_pair = (ab * ca).max(ab * bc).max(bc * ca);
        let least_half_sine = area2 / longest_pair / 2.0;
        // Half of `grow` for the reach, half for the region box's slack.
        // (NaN, from a side of length 0, gives up too.)
        if least_half_sine.is_nan() || least_half_sine * grow < 2.0 * TOUCH {
            return None;
        }
    }
    (lo.0 <= hi.0 && lo.1 <= hi.1)
        .then_some(((lo.0 - grow, lo.1 - grow), (hi.0 + grow, hi.1 + grow)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::texel_beam::ConvexRegion;
    use crate::rng::Rng;

    /// `footprint_box` holds the box of each triangle's region grown by
    /// [`TOUCH`] (which holds every point the region accepts) whenever it
    /// answers, over seeded random triangles from fat ones to needles, and
    /// from 5 texels to a ten-thousandth, far from the origin; and it
    /// answers for all but the sharpest.
    #[test]
    fn the_footprint_box_holds_every_region_it_answers_for() {
        let mut rng = Rng::new(17);
        let (mut answered, mut refused) = (0, 0);
        for k in 0..2000 {
            let a = ((rng.unit() - 0.5) * 2e4, (rng.unit() - 0.5) * 2e4);
            // The corner at `a`: from 1 rad down to 1e-9 rad.
            let angle = 10f64.powf(-9.0 * rng.unit());
            // Sides from 0.1 mm to 5 texels.
            let (side, other) = (10f64.powf(-4.0 + 4.7 * rng.unit()), 0.2 + rng.unit());
            let turn = rng.unit() * std::f64::consts::TAU;
            let b = (a.0 + side * turn.cos(), a.1 + side * turn.sin());
            let far = side * other;
            let c = (
                a.0 + far * (turn + angle).cos(),
                a.1 + far * (turn + angle).sin(),
            );
            let triangle = [a, b, c];
            let Some((lo, hi)) = footprint_box(std::iter::once(Some(triangle)), 1.0 / 8.0) else {
                refused += 1;
                continue;
            };
            answered += 1;
            if let Some(region) = ConvexRegion::new(&triangle, TOUCH) {
                let r = region.bounds();
                assert!(
                    r.x0 >= lo.0 && r.y0 >= lo.1 && r.x1 <= hi.0 && r.y1 <= hi.1,
                    "triangle {k} {triangle:?}: region {r:?} outside {lo:?}..{hi:?}"
                );
            }
        }
        assert!(
            answered > 400 && refused > 400,
            "{answered} answered, {refused} refused"
        );
    }

    /// A cell's quarters hold each of its points exactly once, none is
    /// empty, and no later quarter is larger than the first, over every
    /// cell up to 9 × 9 points.
    #[test]
    fn the_quarters_of_a_cell_hold_each_of_its_points_once() {
        for ni in 1..=9 {
            for nj in 1..=9 {
                let cell = LatticeCell {
                    i0: -3,
                    j0: 5,
                    ni,
                    nj,
                };
                let quarters: Vec<LatticeCell> = cell.quarters().collect();
                assert!(quarters.iter().all(|q| !q.is_empty()), "{cell:?}");
                assert!(
                    quarters.iter().all(|q| q.count() <= quarters[0].count()),
                    "{cell:?}: {quarters:?}"
                );
                let mut points: Vec<(i64, i64)> =
                    quarters.iter().flat_map(|q| q.points()).collect();
                points.sort_unstable();
                let mut expected: Vec<(i64, i64)> = cell.points().collect();
                expected.sort_unstable();
                assert_eq!(points, expected, "{cell:?}");
            }
        }
    }

    /// A top cell's index puts its points, row by row, at `0..count`.
    #[test]
    fn a_top_cells_points_are_indexed_row_by_row() {
        let cell = LatticeCell {
            i0: 8,
            j0: -4,
            ni: 3,
            nj: 5,
        };
        let mut points = TopCellPoints::default();
        points.reset(cell, f64::INFINITY);
        let indices: Vec<usize> = cell.points().map(|(i, j)| points.index(i, j)).collect();
        assert_eq!(indices, (0..cell.count() as usize).collect::<Vec<_>>());
        assert_eq!(points.on.len(), indices.len());
        assert!(points.near.iter().all(|&d| d == f64::INFINITY));
    }
}
