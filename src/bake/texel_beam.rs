//! Beam tests in a light's image plane: a texel's beam (every ray through
//! its square) against projected triangles, as convex polygons in texel
//! units. Only the bake works in the image plane, so this lives beside it:
//! refinement finds where a caster's footprint has an edge, the
//! conservative grid pass (`conservative`) which triangles a beam meets and
//! whether nearer triangles cover all of it, `occlusion` which lattice
//! points an occluder surely covers, and `trace_light` which tiles lie
//! outside the hull of everything a light reaches.
//!
//! Every test errs on one documented side: "overlaps" and "crosses" may
//! answer yes for a polygon a hair away (they take a tolerance), "covers"
//! answers yes only when the uncovered rest is at most a sliver of
//! [`SLIVER`] texels² (what floating-point clipping leaves along shared
//! edges, where the ray/triangle test's tie rule gives every ray to one
//! side). `trace::beam` (the packet node test) bounds a tile's rays for
//! traversal; this module bounds a texel's beam against triangles in the
//! image plane.

/// A point in texel units of one face.
pub type Point = (f64, f64);

/// Area, in texels², below which what a union of clipped triangles leaves
/// of a square counts as covered: the residue of shared edges, where the
/// watertight ray test gives every ray to one of the two triangles.
pub const SLIVER: f64 = 1e-9;

/// An axis-aligned rectangle `[x0, x1] × [y0, y1]` in texel units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

impl Rect {
    pub fn grown(self, by: f64) -> Rect {
        Rect {
            x0: self.x0 - by,
            y0: self.y0 - by,
            x1: self.x1 + by,
            y1: self.y1 + by,
        }
    }

    /// The smallest rectangle holding `points` (inverted, meeting nothing,
    /// for none).
    pub fn around(points: impl IntoIterator<Item = Point>) -> Rect {
        let (lo, hi) = bounds(points);
        Rect {
            x0: lo.0,
            y0: lo.1,
            x1: hi.0,
            y1: hi.1,
        }
    }

    /// The smallest rectangle holding both.
    pub fn union(self, other: Rect) -> Rect {
        Rect {
            x0: self.x0.min(other.x0),
            y0: self.y0.min(other.y0),
            x1: self.x1.max(other.x1),
            y1: self.y1.max(other.y1),
        }
    }

    /// Whether the two closed rectangles share a point.
    pub fn meets(self, other: Rect) -> bool {
        self.x0 <= other.x1 && self.x1 >= other.x0 && self.y0 <= other.y1 && self.y1 >= other.y0
    }

    pub fn corners(self) -> [Point; 4] {
        [
            (self.x0, self.y0),
            (self.x1, self.y0),
            (self.x1, self.y1),
            (self.x0, self.y1),
        ]
    }
}

/// The smallest and largest coordinates of `points`.
pub fn bounds(points: impl IntoIterator<Item = Point>) -> (Point, Point) {
    points.into_iter().fold(
        (
            (f64::INFINITY, f64::INFINITY),
            (f64::NEG_INFINITY, f64::NEG_INFINITY),
        ),
        |(lo, hi), (x, y)| ((lo.0.min(x), lo.1.min(y)), (hi.0.max(x), hi.1.max(y))),
    )
}

/// Twice the signed area of `polygon` (positive: counter-clockwise).
pub fn signed_area2(polygon: &[Point]) -> f64 {
    (0..polygon.len())
        .map(|i| {
            let (a, b) = (polygon[i], polygon[(i + 1) % polygon.len()]);
            a.0 * b.1 - a.1 * b.0
        })
        .sum()
}

fn cross(o: Point, a: Point, b: Point) -> f64 {
    (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
}

/// A convex polygon (either winding) grown by a tolerance, ready for many
/// point tests: each edge's direction and allowance are worked out once,
/// and a point is tested with the same operations, in the same order, as
/// the one-off test [`inside_convex`] (so the two agree bit for bit).
#[derive(Debug, Clone)]
pub struct ConvexRegion {
    /// Per edge: its start, its direction (end − start), how far outside
    /// (a cross product, negative) a point may lie, and its length.
    edges: Edges,
    /// The winding's sign, so "inside" is a non-negative cross product.
    sign: f64,
    /// A box holding every point the test accepts (a quick reject).
    bounds: Rect,
}

impl ConvexRegion {
    /// `None` for a degenerate polygon (fewer than three points or no
    /// area), which contains nothing.
    pub fn new(polygon: &[Point], tolerance: f64) -> Option<ConvexRegion> {
        let sign = signed_area2(polygon).signum();
        if polygon.len() < 3 || sign == 0.0 || sign.is_nan() {
            return None;
        }
        let edge = |i: usize| {
            let (a, b) = (polygon[i], polygon[(i + 1) % polygon.len()]);
            let length = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
            (a, (b.0 - a.0, b.1 - a.1), -tolerance * length, length)
        };
        let edges = match polygon.len() {
            3 => Edges::Triangle([0, 1, 2].map(edge)),
            n => Edges::Polygon((0..n).map(edge).collect()),
        };
        let bounds = grown_bounds(polygon, tolerance.max(0.0));
        Some(ConvexRegion {
            edges,
            sign,
            bounds,
        })
    }

    /// Whether `p` lies within `extra` texels more than the tolerance of
    /// the polygon (each edge moved out by `extra` more; no quick reject by
    /// box, which does not hold the grown corners).
    pub fn contains_grown(&self, p: Point, extra: f64) -> bool {
        self.edges
            .as_slice()
            .iter()
            .all(|&(a, e, allowance, length)| {
                self.sign * (e.0 * (p.1 - a.1) - e.1 * (p.0 - a.0)) >= allowance - extra * length
            })
    }

    /// The x of row `y` where [`Self::contains_grown`] with `extra` ≥ 0
    /// (so also [`Self::contains`]) may accept a point: an interval
    /// `lo..=hi` holding every such point (empty when `lo > hi`), so a
    /// walk along a row tests only the points in it. Each edge steep
    /// enough to cross rows reliably bounds it from one side, with slack
    /// far beyond the rounding of either test (the test still decides).
    pub fn row_span(&self, y: f64, extra: f64) -> (f64, f64) {
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        for &(a, e, allowance, length) in self.edges.as_slice() {
            // The test is c + k·(x − a.0) ≥ floor.
            let k = -self.sign * e.1;
            // (False for NaN too.)
            let steep = k.abs() >= STEEP * length;
            if !steep {
                continue;
            }
            let c = self.sign * e.0 * (y - a.1);
            let floor = allowance - extra * length;
            let bound = a.0 + (floor - c) / k;
            let slack = 1e-9 * (1.0 + a.0.abs() + a.1.abs() + y.abs() + bound.abs());
            if !(bound.is_finite() && slack.is_finite()) {
                continue;
            }
            if k > 0.0 {
                lo = lo.max(bound - slack);
            } else {
                hi = hi.min(bound + slack);
            }
        }
        (lo, hi)
    }

    /// A box holding every point [`Self::contains`] accepts.
    pub fn bounds(&self) -> Rect {
        self.bounds
    }

    /// Whether `p` lies in the polygon or within the tolerance of it.
    #[inline]
    pub fn contains(&self, p: Point) -> bool {
        let b = self.bounds;
        if !(p.0 >= b.x0 && p.0 <= b.x1 && p.1 >= b.y0 && p.1 <= b.y1) {
            return false;
        }
        self.edges.as_slice().iter().all(|&(a, e, allowance, _)| {
            self.sign * (e.0 * (p.1 - a.1) - e.1 * (p.0 - a.0)) >= allowance
        })
    }
}

/// How steep (rise over length) an edge must be to bound a row's span
/// ([`ConvexRegion::row_span`]): the bound's rounding grows as the edge
/// flattens; flatter ones are left to the test.
const STEEP: f64 = 1e-3;

/// A region's edges (start, direction, allowance, length): a triangle's
/// held inline, since refinement makes one per triangle of every caster
/// it looks at, and most are triangles.
#[derive(Debug, Clone)]
enum Edges {
    Triangle([(Point, Point, f64, f64); 3]),
    Polygon(Vec<(Point, Point, f64, f64)>),
}

impl Edges {
    #[inline]
    fn as_slice(&self) -> &[(Point, Point, f64, f64)] {
        match self {
            Edges::Triangle(edges) => edges,
            Edges::Polygon(edges) => edges,
        }
    }
}

/// A box holding convex `polygon` grown by `by` ≥ 0 (each edge moved out
/// by `by`): the polygon's own box when `by` is 0, else the box of the
/// moved edges' crossings, which reach out further than `by` at sharp
/// corners; with a hair of slack for rounding; unbounded when two
/// neighbouring edges are too near parallel to cross reliably.
fn grown_bounds(polygon: &[Point], by: f64) -> Rect {
    let everywhere = Rect {
        x0: f64::NEG_INFINITY,
        y0: f64::NEG_INFINITY,
        x1: f64::INFINITY,
        y1: f64::INFINITY,
    };
    let n = polygon.len();
    if by == 0.0 {
        let own = Rect::around(polygon.iter().copied());
        let scale = own
            .x0
            .abs()
            .max(own.y0.abs())
            .max(own.x1.abs())
            .max(own.y1.abs());
        return own.grown(1e-9 * (1.0 + scale) + 1e-12);
    }
    let sign = signed_area2(polygon).signum();
    // Outward unit normal and offset of edge i (from vertex i to i + 1).
    let line = |i: usize| {
        let (a, b) = (polygon[i], polygon[(i + 1) % n]);
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let length = (dx * dx + dy * dy).sqrt();
        let normal = (sign * dy / length, -sign * dx / length);
        (normal, normal.0 * a.0 + normal.1 * a.1 + by)
    };
    let mut bounds = Rect {
        x0: f64::INFINITY,
        y0: f64::INFINITY,
        x1: f64::NEG_INFINITY,
        y1: f64::NEG_INFINITY,
    };
    let mut scale: f64 = 0.0;
    // Each edge's line is worked out once, carried to its next vertex.
    let Some(last) = n.checked_sub(1) else {
        return everywhere;
    };
    let mut previous = line(last);
    for i in 0..n {
        let current = line(i);
        let ((n1, c1), (n2, c2)) = (previous, current);
        previous = current;
        let det = n1.0 * n2.1 - n1.1 * n2.0;
        if det.is_nan() || det.abs() <= 1e-9 {
            return everywhere;
        }
        let x = (c1 * n2.1 - c2 * n1.1) / det;
        let y = (n1.0 * c2 - n2.0 * c1) / det;
        bounds = Rect {
            x0: bounds.x0.min(x),
            y0: bounds.y0.min(y),
            x1: bounds.x1.max(x),
            y1: bounds.y1.max(y),
        };
        scale = scale.max(x.abs()).max(y.abs());
    }
    if !(bounds.x0 <= bounds.x1 && bounds.y0 <= bounds.y1) {
        return everywhere;
    }
    bounds.grown(1e-9 * (1.0 + scale) + 1e-12)
}

/// Whether `p` lies in the convex `polygon` (either winding) or within
/// `tolerance` texels of it.
pub fn inside_convex(polygon: &[Point], p: Point, tolerance: f64) -> bool {
    ConvexRegion::new(polygon, tolerance).is_some_and(|region| region.contains(p))
}

/// The convex hull of `points`, counter-clockwise (Andrew's monotone
/// chain); collinear points left out, fewer than three points returned as
/// they are (sorted, without repeats).
pub fn convex_hull(mut points: Vec<Point>) -> Vec<Point> {
    points.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let mut hull: Vec<Point> = Vec::with_capacity(2 * points.len());
    // The lower chain left to right, then the upper one right to left.
    for chain in [points.clone(), points.into_iter().rev().collect()] {
        let start = hull.len();
        for p in chain {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        // Each chain's last point is the next chain's first.
        hull.pop();
    }
    hull
}

/// Whether the convex `polygon` and `rect` share a point (separating axes:
/// the rectangle's two and the polygon's edge normals).
pub fn overlaps_rect(polygon: &[Point], rect: Rect) -> bool {
    if polygon.is_empty() {
        return false;
    }
    if !Rect::around(polygon.iter().copied()).meets(rect) {
        return false;
    }
    let sign = signed_area2(polygon).signum();
    if sign == 0.0 {
        return true;
    }
    (0..polygon.len()).all(|i| {
        let (a, b) = (polygon[i], polygon[(i + 1) % polygon.len()]);
        rect.corners().iter().any(|&c| sign * cross(a, b, c) >= 0.0)
    })
}

/// Whether segment `a`–`b` meets `rect` (Liang–Barsky).
pub fn segment_meets_rect(a: Point, b: Point, rect: Rect) -> bool {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - rect.x0),
        (dx, rect.x1 - a.0),
        (-dy, a.1 - rect.y0),
        (dy, rect.y1 - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return false;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
            if t0 > t1 {
                return false;
            }
        }
    }
    true
}

/// The part of convex `polygon` on the side of the line `a`→`b` where
/// `cross(a, b, p) * side >= 0` (Sutherland–Hodgman, one edge).
fn clip_half(polygon: &[Point], a: Point, b: Point, side: f64) -> Vec<Point> {
    let mut out = Vec::with_capacity(polygon.len() + 1);
    for i in 0..polygon.len() {
        let (p, q) = (polygon[i], polygon[(i + 1) % polygon.len()]);
        let (dp, dq) = (side * cross(a, b, p), side * cross(a, b, q));
        if dp >= 0.0 {
            out.push(p);
        }
        if (dp >= 0.0) != (dq >= 0.0) {
            let t = dp / (dp - dq);
            out.push((p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t));
        }
    }
    out
}

/// `rect` ∩ convex `polygon` (empty when they do not meet).
pub fn clip_to_rect(polygon: &[Point], rect: Rect) -> Vec<Point> {
    let corners = rect.corners();
    let mut out = polygon.to_vec();
    for i in 0..4 {
        if out.is_empty() {
            break;
        }
        out = clip_half(&out, corners[i], corners[(i + 1) % 4], 1.0);
    }
    out
}

/// `pieces` (convex polygons) minus the convex `cutter`: each piece is
/// split into its parts outside each edge of the cutter (at most one per
/// edge), pieces of at most [`SLIVER`] texels² are dropped.
pub fn subtract(pieces: Vec<Vec<Point>>, cutter: &[Point]) -> Vec<Vec<Point>> {
    let sign = signed_area2(cutter).signum();
    if cutter.len() < 3 || sign == 0.0 {
        return pieces;
    }
    let mut out = Vec::new();
    for piece in pieces {
        let mut rest = piece;
        for i in 0..cutter.len() {
            if rest.is_empty() {
                break;
            }
            let (a, b) = (cutter[i], cutter[(i + 1) % cutter.len()]);
            // Wholly on one side of the edge's line, the clips below would
            // return the piece itself and nothing: skip their copies.
            let sides = rest.iter().map(|&p| sign * cross(a, b, p));
            if sides.clone().all(|d| d > 0.0) {
                continue;
            }
            if sides.clone().all(|d| d < 0.0) {
                if signed_area2(&rest).abs() * 0.5 > SLIVER {
                    out.push(rest);
                }
                break;
            }
            let outside = clip_half(&rest, a, b, -sign);
            if signed_area2(&outside).abs() * 0.5 > SLIVER {
                out.push(outside);
            }
            rest = clip_half(&rest, a, b, sign);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const SQUARE: Rect = Rect {
        x0: 0.0,
        y0: 0.0,
        x1: 1.0,
        y1: 1.0,
    };

    #[test]
    fn two_triangles_of_a_quad_cover_a_square_on_their_diagonal() {
        let quad = [(-1.0, -1.0), (2.0, -1.0), (2.0, 2.0), (-1.0, 2.0)];
        let first = [quad[0], quad[1], quad[2]];
        let second = [quad[0], quad[2], quad[3]];
        let square = clip_to_rect(&SQUARE.corners(), SQUARE);
        let rest = subtract(subtract(vec![square.clone()], &first), &second);
        assert!(rest.is_empty(), "{rest:?}");
        // One of them alone leaves half the square.
        let half = subtract(vec![square], &first);
        let area: f64 = half.iter().map(|p| signed_area2(p).abs() * 0.5).sum();
        assert!((area - 0.5).abs() < 1e-12, "{area}");
    }

    #[test]
    fn overlap_inside_and_segment_tests() {
        let tri = [(1.5, 0.5), (3.0, 0.5), (1.5, 2.0)];
        assert!(!overlaps_rect(&tri, SQUARE));
        assert!(overlaps_rect(&tri, SQUARE.grown(0.6)));
        // A triangle whose box overlaps the square but which does not.
        let corner = [(0.9, 2.0), (2.0, 0.9), (2.0, 2.0)];
        assert!(!overlaps_rect(&corner, SQUARE));
        assert!(inside_convex(&tri, (1.6, 0.6), 0.0));
        assert!(!inside_convex(&tri, (1.4, 0.6), 0.0));
        assert!(inside_convex(&tri, (1.4, 0.6), 0.11));
        assert!(segment_meets_rect((-1.0, 0.5), (2.0, 0.5), SQUARE));
        assert!(!segment_meets_rect((-1.0, 1.5), (2.0, 1.5), SQUARE));
        assert!(!segment_meets_rect((1.2, 2.0), (2.0, 1.2), SQUARE));
    }

    /// `subtract` without its one-side shortcuts: the two clips per edge.
    fn subtract_by_clipping(pieces: Vec<Vec<Point>>, cutter: &[Point]) -> Vec<Vec<Point>> {
        let sign = signed_area2(cutter).signum();
        if cutter.len() < 3 || sign == 0.0 {
            return pieces;
        }
        let mut out = Vec::new();
        for piece in pieces {
            let mut rest = piece;
            for i in 0..cutter.len() {
                if rest.is_empty() {
                    break;
                }
                let (a, b) = (cutter[i], cutter[(i + 1) % cutter.len()]);
                let outside = clip_half(&rest, a, b, -sign);
                if signed_area2(&outside).abs() * 0.5 > SLIVER {
                    out.push(outside);
                }
                rest = clip_half(&rest, a, b, sign);
            }
        }
        out
    }

    fn random_triangle(rng: &mut crate::rng::Rng, size: f64) -> Vec<Point> {
        let c = (rng.range(-5.0, 5.0), rng.range(-5.0, 5.0));
        (0..3)
            .map(|_| (c.0 + rng.range(-size, size), c.1 + rng.range(-size, size)))
            .collect()
    }

    #[test]
    fn subtract_gives_what_clipping_every_edge_gives() {
        let mut rng = crate::rng::Rng::new(3);
        for _ in 0..2000 {
            let pieces = vec![
                random_triangle(&mut rng, 2.0),
                random_triangle(&mut rng, 1.0),
            ];
            let cutter = random_triangle(&mut rng, 3.0);
            assert_eq!(
                subtract(pieces.clone(), &cutter),
                subtract_by_clipping(pieces, &cutter)
            );
        }
    }

    #[test]
    fn a_convex_region_box_holds_every_point_it_accepts() {
        // Sharp triangles grown by a tolerance reach past their box grown
        // by it at the corners; the region's box must still hold them.
        let mut rng = crate::rng::Rng::new(8);
        let mut accepted = 0;
        for round in 0..3000 {
            let mut polygon = random_triangle(&mut rng, 2.0);
            if round % 2 == 0 {
                // A needle: one vertex near the line through the others.
                let (a, b) = (polygon[0], polygon[1]);
                let t = rng.range(-0.5, 1.5);
                polygon[2] = (
                    a.0 + (b.0 - a.0) * t + rng.range(-1e-3, 1e-3),
                    a.1 + (b.1 - a.1) * t + rng.range(-1e-3, 1e-3),
                );
            }
            let tolerance = [0.0, 1e-6, 0.01, 0.3, -0.01][round % 5];
            let Some(region) = ConvexRegion::new(&polygon, tolerance) else {
                continue;
            };
            let b = region.bounds();
            for _ in 0..40 {
                let v = polygon[rng.below(3)];
                let reach = tolerance.abs().max(1e-3) * 50.0;
                let p = (
                    v.0 + rng.range(-reach, reach),
                    v.1 + rng.range(-reach, reach),
                );
                // The test without the box: every edge within the tolerance.
                let by_edges = region.contains_grown(p, 0.0);
                assert_eq!(
                    region.contains(p),
                    by_edges,
                    "{polygon:?} {tolerance} {p:?}"
                );
                if by_edges {
                    accepted += 1;
                    assert!(
                        p.0 >= b.x0 && p.0 <= b.x1 && p.1 >= b.y0 && p.1 <= b.y1,
                        "{polygon:?} grown by {tolerance}: {p:?} outside {b:?}"
                    );
                }
                // Growing further only adds points.
                assert!(!by_edges || region.contains_grown(p, 0.05));
            }
        }
        assert!(accepted > 5000, "{accepted}");
    }

    /// `row_span` holds every point of its row the region accepts, at the
    /// very edge too (the last accepted point of a row, found by bisection,
    /// and its neighbours a few ulps out), over seeded random triangles and
    /// quads from fat ones to needles and near-flat edges, far from the
    /// origin, shrunk or grown; and it is narrow: the span is finite on
    /// most rows.
    #[test]
    fn a_row_span_holds_every_point_the_region_accepts() {
        let mut rng = crate::rng::Rng::new(29);
        let (mut checked, mut bounded) = (0, 0);
        for round in 0..3000 {
            let far = [0.0, 1e3, 2e4][round % 3];
            let mut polygon: Vec<Point> = random_triangle(&mut rng, 2.0)
                .into_iter()
                .map(|(x, y)| (x + far, y - far))
                .collect();
            match round % 4 {
                // A needle.
                0 => {
                    let (a, b) = (polygon[0], polygon[1]);
                    let t = rng.range(-0.5, 1.5);
                    polygon[2] = (
                        a.0 + (b.0 - a.0) * t + rng.range(-1e-3, 1e-3),
                        a.1 + (b.1 - a.1) * t + rng.range(-1e-3, 1e-3),
                    );
                }
                // A near-flat edge.
                1 => polygon[1].1 = polygon[0].1 + rng.range(-1e-4, 1e-4),
                // A quad (the hull of four points, when convex).
                2 => {
                    let (a, b, c) = (polygon[0], polygon[1], polygon[2]);
                    polygon.push((a.0 + c.0 - b.0, a.1 + c.1 - b.1));
                    polygon.swap(2, 3);
                    polygon.swap(1, 2);
                }
                _ => {}
            }
            let tolerance = [0.0, 1e-6, 0.01, -0.01, 0.3][round % 5];
            let extra = [0.0, 0.0102, 0.3][round % 3];
            let Some(region) = ConvexRegion::new(&polygon, tolerance) else {
                continue;
            };
            let accepts = |p: Point| region.contains_grown(p, extra);
            for k in 0..8 {
                // Rows through a vertex exactly, and random ones.
                let y = match k {
                    0..3 => polygon[k].1,
                    _ => {
                        let v = polygon[rng.below(polygon.len())];
                        v.1 + rng.range(-1.5, 1.5)
                    }
                };
                let (lo, hi) = region.row_span(y, extra);
                bounded += usize::from(lo.is_finite() && hi.is_finite());
                let holds = |x: f64| !accepts((x, y)) || (lo <= x && x <= hi);
                // Random points along the row.
                for _ in 0..20 {
                    let x = polygon[rng.below(polygon.len())].0 + rng.range(-3.0, 3.0);
                    checked += 1;
                    assert!(
                        holds(x),
                        "{polygon:?} {tolerance} {extra} row {y}: {x} outside {lo}..{hi}"
                    );
                }
                // The row's last accepted points, each way, and a few ulps on.
                let inside = polygon.iter().map(|p| p.0).sum::<f64>() / polygon.len() as f64;
                if !accepts((inside, y)) {
                    continue;
                }
                for way in [-1.0, 1.0] {
                    let (mut a, mut b) = (inside, inside + way * 10.0);
                    for _ in 0..200 {
                        let m = 0.5 * (a + b);
                        if accepts((m, y)) {
                            a = m;
                        } else {
                            b = m;
                        }
                    }
                    let mut x = a;
                    for _ in 0..4 {
                        checked += 1;
                        assert!(
                            holds(x),
                            "{polygon:?} {tolerance} {extra} row {y}: edge {x} outside {lo}..{hi}"
                        );
                        x = if way > 0.0 {
                            x.next_up()
                        } else {
                            x.next_down()
                        };
                    }
                }
            }
        }
        assert!(checked > 100_000 && bounded > 10_000, "{checked} {bounded}");
    }
}
