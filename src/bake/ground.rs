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
