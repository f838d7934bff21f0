//! One chunk's terrain block as world-space geometry: the triangles the rays
//! hit and the height query of the below-ground test (SPEC §4). Both come
//! from one cell/diagonal/hole rule so that they can never disagree.
//!
//! Geometry is the visible part of the block only: chunk-local
//! `0..=chunk_size` on x and z. Border samples are read but never become
//! triangles.
//!
//! Diagonals follow the engine's `heightAt` and collision code:
//! - terrain2 (`TerrainHeightMap2::heightAt`): if `(cx ^ cz) & 1` the cell's
//!   diagonal joins (x, z+1)–(x+1, z), else (x, z)–(x+1, z+1). The engine
//!   counts `cx, cz` in the bordered image (visible cell + 2) in `heightAt`
//!   and in visible cells in its collision code; the border is even, so the
//!   parity is the same. Here `cx, cz` are visible cell indices.
//! - terrain1 (`TerrainHeightMap1::heightAt`, BigWorld 1.x/2.0): every cell's
//!   diagonal joins (x, z)–(x+1, z+1); terrain1 does not alternate.
//!
//! Holes: the hole map covers the visible square, a hole cell spanning
//! `chunk_size / holes.width` by `chunk_size / holes.height`. A height cell
//! is a hole if its centre lies in a hole cell (computed exactly in integers:
//! hole column `((2·cx + 1) · holes.width) / (2 · cells_x)`); both of its
//! triangles are then dropped and `height_at` answers `None` inside it. The
//! engine instead tests the hole map at the query point itself; the two agree
//! whenever hole cells are whole multiples of height cells, as in real data.
//!
//! A point on an inner cell edge belongs to the cell on its +x/+z side
//! (floor); the block's far edges (local x or z = chunk_size) belong to the
//! last cell.

use glam::DVec3;

use crate::formats::terrain::{TerrainData, TerrainVersion};

/// A chunk's terrain block in world space.
#[derive(Debug, Clone)]
pub struct TerrainBlock {
    origin: DVec3,
    chunk_size: f64,
    version: TerrainVersion,
    cells_x: usize,
    cells_z: usize,
    spacing_x: f64,
    spacing_z: f64,
    /// Visible vertex heights, `(cells_x + 1) × (cells_z + 1)`, row-major by z.
    heights: Vec<f64>,
    /// One flag per height cell, row-major by z.
    cell_holes: Vec<bool>,
    min_height: f64,
    max_height: f64,
}

impl TerrainBlock {
    /// Builds the block of one chunk from its terrain data, the chunk's world
    /// translation and its size in metres. Fails on a grid too small or
    /// inconsistent to have a visible cell, on non-finite heights, origin or
    /// size, and on a hole map whose size does not match its cells.
    pub fn new(data: &TerrainData, origin: DVec3, chunk_size: f64) -> Result<TerrainBlock, String> {
        if !origin.is_finite() {
            return Err(format!("terrain block origin {origin} is not finite"));
        }
        if !(chunk_size.is_finite() && chunk_size > 0.0) {
            return Err(format!(
                "chunk size {chunk_size} is not a positive finite number of metres"
            ));
        }
        let grid = &data.heights;
        if grid.width.checked_mul(grid.height) != Some(grid.heights.len()) {
            return Err(format!(
                "height grid says {}×{} but holds {} heights",
                grid.width,
                grid.height,
                grid.heights.len()
            ));
        }
        let border = data.border;
        // Visible vertices are the grid minus `border` on each side.
        let visible = |n: usize| n.checked_sub(border.checked_mul(2)?).filter(|&v| v >= 2);
        let (Some(vx), Some(vz)) = (visible(grid.width), visible(grid.height)) else {
            return Err(format!(
                "height grid {}×{} with a {border}-sample border has no visible cell",
                grid.width, grid.height
            ));
        };
        let (cells_x, cells_z) = (vx - 1, vz - 1);

        let mut heights = Vec::with_capacity(vx * vz);
        let (mut min_height, mut max_height) = (f64::INFINITY, f64::NEG_INFINITY);
        for z in 0..vz {
            let row_start = (z + border) * grid.width + border;
            let row = grid
                .heights
                .get(row_start..row_start + vx)
                .ok_or("height grid row out of range")?;
            for (x, &h) in row.iter().enumerate() {
                if !h.is_finite() {
                    return Err(format!(
                        "height {h} at visible sample ({x}, {z}) is not finite"
                    ));
                }
                let h = f64::from(h);
                min_height = min_height.min(h);
                max_height = max_height.max(h);
                heights.push(h);
            }
        }

        let mut cell_holes = vec![false; cells_x * cells_z];
        if let Some(map) = &data.holes {
            if map.width.checked_mul(map.height) != Some(map.holes.len()) {
                return Err(format!(
                    "hole map says {}×{} but holds {} cells",
                    map.width,
                    map.height,
                    map.holes.len()
                ));
            }
            // An empty map means no holes (the engine's noHoles()).
            if map.width > 0 && map.height > 0 {
                for cz in 0..cells_z {
                    let hz = hole_index(cz, cells_z, map.height);
                    for cx in 0..cells_x {
                        let hx = hole_index(cx, cells_x, map.width);
                        if map.holes.get(hz * map.width + hx).copied().unwrap_or(false) {
                            cell_holes[cz * cells_x + cx] = true;
                        }
                    }
                }
            }
        }

        Ok(TerrainBlock {
            origin,
            chunk_size,
            version: data.version,
            cells_x,
            cells_z,
            spacing_x: chunk_size / cells_x as f64,
            spacing_z: chunk_size / cells_z as f64,
            heights,
            cell_holes,
            min_height,
            max_height,
        })
    }

    /// World translation of the chunk (local origin of the visible square).
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    pub fn chunk_size(&self) -> f64 {
        self.chunk_size
    }

    pub fn version(&self) -> TerrainVersion {
        self.version
    }

    /// Visible cells along x and z (e.g. 128 × 128 for heightMapSize 128).
    pub fn cells(&self) -> (usize, usize) {
        (self.cells_x, self.cells_z)
    }

    /// Metres between samples along x and z: chunk size / cells.
    pub fn spacing(&self) -> (f64, f64) {
        (self.spacing_x, self.spacing_z)
    }

    /// Height (chunk-local, without `origin.y`) of visible vertex (x, z).
    pub fn vertex_height(&self, x: usize, z: usize) -> Option<f64> {
        if x > self.cells_x {
            return None;
        }
        self.heights.get(z * (self.cells_x + 1) + x).copied()
    }

    /// Whether height cell (cx, cz) is a hole (no triangles, no height).
    pub fn cell_is_hole(&self, cx: usize, cz: usize) -> bool {
        cx < self.cells_x && self.cell_holes.get(cz * self.cells_x + cx) == Some(&true)
    }

    /// Whether the cell's diagonal joins (x, z+1)–(x+1, z) rather than
    /// (x, z)–(x+1, z+1).
    pub fn cell_has_odd_diagonal(&self, cx: usize, cz: usize) -> bool {
        self.version == TerrainVersion::Terrain2 && (cx ^ cz) & 1 == 1
    }

    /// World-space box of the visible vertices (holes included).
    pub fn bounds(&self) -> (DVec3, DVec3) {
        let o = self.origin;
        (
            DVec3::new(o.x, o.y + self.min_height, o.z),
            DVec3::new(
                o.x + self.chunk_size,
                o.y + self.max_height,
                o.z + self.chunk_size,
            ),
        )
    }

    /// The cell holding world point (x, z) and the point's fractions inside
    /// it, or `None` outside the visible square (edges included).
    fn locate(&self, x: f64, z: f64) -> Option<(usize, usize, f64, f64)> {
        let lx = x - self.origin.x;
        let lz = z - self.origin.z;
        let inside = |l: f64| (0.0..=self.chunk_size).contains(&l);
        if !inside(lx) || !inside(lz) {
            return None;
        }
        let (cx, xf) = cell_and_fraction(lx / self.spacing_x, self.cells_x);
        let (cz, zf) = cell_and_fraction(lz / self.spacing_z, self.cells_z);
        Some((cx, cz, xf, zf))
    }

    /// Whether world point (x, z) is inside the visible square and in a hole
    /// cell (where [`height_at`](Self::height_at) answers `None`).
    pub fn is_hole(&self, x: f64, z: f64) -> bool {
        self.locate(x, z)
            .is_some_and(|(cx, cz, _, _)| self.cell_is_hole(cx, cz))
    }

    /// World height of the terrain surface at world (x, z): `None` outside
    /// the visible square or in a hole, else the height of the triangle
    /// containing the point (the engine's `heightAt` interpolation).
    pub fn height_at(&self, x: f64, z: f64) -> Option<f64> {
        let (cx, cz, xf, zf) = self.locate(x, z)?;
        if self.cell_is_hole(cx, cz) {
            return None;
        }
        let h00 = self.vertex_height(cx, cz)?;
        let h10 = self.vertex_height(cx + 1, cz)?;
        let h01 = self.vertex_height(cx, cz + 1)?;
        let h11 = self.vertex_height(cx + 1, cz + 1)?;
        let h = if self.cell_has_odd_diagonal(cx, cz) {
            if (1.0 - xf) > zf {
                h00 + (h10 - h00) * xf + (h01 - h00) * zf
            } else {
                h11 + (h01 - h11) * (1.0 - xf) + (h10 - h11) * (1.0 - zf)
            }
        } else if xf > zf {
            h10 + (h00 - h10) * (1.0 - xf) + (h11 - h10) * zf
        } else {
            h01 + (h11 - h01) * xf + (h00 - h01) * (1.0 - zf)
        };
        Some(self.origin.y + h)
    }

    /// The visible, non-hole triangles in world space, two per cell (row by
    /// row, x fastest), split along the cell's diagonal and wound so the
    /// geometric normal (v1 − v0) × (v2 − v0) points up (+y): the engine's
    /// vertex orders.
    pub fn triangles(&self) -> Vec<[DVec3; 3]> {
        let mut out = Vec::with_capacity(2 * self.cell_holes.iter().filter(|&&h| !h).count());
        for cz in 0..self.cells_z {
            for cx in 0..self.cells_x {
                if self.cell_is_hole(cx, cz) {
                    continue;
                }
                let v = |x: usize, z: usize| -> DVec3 {
                    let h = self.vertex_height(x, z).unwrap_or(0.0);
                    DVec3::new(
                        self.origin.x + x as f64 * self.spacing_x,
                        self.origin.y + h,
                        self.origin.z + z as f64 * self.spacing_z,
                    )
                };
                let bottom_left = v(cx, cz);
                let bottom_right = v(cx + 1, cz);
                let top_left = v(cx, cz + 1);
                let top_right = v(cx + 1, cz + 1);
                if self.cell_has_odd_diagonal(cx, cz) {
                    out.push([bottom_left, top_left, bottom_right]);
                    out.push([top_left, top_right, bottom_right]);
                } else {
                    out.push([bottom_left, top_left, top_right]);
                    out.push([top_right, bottom_right, bottom_left]);
                }
            }
        }
        out
    }
}

/// The hole-map index whose span holds the centre of cell `c` of `cells`:
/// `floor((c + 0.5) / cells * holes)`, in integers so it is exact.
fn hole_index(c: usize, cells: usize, holes: usize) -> usize {
    let index = (2 * c + 1).saturating_mul(holes) / (2 * cells).max(1);
    index.min(holes.saturating_sub(1))
}

/// Splits a grid coordinate `g` (in cells, `0..=cells`) into a cell index and
/// the fraction inside it; `g == cells` maps to the last cell at fraction 1.
fn cell_and_fraction(g: f64, cells: usize) -> (usize, f64) {
    let last = cells - 1; // cells >= 1 by construction
    let floor = g.floor().max(0.0);
    let c = if floor >= last as f64 {
        last
    } else {
        floor as usize
    };
    (c, (g - c as f64).clamp(0.0, 1.0))
}
