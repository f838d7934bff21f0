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

use super::boxtree::{BoxRay, Span};
use super::triangle::{report_hit, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle};
use glam::{DVec3, Vec3};
use std::sync::{Arc, Mutex, OnceLock};

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
    pub heights: Heights<'a>,
    /// One flag per cell, row-major by z; empty: no hole.
    pub holes: &'a [bool],
    /// terrain2: the diagonal alternates with `(cx ^ cz) & 1`; terrain1:
    /// every diagonal joins (x, z)–(x+1, z+1).
    pub alternating: bool,
    /// The lowest and highest of `heights` ([`extremes_of`]), known to the
    /// block that holds them, so a block's range costs no pass over its
    /// samples.
    pub extremes: (f32, f32),
}

/// A block's samples: held, or decoded by the first reader. A re-bake
/// with a cache traces near a few of a world's blocks; the others are
/// never decoded, their height ranges known before.
#[derive(Clone, Copy, Debug)]
pub enum Heights<'a> {
    Held(&'a [f32]),
    Deferred(&'a DeferredHeights),
}

impl<'a> Heights<'a> {
    /// The samples, decoded now if no reader has yet.
    #[inline]
    pub fn get(self) -> &'a [f32] {
        match self {
            Heights::Held(heights) => heights,
            Heights::Deferred(deferred) => deferred.get(),
        }
    }

    /// The samples if held or decoded already.
    pub fn at_hand(self) -> Option<&'a [f32]> {
        match self {
            Heights::Held(heights) => Some(heights),
            Heights::Deferred(deferred) => deferred.decoded.get().map(Vec::as_slice),
        }
    }
}

/// What makes a block's samples when they are first read.
pub type DecodeHeights = Arc<dyn Fn() -> Vec<f32> + Send + Sync>;

/// Samples decoded once, by whichever thread reads them first; the
/// decoder (and what it holds, the encoded bytes) is dropped then.
pub struct DeferredHeights {
    decoded: OnceLock<Vec<f32>>,
    decode: Mutex<Option<DecodeHeights>>,
}

impl DeferredHeights {
    pub fn new(decode: DecodeHeights) -> DeferredHeights {
        DeferredHeights {
            decoded: OnceLock::new(),
            decode: Mutex::new(Some(decode)),
        }
    }

    pub fn get(&self) -> &[f32] {
        self.decoded.get_or_init(|| {
            let decode = self.decode.lock().unwrap_or_else(|e| e.into_inner()).take();
            decode.map_or_else(Vec::new, |decode| decode())
        })
    }
}

impl Clone for DeferredHeights {
    fn clone(&self) -> DeferredHeights {
        let decode = self
            .decode
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        DeferredHeights {
            decoded: self.decoded.clone(),
            decode: Mutex::new(decode),
        }
    }
}

impl std::fmt::Debug for DeferredHeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.decoded.get() {
            Some(heights) => write!(f, "DeferredHeights({} decoded)", heights.len()),
            None => write!(f, "DeferredHeights(not decoded)"),
        }
    }
}

impl HeightGrid<'_> {
    /// Chunk-local height of vertex (x, z).
    #[inline]
    pub fn height(&self, x: usize, z: usize) -> f64 {
        f64::from(
            self.heights
                .get()
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

    /// The light-relative triangle a hit of this block reports as
    /// `index` (2 × cell + 0 or 1); `None` for a hole or past the block.
    pub(crate) fn hit_triangle(
        &self,
        index: u32,
        reference: DVec3,
        caster: u32,
    ) -> Option<TraceTriangle> {
        let cell = index as usize / 2;
        let (cx, cz) = (cell % self.cells_x.max(1), cell / self.cells_x.max(1));
        if cz >= self.cells_z {
            return None;
        }
        let pair = self.cell_trace_triangles((cx, cz), reference, caster)?;
        Some(pair[index as usize % 2].0)
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
/// instead of 8, since the pyramids are a large part of a big world's
/// terrain memory. The walk's boxes are as conservative as with exact ranges (a
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

/// The lowest and highest of `heights`: (∞, −∞) for none.
pub fn extremes_of(heights: &[f32]) -> (f32, f32) {
    let (mut low, mut high) = (f32::INFINITY, f32::NEG_INFINITY);
    for &h in heights {
        (low, high) = (low.min(h), high.max(h));
    }
    (low, high)
}

/// The lowest and highest of a block's samples, as its grid carries them
/// (checked against samples at hand, never decoding them for it).
fn extremes(grid: &HeightGrid) -> (f32, f32) {
    if let Some(heights) = grid.heights.at_hand() {
        debug_assert_eq!(grid.extremes, extremes_of(heights));
    }
    grid.extremes
}

/// A block's height range from its extremes: (0, 0) for no sample.
fn range_of(low: f32, high: f32) -> (f32, f32) {
    if low > high {
        return (0.0, 0.0);
    }
    (low, high)
}

impl HeightField {
    pub fn build(grid: &HeightGrid) -> HeightField {
        let tiles_x = grid.cells_x.div_ceil(TILE_CELLS);
        let tiles_z = grid.cells_z.div_ceil(TILE_CELLS);
        let side = tiles_x.max(tiles_z).max(1).next_power_of_two();
        // Exactly the pyramid's entries (side² (1 + 1/4 + …)): growing by
        // pushes could double the allocation of a large part of a big
        // world's terrain memory.
        let entries = (4 * side * side - 1) / 3;
        let (low, high) = extremes(grid);
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
        range_of(self.low, self.high)
    }

    /// [`HeightField::height_range`] of the field `grid` would build,
    /// without building it.
    pub fn height_range_of(grid: &HeightGrid) -> (f32, f32) {
        let (low, high) = extremes(grid);
        range_of(low, high)
    }

    pub fn heap_bytes(&self) -> usize {
        self.ranges.len() * std::mem::size_of::<[u16; 2]>() + self.level_start.len() * 8
    }

    /// [`HeightField::heap_bytes`] of the field `grid` would build.
    pub fn heap_bytes_of(grid: &HeightGrid) -> usize {
        let tiles_x = grid.cells_x.div_ceil(TILE_CELLS);
        let tiles_z = grid.cells_z.div_ceil(TILE_CELLS);
        let side = tiles_x.max(tiles_z).max(1).next_power_of_two();
        let levels = side.trailing_zeros() as usize + 1;
        (4 * side * side - 1) / 3 * std::mem::size_of::<[u16; 2]>() + levels * 8
    }

    /// Every hit of the ray on the block's surface within `[t_min, t_max]`,
    /// as [`HeightGrid::brute_force_hits`] finds them, visiting only cells
    /// whose padded box the ray touches: along the ray's path row by row
    /// ([`Self::row_walk`]) when that path is short, else through the
    /// pyramid, nearer tiles first. `boxes` is the top level's box test of
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
        if !prepared.is_valid() {
            return t_max;
        }
        let frame = CellFrame::new(grid, reference);
        let walked = self.row_walk(grid, &frame, boxes, ray, t_max, |cell, t_max| {
            let (min, max) = frame.cell_box(grid, cell);
            if boxes.touches(min, max, ray.t_min, boxes.node_t_max(t_max)) {
                return grid.cell_hits(cell, reference, &prepared, caster, t_max, on_hit);
            }
            t_max
        });
        if let Some(t_max) = walked {
            return t_max;
        }
        let mut t_max = t_max;
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

    /// The cells along a single ray's path through the block, near first:
    /// the part of the ray inside the block's padded box, cut into the rows
    /// of cells it crosses, and in each row the cells its path (padded by
    /// the box padding) crosses. Every cell whose padded box the ray
    /// touches is among them, so `visit(cell, t_max)` (which tests the cell
    /// and returns the new t_max) sees every cell the pyramid would let
    /// through. A steep ray (any light from above) crosses a handful of
    /// cells of a block this way, where the pyramid tests a box per level
    /// and four per tile. `None` (nothing visited): the path crosses more
    /// than [`MAX_ROW_WALK_CELLS`] rows and columns (a grazing ray, where
    /// the pyramid skips empty space), or the span is unbounded (NaN).
    fn row_walk(
        &self,
        grid: &HeightGrid,
        frame: &CellFrame,
        boxes: &BoxRay,
        ray: &TraceRay,
        t_max: f32,
        mut visit: impl FnMut((usize, usize), f32) -> f32,
    ) -> Option<f32> {
        if self.low > self.high {
            return Some(t_max);
        }
        let (min, max) = frame.block_box(grid, self.low, self.high);
        let (t0, t1) = match boxes.span(min, max, ray.t_min, boxes.node_t_max(t_max)) {
            Span::Miss => return Some(t_max),
            Span::Unbounded => return None,
            Span::Within(t0, t1) => (f64::from(t0), f64::from(t1)),
        };
        let origin = ray.origin.as_dvec3();
        let direction = ray.direction.as_dvec3();
        // Beyond the padding the boxes are grown by, twice over: the
        // positions below are computed in f64 from the f32 ray.
        let pad = 2.0 * f64::from(boxes.pad());
        let along = |o: f64, d: f64, t0: f64, t1: f64| {
            let (a, b) = (o + d * t0, o + d * t1);
            (a.min(b) - pad, a.max(b) + pad)
        };
        let columns = frame.cells_x(grid, along(origin.x, direction.x, t0, t1));
        let rows = frame.cells_z(grid, along(origin.z, direction.z, t0, t1));
        if columns.len() + rows.len() > MAX_ROW_WALK_CELLS {
            return None;
        }
        let mut t_max = t_max;
        for cz in near_first(rows, direction.z) {
            let (mut ta, mut tb) = (t0, t1);
            if direction.z != 0.0 {
                let (za, zb) = (
                    f64::from(frame.z_at(cz)) - pad,
                    f64::from(frame.z_at(cz + 1)) + pad,
                );
                let (a, b) = ((za - origin.z) / direction.z, (zb - origin.z) / direction.z);
                (ta, tb) = (ta.max(a.min(b)), tb.min(a.max(b)));
            }
            if ta > f64::from(boxes.node_t_max(t_max)) {
                break;
            }
            if ta > tb {
                continue;
            }
            let span = frame.cells_x(grid, along(origin.x, direction.x, ta, tb));
            for cx in near_first(
                span.start.max(columns.start)..span.end.min(columns.end),
                direction.x,
            ) {
                t_max = visit((cx, cz), t_max);
                if t_max < ray.t_min {
                    return Some(t_max);
                }
            }
        }
        Some(t_max)
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
        let frame = CellFrame::new(grid, reference);
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
            let min = Vec3::new(frame.x_at(cx0), frame.y_at(lo), frame.z_at(cz0));
            let max = Vec3::new(frame.x_at(cx1), frame.y_at(hi), frame.z_at(cz1));
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
                    let (min, max) = frame.cell_box(grid, (cx, cz));
                    if !step(Step::Cell((cx, cz), min, max)) {
                        return;
                    }
                }
            }
        }
    }
}

/// Single rays walk a block's cells along their path when it crosses at
/// most this many rows plus columns (else the pyramid).
const MAX_ROW_WALK_CELLS: usize = 24;

/// The `range` of cell indices in the order a ray with this direction
/// component meets them.
fn near_first(range: std::ops::Range<usize>, direction: f64) -> impl Iterator<Item = usize> {
    let backwards = direction < 0.0;
    let (forward, reverse) = if backwards {
        (None, Some(range.rev()))
    } else {
        (Some(range), None)
    };
    forward
        .into_iter()
        .flatten()
        .chain(reverse.into_iter().flatten())
}

/// A block's cells in the light-relative frame: corners from the block's
/// offset (f64), within a rounding or two of the vertices' own
/// ([`HeightGrid::vertex`]), far inside the padding of the box tests.
struct CellFrame {
    offset: DVec3,
    step_x: f64,
    step_z: f64,
}

impl CellFrame {
    fn new(grid: &HeightGrid, reference: DVec3) -> CellFrame {
        CellFrame {
            offset: grid.origin - reference,
            step_x: grid.chunk_size / grid.cells_x as f64,
            step_z: grid.chunk_size / grid.cells_z as f64,
        }
    }

    fn x_at(&self, cx: usize) -> f32 {
        (self.offset.x + cx as f64 * self.step_x) as f32
    }

    fn z_at(&self, cz: usize) -> f32 {
        (self.offset.z + cz as f64 * self.step_z) as f32
    }

    fn y_at(&self, h: f64) -> f32 {
        (self.offset.y + h) as f32
    }

    /// The box of the whole block between chunk-local heights `low` and
    /// `high`.
    fn block_box(&self, grid: &HeightGrid, low: f32, high: f32) -> (Vec3, Vec3) {
        (
            Vec3::new(self.x_at(0), self.y_at(f64::from(low)), self.z_at(0)),
            Vec3::new(
                self.x_at(grid.cells_x),
                self.y_at(f64::from(high)),
                self.z_at(grid.cells_z),
            ),
        )
    }

    /// Cell (cx, cz)'s box: its four corners' heights.
    #[inline]
    fn cell_box(&self, grid: &HeightGrid, (cx, cz): (usize, usize)) -> (Vec3, Vec3) {
        let corners = [(cx, cz), (cx + 1, cz), (cx, cz + 1), (cx + 1, cz + 1)];
        let (lo, hi) = corners
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |r, &(x, z)| {
                let h = grid.height(x, z);
                (r.0.min(h), r.1.max(h))
            });
        (
            Vec3::new(self.x_at(cx), self.y_at(lo), self.z_at(cz)),
            Vec3::new(self.x_at(cx + 1), self.y_at(hi), self.z_at(cz + 1)),
        )
    }

    /// The columns of cells whose x range meets `[lo, hi]` (light-relative
    /// metres), clipped to the block.
    fn cells_x(&self, grid: &HeightGrid, (lo, hi): (f64, f64)) -> std::ops::Range<usize> {
        cell_range(
            lo - self.offset.x,
            hi - self.offset.x,
            self.step_x,
            grid.cells_x,
        )
    }

    /// The rows of cells whose z range meets `[lo, hi]`.
    fn cells_z(&self, grid: &HeightGrid, (lo, hi): (f64, f64)) -> std::ops::Range<usize> {
        cell_range(
            lo - self.offset.z,
            hi - self.offset.z,
            self.step_z,
            grid.cells_z,
        )
    }
}

/// Cells `i` of size `step` (cell i spans `[i·step, (i+1)·step]`) that
/// meet `[lo, hi]`, clipped to `0..cells`; empty when `[lo, hi]` is.
fn cell_range(lo: f64, hi: f64, step: f64, cells: usize) -> std::ops::Range<usize> {
    // NaN bounds meet nothing (the caller's span was finite).
    if lo.partial_cmp(&hi).is_none_or(|o| o.is_gt()) {
        return 0..0;
    }
    let last = cells as f64 - 1.0;
    // A coordinate exactly on a line between cells meets both.
    let first = (lo / step).ceil() - 1.0;
    let end = (hi / step).floor();
    if end < 0.0 || first > last {
        return 0..0;
    }
    first.clamp(0.0, last) as usize..end.clamp(0.0, last) as usize + 1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Hits as comparable tuples, sorted.
    fn sorted(hits: Vec<Hit>) -> Vec<(u32, u32, bool)> {
        let mut out: Vec<_> = hits
            .iter()
            .map(|h| (h.t.to_bits(), h.triangle, h.back_facing))
            .collect();
        out.sort();
        out
    }

    /// A bumpy 32 × 32-cell block of 100 m (cells of 3.125 m) with holes,
    /// far from the origin.
    fn block() -> (Vec<f32>, Vec<bool>, DVec3) {
        let cells = 32;
        let mut heights = Vec::new();
        for z in 0..=cells {
            for x in 0..=cells {
                let (x, z) = (x as f64, z as f64);
                heights.push(((x * 0.9).sin() * 6.0 + (z * 0.45).cos() * 9.0 + x * 0.3) as f32);
            }
        }
        let mut holes = vec![false; cells * cells];
        holes[5 * cells + 7] = true;
        holes[20 * cells + 31] = true;
        (heights, holes, DVec3::new(1.0e5, 12.0, -3.0e4))
    }

    /// What a top level and the memory model read of a block without its
    /// pyramid (its height range, the pyramid's bytes) is what the built
    /// pyramid says, for blocks of every size the tiles cut unevenly, flat
    /// ones and ones without a sample.
    #[test]
    fn a_pyramids_range_and_bytes_are_known_before_it_is_built() {
        let (bumpy, holes, origin) = block();
        let flat = vec![7.5f32; 33 * 33];
        for (cells, heights) in [(32, &bumpy[..]), (32, &flat[..]), (0, &[][..])] {
            for (cells_x, cells_z) in [(cells, cells), (cells, cells / 3), (cells / 5, cells)] {
                let samples = (cells_x + 1) * (cells_z + 1);
                let grid = HeightGrid {
                    origin,
                    chunk_size: 100.0,
                    cells_x,
                    cells_z,
                    heights: Heights::Held(&heights[..samples.min(heights.len())]),
                    holes: &holes,
                    alternating: true,
                    extremes: extremes_of(&heights[..samples.min(heights.len())]),
                };
                let field = HeightField::build(&grid);
                let what = format!("{cells_x} × {cells_z} cells");
                assert_eq!(
                    HeightField::height_range_of(&grid),
                    field.height_range(),
                    "{what}"
                );
                assert_eq!(
                    HeightField::heap_bytes_of(&grid),
                    field.heap_bytes(),
                    "{what}"
                );
            }
        }
    }

    /// Single rays along the cells' path ([`HeightField::row_walk`]) and
    /// through the pyramid find exactly the hits of testing every cell, for
    /// rays from every kind of direction — straight down, slanted, along an
    /// axis, grazing — aimed at random points, cell corners, edges and
    /// diagonals; and both ways of walking are used.
    #[test]
    fn single_rays_find_every_cell_hit_whichever_walk_they_take() {
        let (heights, holes, origin) = block();
        let grid = HeightGrid {
            origin,
            chunk_size: 100.0,
            cells_x: 32,
            cells_z: 32,
            heights: Heights::Held(&heights),
            holes: &holes,
            alternating: true,
            extremes: extremes_of(&heights),
        };
        let field = HeightField::build(&grid);
        let reference = origin + DVec3::new(37.0, 0.0, 51.0);
        let frame = CellFrame::new(&grid, reference);
        let mut rng = Rng::new(11);
        let (mut along_rows, mut through_pyramid, mut rays) = (0, 0, 0);
        for i in 0..6000 {
            let direction = match i % 6 {
                0 => Vec3::NEG_Y,
                1 => Vec3::new(0.3, -1.0, -0.2),
                2 => Vec3::new(1.0, -0.05, 0.0),
                3 => Vec3::new(0.0, -0.4, -1.0),
                4 => Vec3::new(-1.0, -0.02, 0.7),
                _ => rng.unit_vector().as_vec3() * Vec3::new(1.0, -1.0, 1.0).abs(),
            }
            .normalize();
            // A target on the surface: a random point, or a lattice point,
            // edge midpoint or cell centre (diagonals) exactly.
            let (cx, cz) = ((rng.unit() * 32.0) as usize, (rng.unit() * 32.0) as usize);
            let (fx, fz) = match i % 4 {
                0 => (rng.unit(), rng.unit()),
                1 => (0.0, 0.0),
                2 => (0.5, 0.0),
                _ => (0.5, 0.5),
            };
            let x = grid.origin.x + (cx as f64 + fx) * 100.0 / 32.0;
            let z = grid.origin.z + (cz as f64 + fz) * 100.0 / 32.0;
            let y = grid.origin.y + f64::from(heights[cz * 33 + cx]);
            let target = (DVec3::new(x, y, z) - reference).as_vec3();
            let ray = TraceRay {
                origin: target - direction * 150.0,
                direction,
                t_min: 0.0,
                t_max: 400.0,
            };
            let prepared = PreparedRay::new(&ray);
            let boxes = BoxRay::new(&ray, 2.0e5);
            let mut walked = Vec::new();
            field.hits(&grid, reference, &boxes, &ray, 0, ray.t_max, &mut |h| {
                walked.push(h);
                f32::INFINITY
            });
            let mut every = Vec::new();
            grid.brute_force_hits(reference, &ray, 0, ray.t_max, &mut |h| {
                every.push(h);
                f32::INFINITY
            });
            assert_eq!(sorted(walked), sorted(every), "ray {i}: {ray:?}");
            let took_rows = field.row_walk(&grid, &frame, &boxes, &ray, ray.t_max, |_, t| t);
            match took_rows {
                Some(_) => along_rows += 1,
                None => through_pyramid += 1,
            }
            rays += usize::from(prepared.is_valid());
        }
        assert_eq!(rays, 6000);
        assert!(
            along_rows > 1000 && through_pyramid > 1000,
            "{along_rows} {through_pyramid}"
        );
    }
}
