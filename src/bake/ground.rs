//! The below-ground test of docs/contract.md §4: the terrain height H(x, z) over a world
//! point, from whichever block covers it. Every non-terrain hit of every ray
//! asks it, so most answers come from a coarse ceiling of the terrain
//! before the exact height is looked up.

use crate::scene::terrain::TerrainBlock;
use crate::scene::Scene;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering};

pub struct Ground<'a> {
    scene: &'a Scene,
    /// The outdoor grid cells that hold a terrain block, as a dense table
    /// (every hit of every ray looks its point up here, so hashing the
    /// cell would cost a sizeable part of the trace).
    table: BlockTable,
    chunk_size: f64,
    /// Upper bounds of H over squares of the world, so that most hits
    /// (well above the ground) skip the exact height; `None` for a sparse
    /// grid of blocks.
    ceilings: Option<Ceilings>,
}

/// Squares of the world this many to a chunk side carry a ceiling: fine
/// enough that nearly every hit the below-ground test sees lies above its
/// square's ceiling, where a chunk's highest sample would let far fewer
/// skip the exact height.
const CEILING_SQUARES_PER_CHUNK: i64 = 8;

/// A height the exact test's rounding cannot reach past a ceiling (its
/// interpolation stays within a cell's corner heights up to a few ulps of
/// f64): one millimetre.
const CEILING_SLACK: f64 = 1e-3;

/// A dense grid of squares over the blocks' grid rectangle (one square
/// beyond it on every side), each holding an upper bound of H(x, z) at
/// every point of the square that any block covers: the highest corner
/// sample of every cell of every block that comes within `margin` of the
/// square (holes included), rounded up to f32; −∞ where no cell comes near.
/// A point's square is found by a product with the inverse side that may
/// err by an ulp or two near an edge: the margin (a thousandth of a
/// square) covers that.
///
/// A square's bound is found when a point first asks for it, from the
/// blocks listed for it: a re-bake with a cache asks over a few blocks,
/// whose samples alone it decodes.
struct Ceilings {
    /// World coordinates of square (0, 0)'s lower corner, the side.
    min_x: f64,
    min_z: f64,
    side: f64,
    per_side: f64,
    width: usize,
    depth: usize,
    /// Row-major by z: the bound's f32 bits, [`UNSET`] until found.
    heights: Vec<AtomicU32>,
    /// The blocks that come near square `i`: `near[starts[i]..starts[i + 1]]`.
    starts: Vec<u32>,
    near: Vec<u32>,
}

/// A square whose bound is not found yet: a NaN, which no bound is.
const UNSET: u32 = 0x7fc0_0000;

/// The squares one block comes near, inclusive: x from, x to, z from, z to.
type SquareSpan = (usize, usize, usize, usize);

impl Ceilings {
    /// `None` when the blocks' grid rectangle is mostly empty or not
    /// finite, or a block lies off its grid cell (the exact test alone
    /// then).
    fn new(scene: &Scene, cells: &[((i32, i32), usize)], chunk_size: f64) -> Option<Ceilings> {
        let (min_x, min_z, chunks_x, chunks_z) = grid_rectangle(cells)?;
        if chunks_x * chunks_z > 4 * cells.len() as i64 + 64 {
            return None;
        }
        let n = CEILING_SQUARES_PER_CHUNK;
        let side = chunk_size / n as f64;
        let (width, depth) = ((chunks_x + 2) * n, (chunks_z + 2) * n);
        let mut ceilings = Ceilings {
            min_x: (min_x - 1) as f64 * chunk_size,
            min_z: (min_z - 1) as f64 * chunk_size,
            side,
            per_side: 1.0 / side,
            width: width as usize,
            depth: depth as usize,
            heights: Vec::new(),
            starts: Vec::new(),
            near: Vec::new(),
        };
        if !(ceilings.min_x.is_finite() && ceilings.min_z.is_finite() && side > 0.0) {
            return None;
        }
        let spans: Option<Vec<(SquareSpan, usize)>> = cells
            .par_iter()
            .map(|&(_, block)| Some((ceilings.span(&scene.terrain[block])?, block)))
            .collect();
        ceilings.list_near(&spans?);
        ceilings.heights = (0..ceilings.width * ceilings.depth)
            .map(|_| AtomicU32::new(UNSET))
            .collect();
        Some(ceilings)
    }

    /// Lists each block of `spans` under every square of its span, in
    /// block order.
    fn list_near(&mut self, spans: &[(SquareSpan, usize)]) {
        let width = self.width;
        let squares = move |&((x0, x1, z0, z1), _): &(SquareSpan, usize)| {
            (z0..=z1).flat_map(move |qz| (x0..=x1).map(move |qx| qz * width + qx))
        };
        let mut starts = vec![0u32; self.width * self.depth + 1];
        for span in spans {
            for square in squares(span) {
                starts[square + 1] += 1;
            }
        }
        for i in 1..starts.len() {
            starts[i] += starts[i - 1];
        }
        let mut filled = starts.clone();
        let mut near = vec![0u32; starts.last().copied().unwrap_or(0) as usize];
        for span in spans {
            for square in squares(span) {
                near[filled[square] as usize] = span.1 as u32;
                filled[square] += 1;
            }
        }
        (self.starts, self.near) = (starts, near);
    }

    /// The squares `block`'s cells come near; `None` when the block
    /// reaches past the grid (a block off its grid cell: never from a
    /// well-formed space).
    fn span(&self, block: &TerrainBlock) -> Option<SquareSpan> {
        let o = block.origin();
        let margin = self.side * 1e-3;
        let square = |v: f64, min: f64| ((v - min) / self.side).floor();
        let (x0, x1) = (o.x - margin, o.x + block.chunk_size() + margin);
        let (z0, z1) = (o.z - margin, o.z + block.chunk_size() + margin);
        let (qx0, qx1) = (square(x0, self.min_x), square(x1, self.min_x));
        let (qz0, qz1) = (square(z0, self.min_z), square(z1, self.min_z));
        if !(qx0 >= 0.0 && qz0 >= 0.0 && qx1 < self.width as f64 && qz1 < self.depth as f64) {
            return None;
        }
        Some((qx0 as usize, qx1 as usize, qz0 as usize, qz1 as usize))
    }

    /// The highest corner sample of `block`'s cells that come near square
    /// (qx, qz), in world height rounded up to f32; `None` when none does.
    fn high_near(&self, block: &TerrainBlock, qx: usize, qz: usize) -> Option<f32> {
        let (o, (sx, sz), (nx, nz)) = (block.origin(), block.spacing(), block.cells());
        let margin = self.side * 1e-3;
        let clamp = |v: f64, n: usize| v.clamp(0.0, n as f64 - 1.0) as usize;
        // The square grown by the margin, in the block's cells.
        let (ax, az) = (
            self.min_x + qx as f64 * self.side,
            self.min_z + qz as f64 * self.side,
        );
        let cx = |a: f64| ((a - o.x) / sx).floor();
        let cz = |a: f64| ((a - o.z) / sz).floor();
        let (cx0, cx1) = (cx(ax - margin), cx(ax + self.side + margin));
        let (cz0, cz1) = (cz(az - margin), cz(az + self.side + margin));
        if cx1 < 0.0 || cz1 < 0.0 || cx0 > (nx - 1) as f64 || cz0 > (nz - 1) as f64 {
            return None;
        }
        let (cx0, cx1) = (clamp(cx0, nx), clamp(cx1, nx));
        let (cz0, cz1) = (clamp(cz0, nz), clamp(cz1, nz));
        let mut high = f64::NEG_INFINITY;
        for z in cz0..=cz1 + 1 {
            for x in cx0..=cx1 + 1 {
                high = high.max(block.vertex_height(x, z).unwrap_or(f64::INFINITY));
            }
        }
        Some(round_up(o.y + high))
    }

    /// The ceiling over world point (x, z); `None` outside the grid.
    #[inline]
    fn at(&self, x: f64, z: f64, terrain: &[TerrainBlock]) -> Option<f32> {
        // Truncation is the floor for the non-negative values kept.
        let qx = (x - self.min_x) * self.per_side;
        let qz = (z - self.min_z) * self.per_side;
        if !(qx >= 0.0 && qz >= 0.0 && qx < self.width as f64 && qz < self.depth as f64) {
            return None;
        }
        let (qx, qz) = (qx as usize, qz as usize);
        let square = qz * self.width + qx;
        let bits = self.heights[square].load(Ordering::Relaxed);
        if bits != UNSET {
            return Some(f32::from_bits(bits));
        }
        Some(self.find(square, qx, qz, terrain))
    }

    /// Square (qx, qz)'s bound from its blocks, kept for later points
    /// (threads that find it at once find the same).
    #[cold]
    fn find(&self, square: usize, qx: usize, qz: usize, terrain: &[TerrainBlock]) -> f32 {
        let listed = self.starts[square] as usize..self.starts[square + 1] as usize;
        let bound = self.near[listed]
            .iter()
            .filter_map(|&block| self.high_near(&terrain[block as usize], qx, qz))
            .fold(f32::NEG_INFINITY, f32::max);
        self.heights[square].store(bound.to_bits(), Ordering::Relaxed);
        bound
    }
}

/// `v` as the nearest f32 not below it (+∞ for NaN or beyond f32).
fn round_up(v: f64) -> f32 {
    let f = v as f32;
    match f64::from(f) < v {
        true => f.next_up(),
        false if v.is_nan() => f32::INFINITY,
        false => f,
    }
}

/// Outdoor grid (x, z) → terrain block: a dense table over the bounding
/// rectangle of the chunks that hold blocks, or, when that rectangle is
/// mostly empty (two stray chunk names 60 000 cells apart would make it
/// billions of entries), the sorted cells searched by bisection.
enum BlockTable {
    Dense {
        min_x: i64,
        min_z: i64,
        width: i64,
        depth: i64,
        /// Row-major by z; `u32::MAX`: no block.
        blocks: Vec<u32>,
    },
    Sparse(Vec<((i64, i64), usize)>),
}

/// The rectangle of grid cells holding `cells`: (min x, min z, width,
/// depth); `None` for no cells.
fn grid_rectangle(cells: &[((i32, i32), usize)]) -> Option<(i64, i64, i64, i64)> {
    let xs = cells.iter().map(|&((x, _), _)| i64::from(x));
    let zs = cells.iter().map(|&((_, z), _)| i64::from(z));
    let (min_x, max_x) = (xs.clone().min()?, xs.max()?);
    let (min_z, max_z) = (zs.clone().min()?, zs.max()?);
    Some((min_x, min_z, max_x - min_x + 1, max_z - min_z + 1))
}

/// A dense table may hold this many entries per block (plus a fixed
/// allowance) before the sparse one is used instead.
const DENSE_ENTRIES_PER_BLOCK: i64 = 16;

impl BlockTable {
    fn new(cells: &[((i32, i32), usize)]) -> BlockTable {
        let (min_x, min_z, width, depth) = grid_rectangle(cells).unwrap_or((0, 0, 0, 0));
        if width * depth > DENSE_ENTRIES_PER_BLOCK * cells.len() as i64 + 65_536 {
            let mut sparse: Vec<((i64, i64), usize)> = cells
                .iter()
                .map(|&((x, z), block)| ((i64::from(x), i64::from(z)), block))
                .collect();
            sparse.sort_unstable();
            return BlockTable::Sparse(sparse);
        }
        let mut blocks = vec![u32::MAX; (width * depth) as usize];
        for &((x, z), block) in cells {
            let at = (i64::from(z) - min_z) * width + (i64::from(x) - min_x);
            blocks[at as usize] = block as u32;
        }
        BlockTable::Dense {
            min_x,
            min_z,
            width,
            depth,
            blocks,
        }
    }

    #[inline]
    fn get(&self, x: i64, z: i64) -> Option<usize> {
        match self {
            BlockTable::Dense {
                min_x,
                min_z,
                width,
                depth,
                blocks,
            } => {
                let (dx, dz) = (x - min_x, z - min_z);
                if !(0..*width).contains(&dx) || !(0..*depth).contains(&dz) {
                    return None;
                }
                let block = blocks[(dz * width + dx) as usize];
                (block != u32::MAX).then_some(block as usize)
            }
            BlockTable::Sparse(cells) => cells
                .binary_search_by_key(&(x, z), |&(cell, _)| cell)
                .ok()
                .map(|at| cells[at].1),
        }
    }
}

impl<'a> Ground<'a> {
    /// `None` when the scene has no terrain: no height tests at all.
    pub fn new(scene: &'a Scene) -> Option<Ground<'a>> {
        let cells: Vec<((i32, i32), usize)> = scene
            .chunks
            .iter()
            .filter_map(|chunk| Some((chunk.grid?, chunk.terrain?)))
            .collect();
        let chunk_size = scene.settings.chunk_size;
        (!cells.is_empty()).then(|| Ground {
            scene,
            table: BlockTable::new(&cells),
            chunk_size,
            ceilings: Ceilings::new(scene, &cells, chunk_size),
        })
    }

    /// docs/contract.md §4's below-ground rule for a non-terrain hit at `p`: whether
    /// it lies more than `bias` below H(x, z) (no block or a hole: not
    /// below). The same answer as asking [`Self::height`], without it for
    /// a point above its square's ceiling.
    #[inline]
    pub fn is_below(&self, p: DVec3, bias: f64) -> bool {
        if self
            .ceiling(p.x, p.z)
            .is_some_and(|c| p.y >= c + CEILING_SLACK - bias)
        {
            return false;
        }
        self.height(p.x, p.z).is_some_and(|h| p.y < h - bias)
    }

    /// An upper bound of every height [`Self::height`] can answer at
    /// (x, z), to a square of an eighth of a chunk; `None` when there is
    /// none at hand (outside the grid of ceilings, or no grid).
    #[inline]
    pub fn ceiling(&self, x: f64, z: f64) -> Option<f64> {
        self.ceilings
            .as_ref()?
            .at(x, z, &self.scene.terrain)
            .map(f64::from)
    }

    /// H(x, z): the terrain surface height above or below the point, or
    /// `None` where no block covers it or the point is in a hole.
    #[inline]
    pub fn height(&self, x: f64, z: f64) -> Option<f64> {
        let gx = (x / self.chunk_size).floor();
        let gz = (z / self.chunk_size).floor();
        if !(gx.abs() < 1e9 && gz.abs() < 1e9) {
            return None;
        }
        let (gx, gz) = (gx as i64, gz as i64);
        // A point on a chunk border may be covered by the block on either
        // side (blocks own their closed square); the one the floor picks
        // first, then its neighbours.
        [(0, 0), (-1, 0), (0, -1), (-1, -1)]
            .iter()
            .find_map(|(dx, dz)| {
                let block = self.table.get(gx + dx, gz + dz)?;
                self.scene.terrain[block].height_at(x, z)
            })
    }
}

impl Ground<'_> {
    /// Whether H(x, z) ≤ `level` everywhere over the rectangle `[x0, x1] ×
    /// [z0, z1]` (and so whether no point at or above `level` there can be
    /// below ground), judged by the samples of every cell of every block
    /// that meets it: each cell's surface lies between its corners'
    /// heights. `false` for a rectangle that is not finite or that spans
    /// more than `most_cells` cells of blocks higher than `level`.
    pub fn at_most(
        &self,
        (x0, z0): (f64, f64),
        (x1, z1): (f64, f64),
        level: f64,
        most_cells: usize,
    ) -> bool {
        if !(x0.abs() < 1e9 && z0.abs() < 1e9 && x1.abs() < 1e9 && z1.abs() < 1e9) {
            return false;
        }
        let size = self.chunk_size;
        let chunks = |a: f64, b: f64| (a / size).floor() as i64 - 1..=(b / size).floor() as i64;
        let mut cells = 0;
        for gz in chunks(z0, z1) {
            for gx in chunks(x0, x1) {
                let Some(block) = self.table.get(gx, gz) else {
                    continue;
                };
                let block = &self.scene.terrain[block];
                if block.bounds().1.y <= level {
                    continue;
                }
                let (o, (sx, sz), (nx, nz)) = (block.origin(), block.spacing(), block.cells());
                let span = |a: f64, b: f64, origin: f64, step: f64, n: usize| {
                    let first = ((a - origin) / step).floor().max(0.0);
                    let last = ((b - origin) / step).ceil().min(n as f64);
                    (first <= last).then_some((first as usize, last as usize))
                };
                let (Some((ix0, ix1)), Some((iz0, iz1))) =
                    (span(x0, x1, o.x, sx, nx), span(z0, z1, o.z, sz, nz))
                else {
                    continue;
                };
                cells += (ix1 - ix0 + 1) * (iz1 - iz0 + 1);
                if cells > most_cells {
                    return false;
                }
                for iz in iz0..=iz1 {
                    for ix in ix0..=ix1 {
                        if block.vertex_height(ix, iz).is_some_and(|h| o.y + h > level) {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_and_sparse_tables_find_the_same_blocks() {
        let near: Vec<((i32, i32), usize)> = vec![((-2, 3), 0), ((0, 0), 1), ((1, -1), 2)];
        let far: Vec<((i32, i32), usize)> = vec![((-32768, 0), 0), ((32767, 5), 1)];
        let dense = BlockTable::new(&near);
        assert!(matches!(dense, BlockTable::Dense { .. }));
        let sparse = BlockTable::new(&far);
        assert!(matches!(sparse, BlockTable::Sparse(_)));
        for (table, cells) in [(&dense, &near), (&sparse, &far)] {
            for &((x, z), block) in cells {
                let (x, z) = (i64::from(x), i64::from(z));
                assert_eq!(table.get(x, z), Some(block));
                assert_eq!(table.get(x + 1, z + 7), None);
            }
            assert_eq!(table.get(i64::MIN / 2, 0), None);
        }
    }
}
