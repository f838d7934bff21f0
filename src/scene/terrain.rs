//! One chunk's terrain block as world-space geometry: the triangles the rays
//! hit and the height query of the below-ground test (docs/contract.md §4). Both come
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
//! whenever a hole cell is a whole number of height cells (highlands:
//! heightMapSize 128, holeMapSize 64). They do not always: fantasydemo's
//! arctic space has heightMapSize 32 and holeMapSize 25, where hole borders
//! here follow height cells and may differ from the engine's by up to one
//! height cell (3.125 m).
//!
//! A point on an inner cell edge belongs to the cell on its +x/+z side
//! (floor); the block's far edges (local x or z = chunk_size) belong to the
//! last cell.

use glam::DVec3;

use crate::cache::Key;
use crate::formats::terrain::{DeferredTerrain, HoleMap, TerrainData, TerrainVersion};
use crate::trace::{DeferredHeights, HeightGrid, Heights};

/// Fails on an origin or chunk size a block cannot be placed with.
fn check_placement(origin: DVec3, chunk_size: f64) -> Result<(), String> {
    if !origin.is_finite() {
        return Err(format!("terrain block origin {origin} is not finite"));
    }
    if !(chunk_size.is_finite() && chunk_size > 0.0) {
        return Err(format!(
            "chunk size {chunk_size} is not a positive finite number of metres"
        ));
    }
    Ok(())
}

/// The lowest and highest of `heights` (as f64, exactly), or the index of
/// the first that is not finite. In lanes: a big world holds hundreds of
/// millions of samples.
fn finite_extremes(heights: &[f32]) -> Result<(f64, f64), usize> {
    const LANES: usize = 16;
    let (mut low, mut high) = ([f32::INFINITY; LANES], [f32::NEG_INFINITY; LANES]);
    let mut finite = true;
    let mut runs = heights.chunks_exact(LANES);
    for run in &mut runs {
        for i in 0..LANES {
            let h = run[i];
            finite &= h.is_finite();
            low[i] = if h < low[i] { h } else { low[i] };
            high[i] = if h > high[i] { h } else { high[i] };
        }
    }
    for (i, &h) in runs.remainder().iter().enumerate() {
        finite &= h.is_finite();
        low[i] = if h < low[i] { h } else { low[i] };
        high[i] = if h > high[i] { h } else { high[i] };
    }
    if !finite {
        return Err(heights.iter().position(|h| !h.is_finite()).unwrap_or(0));
    }
    let low = low.into_iter().fold(f32::INFINITY, f32::min);
    let high = high.into_iter().fold(f32::NEG_INFINITY, f32::max);
    Ok((f64::from(low), f64::from(high)))
}

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
    /// Visible vertex heights, `(cells_x + 1) × (cells_z + 1)`, row-major by
    /// z; kept in f32 as the files store them (4 bytes a sample).
    heights: BlockHeights,
    /// One flag per height cell, row-major by z; empty when the block has
    /// no hole (most blocks: that saves a byte per cell on big worlds).
    cell_holes: Vec<bool>,
    range: HeightRange,
    /// The content key of what the block was read from (its file's bytes
    /// and entry), when it was read from a file: what a cache key hashes
    /// instead of the samples, which may not be decoded.
    source: Option<Key>,
}

/// The samples as decoded, or decoded when first read.
#[derive(Debug, Clone)]
enum BlockHeights {
    Held(Vec<f32>),
    Deferred(DeferredHeights),
}

/// The lowest and highest visible sample of a block (every one finite):
/// what the load needs of a block's samples without decoding them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeightRange {
    pub low: f32,
    pub high: f32,
}

impl HeightRange {
    /// Whether a block can have it: both finite, the lowest not above the
    /// highest.
    pub fn is_sound(&self) -> bool {
        self.low.is_finite() && self.high.is_finite() && self.low <= self.high
    }
}

/// A height grid's visible part: the grid's size less the border.
#[derive(Debug, Clone, Copy)]
struct Visible {
    width: usize,
    border: usize,
    vx: usize,
    vz: usize,
}

impl Visible {
    /// Fails on a grid too small to have a visible cell.
    fn of(width: usize, height: usize, border: usize) -> Result<Visible, String> {
        let visible = |n: usize| n.checked_sub(border.checked_mul(2)?).filter(|&v| v >= 2);
        let (Some(vx), Some(vz)) = (visible(width), visible(height)) else {
            return Err(format!(
                "height grid {width}×{height} with a {border}-sample border has no visible cell"
            ));
        };
        Ok(Visible {
            width,
            border,
            vx,
            vz,
        })
    }

    /// The visible rows of a grid's samples.
    fn crop(&self, samples: &[f32]) -> Result<Vec<f32>, String> {
        let mut heights = Vec::with_capacity(self.vx * self.vz);
        for z in 0..self.vz {
            let row_start = (z + self.border) * self.width + self.border;
            let row = samples
                .get(row_start..row_start + self.vx)
                .ok_or("height grid row out of range")?;
            heights.extend_from_slice(row);
        }
        Ok(heights)
    }
}

impl TerrainBlock {
    /// Builds the block of one chunk from its terrain data, the chunk's world
    /// translation and its size in metres. Fails on a grid too small or
    /// inconsistent to have a visible cell, on non-finite heights, origin or
    /// size, and on a hole map whose size does not match its cells.
    pub fn new(data: &TerrainData, origin: DVec3, chunk_size: f64) -> Result<TerrainBlock, String> {
        check_placement(origin, chunk_size)?;
        let grid = &data.heights;
        if grid.width.checked_mul(grid.height) != Some(grid.heights.len()) {
            return Err(format!(
                "height grid says {}×{} but holds {} heights",
                grid.width,
                grid.height,
                grid.heights.len()
            ));
        }
        let visible = Visible::of(grid.width, grid.height, data.border)?;
        let heights = visible.crop(&grid.heights)?;
        let (low, high) = finite_extremes(&heights).map_err(|at| {
            let (x, z) = (at % visible.vx, at / visible.vx);
            format!(
                "height {} at visible sample ({x}, {z}) is not finite",
                heights[at]
            )
        })?;
        let range = HeightRange {
            low: low as f32,
            high: high as f32,
        };
        let block = TerrainBlock::laid_out(data.version, visible, origin, chunk_size, range);
        block.with_holes(data.holes.as_ref(), BlockHeights::Held(heights))
    }

    /// The block of [`TerrainBlock::new`] with its samples decoded when
    /// first read: `range` is the height range a block made by `new` from
    /// the same bytes found (kept by a cache), so it is not found again.
    /// Should decoding ever fail (it did not for these bytes before), the
    /// block is flat at its lowest height.
    pub fn deferred(
        data: DeferredTerrain,
        range: HeightRange,
        origin: DVec3,
        chunk_size: f64,
    ) -> Result<TerrainBlock, String> {
        check_placement(origin, chunk_size)?;
        let visible = Visible::of(data.width, data.height, data.border)?;
        if !range.is_sound() {
            return Err(format!("height range {range:?} is not finite"));
        }
        let block = TerrainBlock::laid_out(data.version, visible, origin, chunk_size, range);
        let samples = visible.vx * visible.vz;
        let encoded = data.heights;
        let decode = move || {
            let decoded = encoded.decode().ok();
            let heights = decoded.and_then(|map| visible.crop(&map.heights).ok());
            heights
                .filter(|h| h.len() == samples)
                .unwrap_or_else(|| vec![range.low; samples])
        };
        let heights = BlockHeights::Deferred(DeferredHeights::new(std::sync::Arc::new(decode)));
        block.with_holes(data.holes.as_ref(), heights)
    }

    /// The block read from the file whose content and entry `source` keys.
    pub fn with_source(mut self, source: Key) -> TerrainBlock {
        self.source = Some(source);
        self
    }

    /// A block of `visible`'s cells without samples or holes yet.
    fn laid_out(
        version: TerrainVersion,
        visible: Visible,
        origin: DVec3,
        chunk_size: f64,
        range: HeightRange,
    ) -> TerrainBlock {
        let (cells_x, cells_z) = (visible.vx - 1, visible.vz - 1);
        TerrainBlock {
            origin,
            chunk_size,
            version,
            cells_x,
            cells_z,
            spacing_x: chunk_size / cells_x as f64,
            spacing_z: chunk_size / cells_z as f64,
            heights: BlockHeights::Held(Vec::new()),
            cell_holes: Vec::new(),
            range,
            source: None,
        }
    }

    /// The block with `heights` and the cells `holes` marks; fails on a
    /// hole map whose size does not match its cells.
    fn with_holes(
        mut self,
        holes: Option<&HoleMap>,
        heights: BlockHeights,
    ) -> Result<TerrainBlock, String> {
        let (cells_x, cells_z) = (self.cells_x, self.cells_z);
        let mut cell_holes = Vec::new();
        if let Some(map) = holes {
            if map.width.checked_mul(map.height) != Some(map.holes.len()) {
                return Err(format!(
                    "hole map says {}×{} but holds {} cells",
                    map.width,
                    map.height,
                    map.holes.len()
                ));
            }
            // An empty map means no holes (the engine's noHoles()); a map
            // without a hole (most blocks) is not mapped cell by cell.
            if map.width > 0 && map.height > 0 && map.holes.contains(&true) {
                cell_holes = vec![false; cells_x * cells_z];
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
        if !cell_holes.contains(&true) {
            cell_holes = Vec::new();
        }
        self.cell_holes = cell_holes;
        self.heights = heights;
        Ok(self)
    }

    /// The lowest and highest visible sample.
    pub fn range(&self) -> HeightRange {
        self.range
    }

    /// What the block was read from, if from a file.
    pub fn source(&self) -> Option<&Key> {
        self.source.as_ref()
    }

    /// Whether its samples are in memory (held, or decoded by a reader).
    pub fn is_decoded(&self) -> bool {
        self.grid().heights.at_hand().is_some()
    }

    /// The samples, decoded now if no reader has yet.
    fn heights(&self) -> &[f32] {
        match &self.heights {
            BlockHeights::Held(heights) => heights,
            BlockHeights::Deferred(deferred) => deferred.get(),
        }
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
        self.heights()
            .get(z * (self.cells_x + 1) + x)
            .copied()
            .map(f64::from)
    }

    /// The block's samples as the tracer reads them: one vertex function,
    /// one hole and diagonal rule for the traced surface and for
    /// [`triangles`](Self::triangles).
    pub fn grid(&self) -> HeightGrid<'_> {
        HeightGrid {
            origin: self.origin,
            chunk_size: self.chunk_size,
            cells_x: self.cells_x,
            cells_z: self.cells_z,
            heights: match &self.heights {
                BlockHeights::Held(heights) => Heights::Held(heights),
                BlockHeights::Deferred(deferred) => Heights::Deferred(deferred),
            },
            holes: &self.cell_holes,
            alternating: self.version == TerrainVersion::Terrain2,
            extremes: (self.range.low, self.range.high),
        }
    }

    /// Visible height samples, decoded or not.
    pub fn samples(&self) -> usize {
        (self.cells_x + 1) * (self.cells_z + 1)
    }

    /// Bytes of height samples and hole flags once decoded.
    pub fn heap_bytes(&self) -> usize {
        self.samples() * 4 + self.cell_holes.len()
    }

    /// Whether height cell (cx, cz) is a hole (no triangles, no height).
    pub fn cell_is_hole(&self, cx: usize, cz: usize) -> bool {
        self.grid().is_hole(cx, cz)
    }

    /// Its drawn triangles: two per cell that is not a hole.
    pub fn visible_triangles(&self) -> usize {
        let holes = self.cell_holes.iter().filter(|&&hole| hole).count();
        2 * (self.cells_x * self.cells_z - holes)
    }

    /// Whether the cell's diagonal joins (x, z+1)–(x+1, z) rather than
    /// (x, z)–(x+1, z+1).
    pub fn cell_has_odd_diagonal(&self, cx: usize, cz: usize) -> bool {
        self.grid().has_odd_diagonal(cx, cz)
    }

    /// World-space box of the visible vertices (holes included).
    pub fn bounds(&self) -> (DVec3, DVec3) {
        let o = self.origin;
        (
            DVec3::new(o.x, o.y + f64::from(self.range.low), o.z),
            DVec3::new(
                o.x + self.chunk_size,
                o.y + f64::from(self.range.high),
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
        let odd = self.cell_has_odd_diagonal(cx, cz);
        let h = cell_height([h00, h10, h01, h11], odd, xf, zf);
        Some(self.origin.y + h)
    }

    /// The visible, non-hole triangles in world space, two per cell (row by
    /// row, x fastest), split along the cell's diagonal and wound so the
    /// geometric normal (v1 − v0) × (v2 − v0) points up (+y): the engine's
    /// vertex orders.
    pub fn triangles(&self) -> Vec<[DVec3; 3]> {
        let grid = self.grid();
        let holes = self.cell_holes.iter().filter(|&&h| h).count();
        let mut out = Vec::with_capacity(2 * (self.cells_x * self.cells_z - holes));
        for cz in 0..self.cells_z {
            for cx in 0..self.cells_x {
                if !self.cell_is_hole(cx, cz) {
                    out.extend(grid.cell_triangles(cx, cz));
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
/// The height inside one cell at fractions (`xf`, `zf`) from its corner
/// heights `[h00, h10, h01, h11]`, on the triangle the diagonal puts the
/// point in (`odd`: the (x, z+1)–(x+1, z) diagonal): the engine's
/// `heightAt`.
pub fn cell_height(corners: [f64; 4], odd: bool, xf: f64, zf: f64) -> f64 {
    let [h00, h10, h01, h11] = corners;
    if odd {
        if (1.0 - xf) > zf {
            h00 + (h10 - h00) * xf + (h01 - h00) * zf
        } else {
            h11 + (h01 - h11) * (1.0 - xf) + (h10 - h11) * (1.0 - zf)
        }
    } else if xf > zf {
        h10 + (h00 - h10) * (1.0 - xf) + (h11 - h10) * zf
    } else {
        h01 + (h11 - h01) * xf + (h00 - h01) * (1.0 - zf)
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::terrain::{HeightMap, HoleMap};
    use crate::rng::Rng;

    const SENTINEL: f32 = 1000.0;

    /// Visible vertex heights of the hand-worked 2×2 block, `[z][x]`.
    const VISIBLE: [[f32; 3]; 3] = [[0.0, 1.0, 0.0], [2.0, 0.0, 4.0], [0.0, 8.0, 0.0]];

    /// The 3×3 visible heights wrapped in a border of sentinel samples that
    /// must never show up in geometry.
    fn data(version: TerrainVersion, holes: Option<HoleMap>) -> TerrainData {
        let border = match version {
            TerrainVersion::Terrain2 => 2,
            TerrainVersion::Terrain1 => 1,
        };
        let w = 3 + 2 * border;
        let mut heights = vec![SENTINEL; w * w];
        for (z, row) in VISIBLE.iter().enumerate() {
            for (x, &h) in row.iter().enumerate() {
                heights[(z + border) * w + x + border] = h;
            }
        }
        TerrainData {
            version,
            heights: HeightMap {
                width: w,
                height: w,
                heights,
            },
            border,
            holes,
        }
    }

    const ORIGIN: DVec3 = DVec3::new(10.0, 5.0, 20.0);

    fn block(version: TerrainVersion, holes: Option<HoleMap>) -> TerrainBlock {
        TerrainBlock::new(&data(version, holes), ORIGIN, 2.0).unwrap()
    }

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < 1e-12)
    }

    #[test]
    fn terrain2_2x2_heights_worked_by_hand() {
        let b = block(TerrainVersion::Terrain2, None);
        assert_eq!(b.cells(), (2, 2));
        assert_eq!(b.spacing(), (1.0, 1.0));
        // (local x, local z, expected local height), see the comments.
        let cases = [
            // cell (0,0) even, diagonal (0,0)-(1,1). Lower-right triangle is
            // the plane h = x - z; upper-left is h = -2x + 2z.
            (0.75, 0.25, 0.5),
            (0.25, 0.75, 1.0),
            // cell (1,0) odd, diagonal (1,1)-(2,0). Triangle (1,0),(2,0),(1,1)
            // has h = 1 - fx - fz; triangle (2,1),(1,1),(2,0) has
            // h = 4 - 4(1-fx) - 4(1-fz).
            (1.25, 0.25, 0.5),
            (1.75, 0.75, 2.0),
            // Distinguishes the diagonal: an even split would give 0.8.
            (1.6, 0.1, 0.3),
            // cell (1,1) even: triangle (1,1),(2,1),(2,2): 4 - 4fx' ... at
            // (0.5, 0.25): 4 + (0-4)(0.5) + (0-4)(0.25) = 1.
            (1.5, 1.25, 1.0),
            // cell (0,1) odd: triangle (0,1),(1,1),(0,2): 2 - 2fx - 2fz.
            (0.25, 1.5, 0.5),
            // vertices and the far corner
            (1.0, 1.0, 0.0),
            (0.0, 1.0, 2.0),
            (2.0, 1.0, 4.0),
            (1.0, 2.0, 8.0),
            (2.0, 2.0, 0.0),
        ];
        for (lx, lz, h) in cases {
            let got = b.height_at(ORIGIN.x + lx, ORIGIN.z + lz);
            assert!(
                close(got, ORIGIN.y + h),
                "({lx}, {lz}): {got:?}, want {}",
                ORIGIN.y + h
            );
        }
        for (lx, lz) in [(-0.001, 1.0), (2.001, 1.0), (1.0, -0.001), (1.0, 2.001)] {
            assert_eq!(b.height_at(ORIGIN.x + lx, ORIGIN.z + lz), None);
        }
        let (lo, hi) = b.bounds();
        assert_eq!(lo, DVec3::new(10.0, 5.0, 20.0));
        assert_eq!(
            hi,
            DVec3::new(12.0, 13.0, 22.0),
            "border sentinels excluded"
        );
    }

    #[test]
    fn terrain1_never_alternates_the_diagonal() {
        let b = block(TerrainVersion::Terrain1, None);
        assert_eq!(b.cells(), (2, 2));
        // Cell (1,0) even here: triangle (1,0),(2,0),(2,1):
        // 0 + (1-0)(1-0.6) + (4-0)(0.1) = 0.8.
        assert!(close(b.height_at(11.6, 20.1), 5.8));
        assert!(!(0..2).any(|c| b.cell_has_odd_diagonal(c, 0) || b.cell_has_odd_diagonal(c, 1)));
    }

    #[test]
    fn triangles_face_up_and_follow_the_diagonals() {
        let b = block(TerrainVersion::Terrain2, None);
        let tris = b.triangles();
        assert_eq!(tris.len(), 8);
        for t in &tris {
            let n = (t[1] - t[0]).cross(t[2] - t[0]);
            assert!(n.y > 0.0, "{t:?} normal {n}");
            for v in t {
                assert!(v.y < 5.0 + 9.0, "border sample leaked: {v}");
            }
        }
        // Cell (1,0) is odd: its triangles share the edge (1,1)-(2,0).
        let p11 = DVec3::new(11.0, 5.0, 21.0);
        let p20 = DVec3::new(12.0, 5.0, 20.0);
        let cell10 = &tris[2..4];
        for t in cell10 {
            assert!(t.contains(&p11) && t.contains(&p20), "{t:?}");
        }
        // Cell (0,0) is even: both triangles hold (0,0) and (1,1).
        let p00 = DVec3::new(10.0, 5.0, 20.0);
        for t in &tris[0..2] {
            assert!(t.contains(&p00) && t.contains(&p11), "{t:?}");
        }
    }

    #[test]
    fn holes_remove_cells_from_both_queries() {
        // 2×2 hole map over 2×2 cells: hole at hole cell (1,0).
        let holes = HoleMap {
            width: 2,
            height: 2,
            holes: vec![false, true, false, false],
        };
        let b = block(TerrainVersion::Terrain2, Some(holes));
        assert_eq!(b.height_at(11.5, 20.5), None);
        assert!(b.is_hole(11.5, 20.5));
        assert!(!b.is_hole(10.5, 20.5));
        assert!(!b.is_hole(30.0, 20.5), "outside is not a hole");
        assert!(b.height_at(10.5, 20.5).is_some());
        assert_eq!(b.triangles().len(), 6);
        // A finer hole map: 4×4 hole cells of 0.5 m; cell (0,1) centre
        // (0.5, 1.5) falls in hole cell (1, 3).
        let mut fine = vec![false; 16];
        fine[3 * 4 + 1] = true;
        fine[0] = true; // hole cell (0,0) holds no cell centre: no effect
        let b = block(
            TerrainVersion::Terrain2,
            Some(HoleMap {
                width: 4,
                height: 4,
                holes: fine,
            }),
        );
        assert_eq!(b.triangles().len(), 6);
        assert!(b.cell_is_hole(0, 1));
        assert!(!b.cell_is_hole(0, 0));
        // An empty hole map means no holes.
        let b = block(
            TerrainVersion::Terrain2,
            Some(HoleMap {
                width: 0,
                height: 0,
                holes: vec![],
            }),
        );
        assert_eq!(b.triangles().len(), 8);
    }

    #[test]
    fn hole_index_takes_the_cell_centre() {
        // 2 cells over 3 hole cells: centres at 0.25 and 0.75 of the block.
        assert_eq!(hole_index(0, 2, 3), 0);
        assert_eq!(hole_index(1, 2, 3), 2);
        // 128 cells over 32 hole cells: 4 cells per hole cell.
        assert_eq!(hole_index(3, 128, 32), 0);
        assert_eq!(hole_index(4, 128, 32), 1);
        assert_eq!(hole_index(127, 128, 32), 31);
    }

    #[test]
    fn bad_blocks_are_refused() {
        let good = data(TerrainVersion::Terrain2, None);
        let mut d = good.clone();
        d.heights.heights.pop();
        assert!(TerrainBlock::new(&d, ORIGIN, 2.0).is_err());
        let mut d = good.clone();
        d.heights.heights[2 * 7 + 3] = f32::NAN;
        assert!(TerrainBlock::new(&d, ORIGIN, 2.0).is_err());
        // A NaN in the border is harmless.
        let mut d = good.clone();
        d.heights.heights[0] = f32::NAN;
        assert!(TerrainBlock::new(&d, ORIGIN, 2.0).is_ok());
        let mut d = good.clone();
        d.border = 3; // 7 - 6 = 1 visible sample: no cell
        assert!(TerrainBlock::new(&d, ORIGIN, 2.0).is_err());
        assert!(TerrainBlock::new(&good, ORIGIN, 0.0).is_err());
        assert!(TerrainBlock::new(&good, ORIGIN, f64::NAN).is_err());
        assert!(TerrainBlock::new(&good, DVec3::new(f64::INFINITY, 0.0, 0.0), 2.0).is_err());
        let mut d = good;
        d.holes = Some(HoleMap {
            width: 2,
            height: 2,
            holes: vec![true],
        });
        assert!(TerrainBlock::new(&d, ORIGIN, 2.0).is_err());
    }

    /// Height at (x, z) of the plane through `t`, if (x, z) is inside `t`'s
    /// xz projection by a margin (so edge points, which two triangles share,
    /// are skipped). Independent of the block's own cell logic.
    fn plane_height(t: &[DVec3; 3], x: f64, z: f64) -> Option<f64> {
        let (a, b, c) = (t[0], t[1], t[2]);
        let area = (b.x - a.x) * (c.z - a.z) - (c.x - a.x) * (b.z - a.z);
        let wa = ((b.x - x) * (c.z - z) - (c.x - x) * (b.z - z)) / area;
        let wb = ((c.x - x) * (a.z - z) - (a.x - x) * (c.z - z)) / area;
        let wc = 1.0 - wa - wb;
        let margin = 1e-9;
        (wa > margin && wb > margin && wc > margin).then_some(wa * a.y + wb * b.y + wc * c.y)
    }

    #[test]
    fn a_deferred_block_is_the_decoded_block_once_read() {
        use crate::formats::terrain::{read_terrain, read_terrain_deferred, write_terrain2_cdata};
        let mut rng = Rng::new(31);
        let (w, h) = (13, 11);
        let heights = HeightMap {
            width: w,
            height: h,
            heights: (0..w * h)
                .map(|_| (rng.unit() * 80.0 - 30.0) as f32)
                .collect(),
        };
        let holes = HoleMap {
            width: 8,
            height: 8,
            holes: (0..64).map(|_| rng.next_u64().is_multiple_of(5)).collect(),
        };
        let bytes = write_terrain2_cdata(&heights, Some(&holes));
        let origin = DVec3::new(-200.0, 3.5, 700.0);
        let eager = TerrainBlock::new(&read_terrain(&bytes, "terrain2").unwrap(), origin, 100.0);
        let eager = eager.unwrap();
        let data = read_terrain_deferred(&bytes, "terrain2").unwrap().unwrap();
        let deferred = TerrainBlock::deferred(data, eager.range(), origin, 100.0).unwrap();
        assert!(eager.is_decoded() && !deferred.is_decoded());
        // What the load and the top levels read needs no sample.
        assert_eq!(deferred.bounds(), eager.bounds());
        assert_eq!(deferred.cells(), eager.cells());
        assert_eq!(deferred.samples(), eager.samples());
        assert_eq!(deferred.visible_triangles(), eager.visible_triangles());
        let (nx, nz) = eager.cells();
        for (cx, cz) in (0..nz).flat_map(|cz| (0..nx).map(move |cx| (cx, cz))) {
            assert_eq!(deferred.cell_is_hole(cx, cz), eager.cell_is_hole(cx, cz));
        }
        let copy = deferred.clone();
        assert!(!deferred.is_decoded() && !copy.is_decoded());
        // The first height asked decodes the samples, the same ones.
        let (x, z) = (origin.x + 41.0, origin.z + 17.0);
        assert_eq!(deferred.height_at(x, z), eager.height_at(x, z));
        assert!(deferred.is_decoded() && !copy.is_decoded());
        for block in [&deferred, &copy] {
            assert_eq!(block.grid().heights.get(), eager.grid().heights.get());
            assert_eq!(block.triangles(), eager.triangles());
        }
        let holed = (0..nz).any(|cz| (0..nx).any(|cx| eager.cell_is_hole(cx, cz)));
        assert!(holed, "the seed gives the block a hole");
    }

    #[test]
    fn terrain1_is_never_deferred() {
        let bytes = crate::formats::binsection::MAGIC;
        let deferred = crate::formats::terrain::read_terrain_deferred(&bytes, "terrain");
        assert!(deferred.unwrap().is_none());
    }

    #[test]
    fn height_at_matches_the_triangles_at_random_points() {
        for (seed, version) in [
            (1u64, TerrainVersion::Terrain2),
            (7, TerrainVersion::Terrain1),
        ] {
            let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15 ^ seed);
            let border = if version == TerrainVersion::Terrain2 {
                2
            } else {
                1
            };
            let (cx, cz) = (6usize, 5usize);
            let (w, h) = (cx + 1 + 2 * border, cz + 1 + 2 * border);
            let heights = (0..w * h)
                .map(|_| (rng.unit() * 40.0 - 20.0) as f32)
                .collect();
            let holes = HoleMap {
                width: 3,
                height: 5,
                holes: (0..15).map(|_| rng.next_u64().is_multiple_of(4)).collect(),
            };
            let d = TerrainData {
                version,
                heights: HeightMap {
                    width: w,
                    height: h,
                    heights,
                },
                border,
                holes: Some(holes),
            };
            let origin = DVec3::new(-3100.0, 12.5, 4700.0);
            let b = TerrainBlock::new(&d, origin, 100.0).unwrap();
            let tris = b.triangles();
            let (mut solid, mut holed) = (0, 0);
            for _ in 0..4000 {
                // Some points fall outside the block on purpose.
                let x = origin.x - 5.0 + rng.unit() * 110.0;
                let z = origin.z - 5.0 + rng.unit() * 110.0;
                let expected = tris.iter().find_map(|t| plane_height(t, x, z));
                let got = b.height_at(x, z);
                match (got, expected) {
                    (Some(g), Some(e)) => {
                        assert!((g - e).abs() < 1e-9, "({x}, {z}): height_at {g}, plane {e}");
                        solid += 1;
                    }
                    (None, None) => {
                        let inside = (0.0..=100.0).contains(&(x - origin.x))
                            && (0.0..=100.0).contains(&(z - origin.z));
                        if inside {
                            assert!(b.is_hole(x, z), "({x}, {z})");
                            holed += 1;
                        }
                    }
                    (g, e) => {
                        // Only a point within the margin of an edge may
                        // find no triangle; it must still be solid ground.
                        assert!(
                            g.is_some() && e.is_none(),
                            "({x}, {z}): height_at {g:?}, triangles {e:?}"
                        );
                    }
                }
            }
            assert!(
                solid > 1000 && holed > 100,
                "{solid} solid, {holed} in holes"
            );
        }
    }
}
