//! The terrain for the raster's below-ground test: every block's vertex
//! heights and cell flags packed into one atlas (blocks may differ in
//! resolution, and a big world's blocks do not fit one texture side by side
//! at their true positions), plus an index over the outdoor chunk grid
//! saying where each chunk's block sits in the atlas. The fragment shader
//! looks a point up the way `bake::ground::Ground` does: the chunk the
//! point's floor falls in, then its neighbours for points on a border or
//! in a hole.

use crate::scene::terrain::cell_height;
use crate::scene::Scene;
use std::collections::HashMap;

/// Where one chunk's block sits in the atlas and how it maps world x, z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// Atlas texel of the block's vertex (0, 0).
    pub atlas: (usize, usize),
    pub cells: (usize, usize),
    /// World x, z of the block's vertex (0, 0).
    pub origin: (f64, f64),
    pub spacing: (f64, f64),
}

#[derive(Debug, Clone)]
pub struct GroundAtlas {
    /// Outdoor grid (x, z) of index entry (0, 0).
    pub grid_min: (i32, i32),
    /// Index entries per side.
    pub grid_count: (usize, usize),
    pub chunk_size: f64,
    /// Per chunk of the index (row-major, x fastest): its block, if any.
    pub index: Vec<Option<Placement>>,
    /// Atlas texels per side.
    pub size: (usize, usize),
    /// World heights of block vertices at their atlas texels.
    pub heights: Vec<f64>,
    /// Per cell, at the atlas texel of its (x, z) vertex: bit 0 solid (no
    /// hole), bit 1 odd diagonal.
    pub flags: Vec<u8>,
}

impl GroundAtlas {
    /// `Ok(None)`: no terrain. `Err`: why it does not fit textures of
    /// `max_side` texels a side (the caller turns the test off and says so).
    pub fn new(scene: &Scene, max_side: usize) -> Result<Option<GroundAtlas>, String> {
        let by_grid: HashMap<(i32, i32), usize> = scene
            .chunks
            .iter()
            .filter_map(|chunk| Some((chunk.grid?, chunk.terrain?)))
            .collect();
        if by_grid.is_empty() {
            return Ok(None);
        }
        let mut grids: Vec<(i32, i32)> = by_grid.keys().copied().collect();
        grids.sort_unstable_by_key(|&(x, z)| (z, x));
        let min = grids
            .iter()
            .fold((i32::MAX, i32::MAX), |m, g| (m.0.min(g.0), m.1.min(g.1)));
        let max = grids
            .iter()
            .fold((i32::MIN, i32::MIN), |m, g| (m.0.max(g.0), m.1.max(g.1)));
        let count = (
            (i64::from(max.0) - i64::from(min.0) + 1) as usize,
            (i64::from(max.1) - i64::from(min.1) + 1) as usize,
        );
        if count.0 > max_side || count.1 > max_side {
            return Err(format!(
                "the terrain spans {} × {} chunks, more than the {max_side} a texture side holds",
                count.0, count.1
            ));
        }
        // Shelf packing in grid order: blocks of one world mostly share a
        // size, so rows fill evenly.
        let mut index = vec![None; count.0 * count.1];
        let (mut x, mut y, mut row_height, mut width) = (0usize, 0usize, 0usize, 0usize);
        let mut placed = Vec::with_capacity(grids.len());
        for grid in &grids {
            let block = &scene.terrain[by_grid[grid]];
            let cells = block.cells();
            let side = (cells.0 + 1, cells.1 + 1);
            if side.0 > max_side {
                return Err(format!(
                    "a terrain block of {} × {} cells is wider than a texture",
                    cells.0, cells.1
                ));
            }
            if x + side.0 > max_side {
                x = 0;
                y += row_height;
                row_height = 0;
            }
            if y + side.1 > max_side {
                return Err(format!(
                    "the {} terrain blocks do not fit one {max_side} × {max_side} texture",
                    grids.len()
                ));
            }
            let origin = block.origin();
            let placement = Placement {
                atlas: (x, y),
                cells,
                origin: (origin.x, origin.z),
                spacing: block.spacing(),
            };
            let at = (grid.1 - min.1) as usize * count.0 + (grid.0 - min.0) as usize;
            index[at] = Some(placement);
            placed.push((by_grid[grid], placement));
            x += side.0;
            width = width.max(x);
            row_height = row_height.max(side.1);
        }
        let size = (width, y + row_height);
        let mut heights = vec![0.0; size.0 * size.1];
        let mut flags = vec![0u8; size.0 * size.1];
        for (block, p) in placed {
            let block = &scene.terrain[block];
            let base_y = block.origin().y;
            for vz in 0..=p.cells.1 {
                for vx in 0..=p.cells.0 {
                    let at = (p.atlas.1 + vz) * size.0 + p.atlas.0 + vx;
                    if let Some(h) = block.vertex_height(vx, vz) {
                        heights[at] = base_y + h;
                    }
                    if vx < p.cells.0 && vz < p.cells.1 {
                        flags[at] = u8::from(!block.cell_is_hole(vx, vz))
                            | (u8::from(block.cell_has_odd_diagonal(vx, vz)) << 1);
                    }
                }
            }
        }
        Ok(Some(GroundAtlas {
            grid_min: min,
            grid_count: count,
            chunk_size: scene.settings.chunk_size,
            index,
            size,
            heights,
            flags,
        }))
    }

    /// The shader's lookup, step for step, in f64: H(x, z) or `None`. Tests
    /// hold it to `Ground::height`; the shader is held to the ray cast by
    /// the cross-check tests.
    pub fn height(&self, x: f64, z: f64) -> Option<f64> {
        let g0 = (
            ((x - f64::from(self.grid_min.0) * self.chunk_size) / self.chunk_size).floor(),
            ((z - f64::from(self.grid_min.1) * self.chunk_size) / self.chunk_size).floor(),
        );
        [(0.0, 0.0), (-1.0, 0.0), (0.0, -1.0), (-1.0, -1.0)]
            .iter()
            .find_map(|(dx, dz)| {
                let g = (g0.0 + dx, g0.1 + dz);
                if g.0 < 0.0
                    || g.1 < 0.0
                    || g.0 >= self.grid_count.0 as f64
                    || g.1 >= self.grid_count.1 as f64
                {
                    return None;
                }
                let p = self.index[g.1 as usize * self.grid_count.0 + g.0 as usize]?;
                let l = (x - p.origin.0, z - p.origin.1);
                let inside = |v: f64| (0.0..=self.chunk_size).contains(&v);
                if !inside(l.0) || !inside(l.1) {
                    return None;
                }
                let cell = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n - 1);
                let gl = (l.0 / p.spacing.0, l.1 / p.spacing.1);
                let c = (cell(gl.0, p.cells.0), cell(gl.1, p.cells.1));
                let xf = (gl.0 - c.0 as f64).clamp(0.0, 1.0);
                let zf = (gl.1 - c.1 as f64).clamp(0.0, 1.0);
                let a = (p.atlas.0 + c.0, p.atlas.1 + c.1);
                let f = self.flags[a.1 * self.size.0 + a.0];
                if f & 1 == 0 {
                    return None;
                }
                let h = |dx: usize, dz: usize| self.heights[(a.1 + dz) * self.size.0 + a.0 + dx];
                let corners = [h(0, 0), h(1, 0), h(0, 1), h(1, 1)];
                Some(cell_height(corners, f & 2 != 0, xf, zf))
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::ground::Ground;
    use crate::formats::space_settings::{outdoor_chunk_name, SpaceSettings};
    use crate::formats::terrain::{HeightMap, HoleMap, TerrainData, TerrainVersion};
    use crate::rng::Rng;
    use crate::scene::{Chunk, Scene, TerrainBlock};
    use glam::{DMat4, DVec3};

    const SIZE: f64 = 16.0;

    /// 3 × 2 chunks from grid (−1, 0): blocks of 8 and 5 cells a side, one
    /// chunk without terrain, one block with holes, bumpy heights, chunk y
    /// offsets.
    fn world() -> Scene {
        let mut chunks = Vec::new();
        let mut terrain = Vec::new();
        let mut rng = Rng::new(7);
        for (i, (x, z)) in [(-1, 0), (0, 0), (1, 0), (-1, 1), (0, 1), (1, 1)]
            .into_iter()
            .enumerate()
        {
            let origin = DVec3::new(x as f64 * SIZE, i as f64 * 0.25, z as f64 * SIZE);
            let block = (i != 4).then(|| {
                let cells = if i % 2 == 0 { 8 } else { 5 };
                let width = cells + 5;
                let heights = (0..width * width)
                    .map(|_| rng.range(-3.0, 3.0) as f32)
                    .collect();
                let holes = (i == 1).then(|| HoleMap {
                    width: cells,
                    height: cells,
                    holes: (0..cells * cells).map(|c| c % 3 == 0).collect(),
                });
                let data = TerrainData {
                    version: TerrainVersion::Terrain2,
                    heights: HeightMap {
                        width,
                        height: width,
                        heights,
                    },
                    border: 2,
                    holes,
                };
                TerrainBlock::new(&data, origin, SIZE).expect("valid block")
            });
            chunks.push(Chunk {
                name: outdoor_chunk_name(x, z),
                file: format!("{x}_{z}.chunk").into(),
                file_key: None,
                grid: Some((x, z)),
                transform: DMat4::from_translation(origin),
                instances: 0..0,
                instance_elements: 0,
                speedtree_elements: 0,
                sites: None,
                terrain: block.map(|b| {
                    terrain.push(b);
                    terrain.len() - 1
                }),
            });
        }
        Scene {
            space_dir: "atlas".into(),
            settings: SpaceSettings {
                min_x: -1,
                max_x: 1,
                min_z: 0,
                max_z: 1,
                chunk_size: SIZE,
                single_dir: false,
                terrain_version: Some(200),
                height_map_size: None,
            },
            chunks,
            models: Vec::new(),
            instances: Vec::new(),
            terrain,
            items: Vec::new(),
            problems: Vec::new(),
            inputs: Vec::new(),
        }
    }

    #[test]
    fn the_atlas_lookup_gives_the_ray_casts_heights() {
        let scene = world();
        let atlas = GroundAtlas::new(&scene, 64).unwrap().unwrap();
        let ground = Ground::new(&scene).unwrap();
        let mut rng = Rng::new(11);
        let mut points: Vec<(f64, f64)> = (0..20000)
            .map(|_| (rng.range(-20.0, 52.0), rng.range(-4.0, 36.0)))
            .collect();
        // Chunk borders, block lattice lines and corners exactly.
        for i in -2..=7 {
            for j in -1..=5 {
                points.push((i as f64 * 8.0, j as f64 * 8.0));
                points.push((i as f64 * 8.0, j as f64 * 3.2 + 0.1));
                points.push((i as f64 * 3.2, j as f64 * 8.0));
            }
        }
        let (mut some, mut none) = (0, 0);
        for (x, z) in points {
            let (a, b) = (atlas.height(x, z), ground.height(x, z));
            match (a, b) {
                (Some(a), Some(b)) => {
                    assert!((a - b).abs() < 1e-9, "({x}, {z}): {a} vs {b}");
                    some += 1;
                }
                (None, None) => none += 1,
                _ => panic!("({x}, {z}): atlas {a:?}, ground {b:?}"),
            }
        }
        // Both kinds of answer occur: covered, holes, the chunk without
        // terrain and the outside.
        assert!(some > 6000 && none > 6000, "{some} {none}");
    }

    #[test]
    fn blocks_of_different_sizes_share_the_atlas() {
        let atlas = GroundAtlas::new(&world(), 64).unwrap().unwrap();
        let placed: Vec<Placement> = atlas.index.iter().flatten().copied().collect();
        assert_eq!(placed.len(), 5);
        assert!(
            placed.iter().any(|p| p.cells == (8, 8)) && placed.iter().any(|p| p.cells == (5, 5))
        );
        // No two blocks' vertex squares overlap.
        for (i, a) in placed.iter().enumerate() {
            for b in &placed[i + 1..] {
                let apart = |a: &Placement, b: &Placement| {
                    a.atlas.0 + a.cells.0 < b.atlas.0 || a.atlas.1 + a.cells.1 < b.atlas.1
                };
                assert!(apart(a, b) || apart(b, a), "{a:?} {b:?}");
            }
        }
    }

    #[test]
    fn a_texture_too_small_is_an_error_that_says_so() {
        let err = GroundAtlas::new(&world(), 2).unwrap_err();
        assert!(err.contains("chunks"), "{err}");
        let err = GroundAtlas::new(&world(), 12).unwrap_err();
        assert!(err.contains("texture"), "{err}");
    }
}
