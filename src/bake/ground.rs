//! The below-ground test of SPEC §4: the terrain height H(x, z) over a world
//! point, from whichever block covers it.

use crate::scene::Scene;
use std::collections::HashMap;

pub struct Ground<'a> {
    scene: &'a Scene,
    /// Outdoor grid (x, z) → terrain block.
    by_grid: HashMap<(i32, i32), usize>,
    chunk_size: f64,
}

impl<'a> Ground<'a> {
    /// `None` when the scene has no terrain: no height tests at all.
    pub fn new(scene: &'a Scene) -> Option<Ground<'a>> {
        let by_grid: HashMap<(i32, i32), usize> = scene
            .chunks
            .iter()
            .filter_map(|chunk| Some((chunk.grid?, chunk.terrain?)))
            .collect();
        (!by_grid.is_empty()).then_some(Ground {
            scene,
            by_grid,
            chunk_size: scene.settings.chunk_size,
        })
    }

    /// H(x, z): the terrain surface height above or below the point, or
    /// `None` where no block covers it or the point is in a hole.
    pub fn height(&self, x: f64, z: f64) -> Option<f64> {
        let gx = (x / self.chunk_size).floor();
        let gz = (z / self.chunk_size).floor();
        if !(gx.abs() < 1e9 && gz.abs() < 1e9) {
            return None;
        }
        let (gx, gz) = (gx as i32, gz as i32);
        // A point on a chunk border may be covered by the block on either
        // side (blocks own their closed square); the one the floor picks
        // first, then its neighbours.
        [(0, 0), (-1, 0), (0, -1), (-1, -1)]
            .iter()
            .find_map(|(dx, dz)| {
                let block = *self.by_grid.get(&(gx + dx, gz + dz))?;
                self.scene.terrain[block].height_at(x, z)
            })
    }
}
