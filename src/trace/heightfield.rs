//! Terrain as a height field: a block's cells are traced where the ray
//! goes, not flattened into triangles. A per-block min/max pyramid (leaf
//! tiles of 2×2 cells) skips empty space; at a leaf, each cell's two
//! triangles go through the same watertight test and tie rule as models.
//!
//! Watertight across cells and blocks: a vertex is computed by one function
//! ([`HeightGrid::vertex`], `origin + i·size/cells` in f64, then minus the
//! reference point, then rounded to f32), so a vertex shared by two cells,
//! or by two neighbouring blocks (whose origins differ by exactly the chunk
//! size), is bit-equal in both, and the tie rule gives every shared edge
//! and vertex to exactly one triangle. The pyramid only culls: its tile
//! boxes hold every vertex of their cells (rounded the same way) and are
//! padded like tree nodes, so the hits are those of testing every cell.

use super::boxtree::BoxRay;
use super::triangle::{report_hit, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle};
use glam::{DVec3, Vec3};

/// Cells per leaf tile side.
const TILE_CELLS: usize = 2;

/// A terrain block's samples as the tracer and the below-ground test both
/// read them (borrowed from the scene: never copied per light).
#[derive(Clone, Copy, Debug)]
pub struct HeightGrid<'a> {
    /// World position of the block's local origin (its visible corner).
    pub origin: DVec3,
    pub chunk_size: f64,
    pub cells_x: usize,
    pub cells_z: usize,
    /// Chunk-local heights of the visible vertices, `(cells_x + 1) ×
    /// (cells_z + 1)`, row-major by z.
    pub heights: &'a [f32],
    /// One flag per cell, row-major by z.
    /// One flag per cell, row-major by z; empty: no hole.
    pub holes: &'a [bool],
    /// terrain2: the diagonal alternates with `(cx ^ cz) & 1`; terrain1:
    /// every diagonal joins (x, z)–(x+1, z+1).
    pub alternating: bool,
}

impl HeightGrid<'_> {
    /// Chunk-local height of vertex (x, z).
    #[inline]
    pub fn height(&self, x: usize, z: usize) -> f64 {
        f64::from(
            self.heights
                .get(z * (self.cells_x + 1) + x)
                .copied()
                .unwrap_or(0.0),
        )
    }

    /// World position of vertex (x, z): the one place a terrain vertex is
    /// computed, so neighbours agree bit for bit.
    #[inline]
    pub fn vertex(&self, x: usize, z: usize) -> DVec3 {
        DVec3::new(
            self.origin.x + x as f64 * self.chunk_size / self.cells_x as f64,
            self.origin.y + self.height(x, z),
            self.origin.z + z as f64 * self.chunk_size / self.cells_z as f64,
        )
    }

    pub fn is_hole(&self, cx: usize, cz: usize) -> bool {
        cx < self.cells_x && self.holes.get(cz * self.cells_x + cx) == Some(&true)
    }

    /// Whether the cell's diagonal joins (x, z+1)–(x+1, z).
    pub fn has_odd_diagonal(&self, cx: usize, cz: usize) -> bool {
        self.alternating && (cx ^ cz) & 1 == 1
    }

    /// The cell's two triangles in world space, split along its diagonal
    /// and wound so the geometric normal points up (+y): the engine's
    /// vertex orders.
    pub fn cell_triangles(&self, cx: usize, cz: usize) -> [[DVec3; 3]; 2] {
        let bottom_left = self.vertex(cx, cz);
        let bottom_right = self.vertex(cx + 1, cz);
        let top_left = self.vertex(cx, cz + 1);
        let top_right = self.vertex(cx + 1, cz + 1);
        if self.has_odd_diagonal(cx, cz) {
            [
                [bottom_left, top_left, bottom_right],
                [top_left, top_right, bottom_right],
            ]
        } else {
            [
                [bottom_left, top_left, top_right],
                [top_right, bottom_right, bottom_left],
            ]
        }
    }

    /// Cell (cx, cz)'s two triangles in the light-relative frame, each with
    /// its hit index (2 × cell + 0 or 1); `None` for a hole.
    #[inline]
    pub(crate) fn cell_trace_triangles(
        &self,
        cell: (usize, usize),
        reference: DVec3,
        caster: u32,
    ) -> Option<[(TraceTriangle, u32); 2]> {
        let (cx, cz) = cell;
        if self.is_hole(cx, cz) {
            return None;
        }
        let [a, b] = self.cell_triangles(cx, cz);
        let first = ((cz * self.cells_x + cx) * 2) as u32;
        let traced = |triangle: [DVec3; 3]| TraceTriangle {
            vertices: triangle.map(|p| (p - reference).as_vec3()),
            caster,
        };
        Some([(traced(a), first), (traced(b), first + 1)])
    }

    /// Calls `on_hit` for each of cell (cx, cz)'s triangles the ray crosses
    /// within `[t_min, t_max]` (a hole: none); returns the new t_max.
    #[inline]
    fn cell_hits(
        &self,
        cell: (usize, usize),
        reference: DVec3,
        prepared: &PreparedRay,
        caster: u32,
        t_max: f32,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        let mut t_max = t_max;
        for (tri, index) in self
            .cell_trace_triangles(cell, reference, caster)
            .into_iter()
            .flatten()
        {
            t_max = report_hit(prepared, &tri, index, t_max, on_hit);
        }
        t_max
    }

    /// The oracle: every cell of the block, no pyramid.
    pub(crate) fn brute_force_hits(
        &self,
        reference: DVec3,
        ray: &TraceRay,
        caster: u32,
        t_max: f32,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        let prepared = PreparedRay::new(ray);
        let mut t_max = t_max;
        if !prepared.is_valid() {
            return t_max;
        }
        for cz in 0..self.cells_z {
            for cx in 0..self.cells_x {
                t_max = self.cell_hits((cx, cz), reference, &prepared, caster, t_max, on_hit);
            }
        }
        t_max
    }
}

/// One step of [`HeightField::walk`]: a tile's box, or a cell of a leaf
/// tile (column, row) and its box.
pub(crate) enum Step {
    Tile(Vec3, Vec3),
    Cell((usize, usize), Vec3, Vec3),
}

/// The min/max pyramid of one block: built once per bake, shared by every
/// light. Level 0 has one entry per leaf tile of a square of `side` ×
/// `side` tiles (a power of two covering the block); each level above
/// halves the side. Heights are chunk-local; tiles outside the block are
/// empty (min > max).
///
/// A range is stored as two u16 steps of `(high − low) / 65535` above the
/// block's lowest height, rounded outward ([`Quantizer`]): 4 bytes a tile
/// instead of 8, the pyramid being a third of a big world's terrain
/// memory. The walk's boxes are as conservative as with exact ranges (a
/// box only grows), slightly looser.
#[derive(Clone, Debug, Default)]
pub struct HeightField {
    side: usize,
    /// Per level, its first entry in `ranges`.
    level_start: Vec<usize>,
    ranges: Vec<[u16; 2]>,
    quantizer: Quantizer,
    /// The block's exact lowest and highest chunk-local heights.
    low: f32,
    high: f32,
}

/// Chunk-local heights as u16 steps above `low`.
#[derive(Clone, Copy, Debug, Default)]
struct Quantizer {
    low: f64,
    step: f64,
}

/// The stored range of a tile outside the block (low > high).
const EMPTY: [u16; 2] = [u16::MAX, 0];

impl Quantizer {
    fn new(low: f32, high: f32) -> Quantizer {
        let (low, high) = (f64::from(low), f64::from(high));
        let step = if high > low {
            (high - low) / f64::from(u16::MAX)
        } else {
            1.0
        };
        Quantizer { low, step }
    }

    fn height(&self, q: u16) -> f64 {
        self.low + f64::from(q) * self.step
    }

    /// Steps whose heights hold `[lo, hi]` (heights of this block).
    fn range(&self, lo: f32, hi: f32) -> [u16; 2] {
        if lo > hi {
            return EMPTY;
        }
        let (lo, hi) = (f64::from(lo), f64::from(hi));
        let max = f64::from(u16::MAX);
        let mut q_lo = ((lo - self.low) / self.step).floor().clamp(0.0, max) as u16;
        let mut q_hi = ((hi - self.low) / self.step).ceil().clamp(0.0, max) as u16;
        // The division rounds: step once more outward where it rounded in.
        if self.height(q_lo) > lo {
            q_lo = q_lo.saturating_sub(1);
        }
        if self.height(q_hi) < hi {
            q_hi = q_hi.saturating_add(1);
        }
        [q_lo, q_hi]
    }

    /// The heights a stored range stands for (low > high: empty).
    fn heights(&self, [q_lo, q_hi]: [u16; 2]) -> (f64, f64) {
        if q_lo > q_hi {
            return (f64::INFINITY, f64::NEG_INFINITY);
        }
        (self.height(q_lo), self.height(q_hi))
    }
}

impl HeightField {
    pub fn build(grid: &HeightGrid) -> HeightField {
        let tiles_x = grid.cells_x.div_ceil(TILE_CELLS);
        let tiles_z = grid.cells_z.div_ceil(TILE_CELLS);
        let side = tiles_x.max(tiles_z).max(1).next_power_of_two();
        // Exactly the pyramid's entries (side² (1 + 1/4 + …)): growing by
        // pushes would double the allocation, a third of a big world's
        // terrain memory.
        let entries = (4 * side * side - 1) / 3;
        let (mut low, mut high) = (f32::INFINITY, f32::NEG_INFINITY);
        for &h in grid.heights {
            (low, high) = (low.min(h), high.max(h));
        }
        let quantizer = Quantizer::new(low, high);
        let mut ranges = Vec::with_capacity(entries);
        ranges.resize(side * side, EMPTY);
        for tz in 0..tiles_z {
            for tx in 0..tiles_x {
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                let x_end = ((tx + 1) * TILE_CELLS).min(grid.cells_x);
                let z_end = ((tz + 1) * TILE_CELLS).min(grid.cells_z);
                for z in tz * TILE_CELLS..=z_end {
                    for x in tx * TILE_CELLS..=x_end {
                        let h = grid.height(x, z) as f32;
                        lo = lo.min(h);
                        hi = hi.max(h);
                    }
                }
                ranges[tz * side + tx] = quantizer.range(lo, hi);
            }
        }
        let mut level_start = vec![0];
        let mut n = side;
        while n > 1 {
            let below = *level_start.last().unwrap();
            let start = ranges.len();
            let half = n / 2;
            for j in 0..half {
                for i in 0..half {
                    let mut range = EMPTY;
                    for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let [lo, hi] = ranges[below + (2 * j + dj) * n + 2 * i + di];
                        range = [range[0].min(lo), range[1].max(hi)];
                    }
                    ranges.push(range);
                }
            }
            level_start.push(start);
            n = half;
        }
        HeightField {
            side,
            level_start,
            ranges,
            quantizer,
            low,
            high,
        }
    }

    /// Lowest and highest chunk-local height of the block (holes included).
    pub fn height_range(&self) -> (f32, f32) {
        if self.low > self.high {
            return (0.0, 0.0);
        }
        (self.low, self.high)
    }

    pub fn heap_bytes(&self) -> usize {
        self.ranges.len() * std::mem::size_of::<[u16; 2]>() + self.level_start.len() * 8
    }

    /// Every hit of the ray on the block's surface within `[t_min, t_max]`,
    /// as [`HeightGrid::brute_force_hits`] finds them, visiting only the
    /// tiles (and, in a leaf tile, the cells) whose padded box the ray
    /// touches, nearer tiles first. `boxes` is the top level's box test of
    /// this ray: its padding (hundreds of ulps of the whole world's
    /// magnitude) covers the rounding of tile corners computed here.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn hits(
        &self,
        grid: &HeightGrid,
        reference: DVec3,
        boxes: &BoxRay,
        ray: &TraceRay,
        caster: u32,
        t_max: f32,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        let prepared = PreparedRay::new(ray);
        let mut t_max = t_max;
        if !prepared.is_valid() {
            return t_max;
        }
        self.walk(grid, reference, ray.direction, |step| match step {
            Step::Tile(min, max) => boxes.touches(min, max, ray.t_min, boxes.node_t_max(t_max)),
            Step::Cell(cell, min, max) => {
                if boxes.touches(min, max, ray.t_min, boxes.node_t_max(t_max)) {
                    t_max = grid.cell_hits(cell, reference, &prepared, caster, t_max, on_hit);
                }
                t_max >= ray.t_min
            }
        });
        t_max
    }

    /// The pyramid walk shared by the single-ray and the packet traversal:
    /// `step` hears of each non-empty tile's box (true: look inside) and,
    /// in a leaf tile, of each cell and its box (false: stop), nearer tiles
    /// first for rays along `direction`. Boxes are light-relative and hold
    /// every vertex of their cells up to a rounding or two, which the
    /// callers' padding covers.
    pub(crate) fn walk(
        &self,
        grid: &HeightGrid,
        reference: DVec3,
        direction: Vec3,
        mut step: impl FnMut(Step) -> bool,
    ) {
        if self.ranges.is_empty() {
            return;
        }
        // Light-relative corners, from the block's offset (f64): within a
        // rounding or two of the vertices' own, far inside the padding.
        let offset = grid.origin - reference;
        let step_x = grid.chunk_size / grid.cells_x as f64;
        let step_z = grid.chunk_size / grid.cells_z as f64;
        let x_at = |cx: usize| (offset.x + cx as f64 * step_x) as f32;
        let z_at = |cz: usize| (offset.z + cz as f64 * step_z) as f32;
        let y_at = |h: f64| (offset.y + h) as f32;
        let quantizer = self.quantizer;
        let flip_x = usize::from(direction.x >= 0.0);
        let flip_z = usize::from(direction.z >= 0.0);
        let top = self.level_start.len() - 1;
        // Depth-first with at most 3 siblings waiting per level; entries
        // pack (level, i, j) into 6 + 29 + 29 bits (a side of at most 2^29
        // tiles, far beyond any block that fits in memory).
        let pack = |level: usize, i: usize, j: usize| {
            ((level as u64) << 58) | ((i as u64) << 29) | j as u64
        };
        let mut stack = [0u64; 3 * 32 + 1];
        let mut len = 1;
        stack[0] = pack(top, 0, 0);
        while len > 0 {
            len -= 1;
            let entry = stack[len];
            let mask = (1u64 << 29) - 1;
            let (level, i, j) = (
                (entry >> 58) as usize,
                ((entry >> 29) & mask) as usize,
                (entry & mask) as usize,
            );
            let stored = self.ranges[self.level_start[level] + j * (self.side >> level) + i];
            let (lo, hi) = quantizer.heights(stored);
            if lo > hi {
                continue;
            }
            let span = TILE_CELLS << level;
            let (cx0, cz0) = (i * span, j * span);
            let cx1 = (cx0 + span).min(grid.cells_x);
            let cz1 = (cz0 + span).min(grid.cells_z);
            let min = Vec3::new(x_at(cx0), y_at(lo), z_at(cz0));
            let max = Vec3::new(x_at(cx1), y_at(hi), z_at(cz1));
            if !step(Step::Tile(min, max)) {
                continue;
            }
            if level > 0 {
                // Far children first on the stack, so the nearer pop first
                // and shrink t_max before the farther are tested.
                for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (ci, cj) = (2 * i + (di ^ flip_x), 2 * j + (dj ^ flip_z));
                    stack[len] = pack(level - 1, ci, cj);
                    len += 1;
                }
                continue;
            }
            for cz in cz0..cz1 {
                for cx in cx0..cx1 {
                    let corners = [(cx, cz), (cx + 1, cz), (cx, cz + 1), (cx + 1, cz + 1)];
                    let (lo, hi) =
                        corners
                            .iter()
                            .fold((f64::INFINITY, f64::NEG_INFINITY), |r, &(x, z)| {
                                let h = grid.height(x, z);
                                (r.0.min(h), r.1.max(h))
                            });
                    let min = Vec3::new(x_at(cx), y_at(lo), z_at(cz));
                    let max = Vec3::new(x_at(cx + 1), y_at(hi), z_at(cz + 1));
                    if !step(Step::Cell((cx, cz), min, max)) {
                        return;
                    }
                }
            }
        }
    }
}
