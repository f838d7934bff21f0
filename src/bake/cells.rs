//! The cells of a light's grid and what each cell's rays can meet: the
//! unit the bake cache keeps and traces again (see `cache_keys`).
//!
//! A cell is a square of [`CELL_TILES`]² tiles of one face (the last row
//! and column of a face are cut short). Its *reach* is every placed part
//! and terrain block whose world box projects (`TexelGrid::box_image`)
//! onto the cell's texels grown by a margin: the filter radius (a tile's
//! halo), one texel (a conservative beam's square and its growth), and the
//! rounding by which a hit's image strays from its ray's position
//! (`TexelGrid::image_rounding`). Exact: a hit lies in its entry's box,
//! and a point of the box projects inside the box's image, so every ray of
//! the cell (halo included) can hit only what is in its reach. To it come
//! the terrain blocks the below-ground test may read for a hit on one of
//! those parts ([`GroundNear`]). Lists are in scene order (parts in caster
//! id order, blocks by index), so a cell's reach reads the same in every
//! bake of the same world.

use super::casters::set_bits;
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::TILE;
use crate::light::{BoxImage, TexelGrid};
use crate::scene::Scene;
use crate::trace::transform_box;
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::ops::RangeInclusive;

/// Tiles per cell side: a cell is 512 × 512 texels.
pub const CELL_TILES: u32 = 16;

/// The cells of one grid: faces, then rows of cells, then columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cells {
    faces: usize,
    width: u32,
    height: u32,
    tiles_x: u64,
    tiles_y: u64,
    cells_x: u64,
    cells_y: u64,
}

impl Cells {
    pub fn of(grid: &TexelGrid) -> Cells {
        let tiles_x = grid.width().div_ceil(TILE) as u64;
        let tiles_y = grid.height().div_ceil(TILE) as u64;
        Cells {
            faces: grid.faces(),
            width: grid.width(),
            height: grid.height(),
            tiles_x,
            tiles_y,
            cells_x: tiles_x.div_ceil(CELL_TILES as u64),
            cells_y: tiles_y.div_ceil(CELL_TILES as u64),
        }
    }

    pub fn count(&self) -> u64 {
        self.faces as u64 * self.cells_x * self.cells_y
    }

    /// Cell `cell`'s face and texel rectangle `x0..x1 × y0..y1`.
    pub fn rect(&self, cell: u64) -> (usize, u32, u32, u32, u32) {
        let per_face = self.cells_x * self.cells_y;
        let face = (cell / per_face) as usize;
        let within = cell % per_face;
        let side = CELL_TILES * TILE;
        let x0 = (within % self.cells_x) as u32 * side;
        let y0 = (within / self.cells_x) as u32 * side;
        (
            face,
            x0,
            y0,
            (x0 + side).min(self.width),
            (y0 + side).min(self.height),
        )
    }

    /// The tiles of cell `cell` (indices of `trace_light::tile_rect`), in
    /// tile order.
    pub fn tiles(&self, cell: u64) -> Vec<u64> {
        let per_face = self.cells_x * self.cells_y;
        let face = cell / per_face;
        let within = cell % per_face;
        let (cx, cy) = (within % self.cells_x, within / self.cells_x);
        let n = CELL_TILES as u64;
        let rows = cy * n..((cy + 1) * n).min(self.tiles_y);
        let columns = cx * n..((cx + 1) * n).min(self.tiles_x);
        let first = face * self.tiles_x * self.tiles_y;
        rows.flat_map(|ty| {
            columns
                .clone()
                .map(move |tx| first + ty * self.tiles_x + tx)
        })
        .collect()
    }

    /// The cell holding tile `tile`.
    pub fn of_tile(&self, tile: u64) -> u64 {
        let per_face = self.tiles_x * self.tiles_y;
        let face = tile / per_face;
        let within = tile % per_face;
        let n = CELL_TILES as u64;
        let (cx, cy) = ((within % self.tiles_x) / n, (within / self.tiles_x) / n);
        (face * self.cells_y + cy) * self.cells_x + cx
    }

    /// Rays of cell `cell` at `samples`² a texel.
    pub fn rays(&self, cell: u64, samples: u32) -> u64 {
        let (_, x0, y0, x1, y1) = self.rect(cell);
        u64::from(x1 - x0) * u64::from(y1 - y0) * u64::from(samples.max(1)).pow(2)
    }

    /// The cells of `face` whose texels grown by `margin` meet `image`.
    fn meeting(&self, face: usize, image: BoxImage, margin: f64) -> impl Iterator<Item = u64> {
        let side = f64::from(CELL_TILES * TILE);
        let span = |lo: f64, hi: f64, cells: u64| -> std::ops::Range<u64> {
            // NaN compares false: no cell.
            let first = ((lo - margin) / side).floor().max(0.0);
            let last = ((hi + margin) / side).floor().min(cells as f64 - 1.0);
            if first <= last {
                first as u64..last as u64 + 1
            } else {
                0..0
            }
        };
        let (xs, ys) = match image {
            BoxImage::Nowhere => (0..0, 0..0),
            BoxImage::WholeFace => (0..self.cells_x, 0..self.cells_y),
            BoxImage::Rect(x0, y0, x1, y1) => {
                let (w, h) = (f64::from(self.width), f64::from(self.height));
                // The cells' texels end at the face's edges.
                let inside = x1 + margin >= 0.0 && y1 + margin >= 0.0;
                if inside && x0 - margin <= w && y0 - margin <= h {
                    (span(x0, x1, self.cells_x), span(y0, y1, self.cells_y))
                } else {
                    (0..0, 0..0)
                }
            }
        };
        let cells_x = self.cells_x;
        let first = face as u64 * self.cells_x * self.cells_y;
        ys.flat_map(move |cy| xs.clone().map(move |cx| first + cy * cells_x + cx))
    }
}

/// Per part (in `BakeWorld::parts` order), the terrain blocks the
/// below-ground test may read for a hit on it: H(x, z) of a point reads
/// the block of its chunk cell and of the cells before it on x and z (a
/// point on a border may belong to either), and the conservative pass's
/// and refinement's "surely above" test reads the cells from one before
/// its box to its box. Both lie in the chunk cells `floor(x0/s) − 1 ..=
/// floor(x1/s)` (and on z) of the part's box, grown by a metre and a part
/// in 10⁵ of its coordinates for the rounding of a hit point.
#[derive(Debug, Clone, Default)]
pub struct GroundNear {
    /// Offsets into `blocks`: part `p`'s are `blocks[starts[p]..starts[p + 1]]`.
    starts: Vec<u32>,
    blocks: Vec<u32>,
}

impl GroundNear {
    pub fn of(world: &BakeWorld) -> GroundNear {
        let scene = world.scene;
        let cells = BlockCells::of(scene);
        let mut near = GroundNear {
            starts: vec![0],
            blocks: Vec::new(),
        };
        if cells.is_empty() {
            near.starts.resize(world.parts.len() + 1, 0);
            return near;
        }
        // Runs of parts, each into one list (not a list per part: millions
        // of small allocations on a large world).
        let runs: Vec<(Vec<u32>, Vec<u32>)> = world
            .parts
            .par_chunks(GROUND_NEAR_RUN)
            .map(|run| {
                let (mut ends, mut blocks) = (Vec::with_capacity(run.len()), Vec::new());
                for part in run {
                    if let Some((min, max)) = part_box(world, part) {
                        blocks_near(scene, &cells, min, max, &mut blocks);
                    }
                    ends.push(blocks.len() as u32);
                }
                (ends, blocks)
            })
            .collect();
        for (ends, blocks) in runs {
            let before = near.blocks.len() as u32;
            near.starts.extend(ends.iter().map(|&end| before + end));
            near.blocks.extend(blocks);
        }
        near
    }

    /// The blocks near part `part` (an index into `BakeWorld::parts`).
    pub fn of_part(&self, part: u32) -> &[u32] {
        let p = part as usize;
        match (self.starts.get(p), self.starts.get(p + 1)) {
            (Some(&a), Some(&b)) => &self.blocks[a as usize..b as usize],
            _ => &[],
        }
    }
}

/// Parts per parallel run of [`GroundNear::of`].
const GROUND_NEAR_RUN: usize = 8192;

/// Appends to `blocks` the blocks in the chunk cells the box `min..max` may
/// read (see [`GroundNear`]), ascending.
fn blocks_near(scene: &Scene, cells: &BlockCells, min: DVec3, max: DVec3, blocks: &mut Vec<u32>) {
    let size = scene.settings.chunk_size;
    let grow = 1.0 + 1e-5 * min.abs().max(max.abs()).max_element();
    let range = |lo: f64, hi: f64| {
        let first = ((lo - grow) / size).floor() - 1.0;
        let last = ((hi + grow) / size).floor();
        // A box beyond any chunk coordinate reads no block.
        (first.abs() < 1e9 && last.abs() < 1e9).then_some((first as i64, last as i64))
    };
    let (Some((x0, x1)), Some((z0, z1))) = (range(min.x, max.x), range(min.z, max.z)) else {
        return;
    };
    let start = blocks.len();
    cells.extend_in(x0..=x1, z0..=z1, blocks);
    blocks[start..].sort_unstable();
}

/// The terrain block of each outdoor chunk cell: a grid over the cells'
/// rectangle where that is compact (an outdoor space's chunks fill
/// theirs), else a map. Every placed part looks up four or more cells,
/// and hashing each lookup was most of finding the blocks near a part.
enum BlockCells {
    Grid {
        x0: i64,
        z0: i64,
        width: i64,
        /// Row by row from `(x0, z0)`; `NO_BLOCK` where a cell has none.
        blocks: Vec<u32>,
        count: usize,
    },
    Map(HashMap<(i64, i64), u32>),
}

const NO_BLOCK: u32 = u32::MAX;

impl BlockCells {
    fn of(scene: &Scene) -> BlockCells {
        let cells: HashMap<(i64, i64), u32> = scene
            .chunks
            .iter()
            .filter_map(|c| {
                let (x, z) = c.grid?;
                Some(((i64::from(x), i64::from(z)), c.terrain? as u32))
            })
            .collect();
        BlockCells::from_map(cells)
    }

    /// A grid of `cells` where compact, else the map.
    fn from_map(cells: HashMap<(i64, i64), u32>) -> BlockCells {
        let (Some(x0), Some(x1)) = (
            cells.keys().map(|k| k.0).min(),
            cells.keys().map(|k| k.0).max(),
        ) else {
            return BlockCells::Map(cells);
        };
        let (z0, z1) = (
            cells.keys().map(|k| k.1).min(),
            cells.keys().map(|k| k.1).max(),
        );
        let (Some(z0), Some(z1)) = (z0, z1) else {
            return BlockCells::Map(cells);
        };
        let (width, height) = (x1 - x0 + 1, z1 - z0 + 1);
        if width.saturating_mul(height) > 4 * cells.len() as i64 + 1024 {
            return BlockCells::Map(cells);
        }
        let mut blocks = vec![NO_BLOCK; (width * height) as usize];
        for (&(x, z), &block) in &cells {
            blocks[((z - z0) * width + (x - x0)) as usize] = block;
        }
        BlockCells::Grid {
            x0,
            z0,
            width,
            blocks,
            count: cells.len(),
        }
    }

    fn is_empty(&self) -> bool {
        match self {
            BlockCells::Grid { count, .. } => *count == 0,
            BlockCells::Map(cells) => cells.is_empty(),
        }
    }

    /// Appends the blocks of the cells `xs × zs`, in no particular order.
    fn extend_in(&self, xs: RangeInclusive<i64>, zs: RangeInclusive<i64>, out: &mut Vec<u32>) {
        match self {
            BlockCells::Grid {
                x0,
                z0,
                width,
                blocks,
                ..
            } => {
                let height = blocks.len() as i64 / width;
                let columns = (*xs.start()).max(*x0)..=(*xs.end()).min(x0 + width - 1);
                for z in (*zs.start()).max(*z0)..=(*zs.end()).min(z0 + height - 1) {
                    let row = (z - z0) * width - x0;
                    let cells = columns.clone().map(|x| blocks[(row + x) as usize]);
                    out.extend(cells.filter(|&b| b != NO_BLOCK));
                }
            }
            BlockCells::Map(cells) => {
                let area = (xs.end() - xs.start() + 1).saturating_mul(zs.end() - zs.start() + 1);
                if area > cells.len() as i64 {
                    out.extend(cells.iter().filter_map(|(&(x, z), &b)| {
                        (xs.contains(&x) && zs.contains(&z)).then_some(b)
                    }));
                } else {
                    for z in zs {
                        for x in xs.clone() {
                            out.extend(cells.get(&(x, z)));
                        }
                    }
                }
            }
        }
    }
}

/// A placed part's world box (its model's bottom level's), or `None` when
/// the model has nothing to hit.
pub fn part_box(world: &BakeWorld, part: &super::casters::PartCasters) -> Option<(DVec3, DVec3)> {
    let (min, max) = world.bottom.models[part.model].bounds()?;
    let placed = &world.scene.instances[part.instance].world;
    Some(transform_box(placed, min.as_dvec3(), max.as_dvec3()))
}

/// What each cell of a light's grid can meet (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct CellReach {
    /// Per cell, indices into `BakeWorld::parts`, ascending.
    pub parts: Vec<Vec<u32>>,
    /// Per cell, the terrain blocks its rays can hit, ascending.
    pub blocks: Vec<Vec<u32>>,
    /// Per cell, the terrain blocks the below-ground test may read for a
    /// hit on one of its parts, ascending.
    pub ground: Vec<Vec<u32>>,
}

impl CellReach {
    /// The reach of every cell of `setup`'s grid, its texels grown by
    /// `halo` texels (the filter radius) besides the margin every cell
    /// has.
    pub fn of(
        world: &BakeWorld,
        setup: &LightSetup,
        cells: &Cells,
        halo: f64,
        ground: &GroundNear,
    ) -> CellReach {
        let grid = &setup.grid;
        let margin = halo + 1.0 + grid.image_rounding(reach_magnitude(setup));
        let count = cells.count() as usize;
        let cells_of = move |min: DVec3, max: DVec3| {
            (0..grid.faces())
                .flat_map(move |face| cells.meeting(face, grid.box_image(face, min, max), margin))
        };
        let parts = bin(count, &setup.reach.parts, |&p| {
            part_box(world, &world.parts[p as usize])
                .into_iter()
                .flat_map(|(a, b)| cells_of(a, b))
        });
        let blocks = bin(count, &setup.reach.blocks, |&b| {
            let (min, max) = world.scene.terrain[b as usize].bounds();
            cells_of(min, max)
        });
        // Each cell's blocks as bits over the world's blocks: a cell's
        // parts name tens of thousands of blocks, mostly the same few.
        let words = world.scene.terrain.len().div_ceil(64);
        let ground = parts
            .par_iter()
            .map_init(
                || vec![0u64; words],
                |seen, parts| {
                    for &b in parts.iter().flat_map(|&p| ground.of_part(p)) {
                        seen[b as usize / 64] |= 1 << (b % 64);
                    }
                    let near = set_bits(seen).collect();
                    seen.fill(0);
                    near
                },
            )
            .collect();
        CellReach {
            parts,
            blocks,
            ground,
        }
    }

    /// Whether nothing is in cell `cell`'s reach (its rays hit nothing).
    pub fn is_empty(&self, cell: u64) -> bool {
        let c = cell as usize;
        self.parts[c].is_empty() && self.blocks[c].is_empty()
    }
}

/// Each of `items` (ascending) into the cells `cells_of` it names: per
/// cell, its items, ascending. Each thread bins a run of consecutive
/// items on its own; a cell's list is then its runs' lists in item order,
/// already ascending, joined at its exact size.
fn bin<Named: Iterator<Item = u64>>(
    count: usize,
    items: &[u32],
    cells_of: impl Fn(&u32) -> Named + Sync,
) -> Vec<Vec<u32>> {
    let runs = (rayon::current_num_threads() * 2).clamp(1, items.len().div_ceil(4096).max(1));
    let run_length = items.len().div_ceil(runs).max(1);
    let binned_runs: Vec<Vec<Vec<u32>>> = items
        .par_chunks(run_length)
        .map(|run| {
            let mut binned = vec![Vec::new(); count];
            for item in run {
                for cell in cells_of(item) {
                    binned[cell as usize].push(*item);
                }
            }
            binned
        })
        .collect();
    (0..count)
        .into_par_iter()
        .map(|cell| {
            let size = binned_runs.iter().map(|run| run[cell].len()).sum();
            let mut joined = Vec::with_capacity(size);
            for run in &binned_runs {
                joined.extend_from_slice(&run[cell]);
            }
            joined
        })
        .collect()
}

/// The largest light-relative coordinate of what the light's top level
/// holds (for [`TexelGrid::image_rounding`]), as `TileReach` takes it.
fn reach_magnitude(setup: &LightSetup) -> f64 {
    setup.extent.bounds.map_or(0.0, |(lo, hi)| {
        let (lo, hi) = (lo.as_dvec3(), hi.as_dvec3());
        lo.abs().max(hi.abs()).max_element()
    })
}

/// The texel rectangles of the tiles of cell `cell` cover its rectangle
/// exactly: what the tests check of [`Cells`].
#[cfg(test)]
fn tiles_cover(cells: &Cells, grid: &TexelGrid, cell: u64) -> bool {
    use super::trace_light::tile_rect;
    let (face, x0, y0, x1, y1) = cells.rect(cell);
    let tiles = cells.tiles(cell);
    let area: u64 = tiles
        .iter()
        .map(|&t| {
            let (f, a, b, c, d) = tile_rect(grid, t);
            assert_eq!(f, face);
            assert!(a >= x0 && b >= y0 && c <= x1 && d <= y1);
            assert_eq!(cells.of_tile(t), cell);
            u64::from(c - a) * u64::from(d - b)
        })
        .sum();
    area == u64::from(x1 - x0) * u64::from(y1 - y0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The grid finds what the map finds: seeded cells (holes, a ragged
    /// edge, negative coordinates) and ranges inside, across and beyond
    /// them.
    #[test]
    fn block_cells_grid_and_map_agree() {
        let mut rng = crate::rng::Rng::new(0xce11);
        let mut cells = HashMap::new();
        for z in -7i64..9 {
            for x in -3i64..(5 + z.rem_euclid(4)) {
                if rng.chance(0.85) {
                    cells.insert((x, z), cells.len() as u32);
                }
            }
        }
        let grid = BlockCells::from_map(cells.clone());
        assert!(matches!(grid, BlockCells::Grid { .. }));
        let map = BlockCells::Map(cells);
        for _ in 0..2_000 {
            let a = rng.below(40) as i64 - 20;
            let b = a + rng.below(12) as i64 - 1;
            let c = rng.below(40) as i64 - 20;
            let d = c + rng.below(12) as i64 - 1;
            let (mut from_grid, mut from_map) = (Vec::new(), Vec::new());
            grid.extend_in(a..=b, c..=d, &mut from_grid);
            map.extend_in(a..=b, c..=d, &mut from_map);
            from_grid.sort_unstable();
            from_map.sort_unstable();
            assert_eq!(from_grid, from_map, "{a}..={b} × {c}..={d}");
        }
        let far = HashMap::from([((0, 0), 0), ((1 << 30, 0), 1)]);
        assert!(matches!(BlockCells::from_map(far), BlockCells::Map(_)));
    }

    /// Binned in order, each cell's items are those a sort of the pairs
    /// gives: every item that names it, ascending, repeats kept.
    #[test]
    fn binning_keeps_each_cells_items_ascending() {
        let mut rng = crate::rng::Rng::new(0xb1);
        let count = 37;
        // Enough items for several runs (4 096 or more each).
        let items: Vec<u32> = (0..40_000u32).filter(|_| rng.chance(0.7)).collect();
        let named: Vec<Vec<u64>> = items
            .iter()
            .map(|_| (0..rng.below(4)).map(|_| rng.below(count) as u64).collect())
            .collect();
        let position = |item: &u32| items.binary_search(item).unwrap();
        let binned = bin(count, &items, |item| {
            named[position(item)].clone().into_iter()
        });
        let mut pairs: Vec<(u64, u32)> = items
            .iter()
            .flat_map(|item| named[position(item)].iter().map(move |&c| (c, *item)))
            .collect();
        pairs.sort_unstable();
        let mut expected = vec![Vec::new(); count];
        for (cell, item) in pairs {
            expected[cell as usize].push(item);
        }
        assert_eq!(binned, expected);
        assert!(expected.iter().all(|items| items.len() > 10));
    }
    use crate::formats::bake_settings::{LightKind, LightSettings};

    #[test]
    fn cells_partition_the_tiles_of_every_face() {
        let lights = [
            LightKind::Directional {
                direction: DVec3::new(-0.3, -1.0, 0.2),
                texel_size: 0.37,
            },
            LightKind::Point {
                position: DVec3::ZERO,
                near: 0.1,
                far: 50.0,
                resolution: 300,
            },
        ];
        for kind in lights {
            let light = LightSettings {
                name: "l".into(),
                kind,
            };
            let bounds = (
                DVec3::new(-100.0, 0.0, -90.0),
                DVec3::new(300.0, 40.0, 500.0),
            );
            let grid = TexelGrid::new(&light, bounds).unwrap();
            let cells = Cells::of(&grid);
            let tiles = crate::bake::trace_light::tile_count(&grid);
            let mut seen = vec![0u32; tiles as usize];
            for cell in 0..cells.count() {
                assert!(tiles_cover(&cells, &grid, cell), "cell {cell}");
                for t in cells.tiles(cell) {
                    seen[t as usize] += 1;
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "every tile in one cell");
            let texels: u64 = (0..cells.count()).map(|c| cells.rays(c, 1)).sum();
            assert_eq!(texels, grid.texel_count());
        }
    }
}
