//! The below-ground test of SPEC §4: the terrain height H(x, z) over a world
//! point, from whichever block covers it.

use crate::scene::Scene;

pub struct Ground<'a> {
    scene: &'a Scene,
    /// The outdoor grid cells that hold a terrain block, as a dense table
    /// (every hit of every ray looks its point up here: hashing the cell
    /// was a tenth of a fine sun's trace).
    table: BlockTable,
    chunk_size: f64,
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

/// A dense table may hold this many entries per block (plus a fixed
/// allowance) before the sparse one is used instead.
const DENSE_ENTRIES_PER_BLOCK: i64 = 16;

impl BlockTable {
    fn new(cells: &[((i32, i32), usize)]) -> BlockTable {
        let xs = cells.iter().map(|&((x, _), _)| i64::from(x));
        let zs = cells.iter().map(|&((_, z), _)| i64::from(z));
        let (min_x, max_x) = (xs.clone().min().unwrap_or(0), xs.max().unwrap_or(-1));
        let (min_z, max_z) = (zs.clone().min().unwrap_or(0), zs.max().unwrap_or(-1));
        let (width, depth) = ((max_x - min_x + 1).max(0), (max_z - min_z + 1).max(0));
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
        (!cells.is_empty()).then(|| Ground {
            scene,
            table: BlockTable::new(&cells),
            chunk_size: scene.settings.chunk_size,
        })
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
