//! Terrain height data of a chunk: terrain2 `.cdata` ZIPs
//! (terrain/terrain_height_map2.*) and terrain1 blocks.

use crate::error::FormatError;

/// Heights in metres, row-major: `heights[z * width + x]`, chunk-local,
/// including the format's border samples.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightGrid {
    pub width: usize,
    pub height: usize,
    pub heights: Vec<f32>,
}

/// Holes over the visible part of the block, row-major, `true` = hole.
#[derive(Debug, Clone, PartialEq)]
pub struct HoleMap {
    pub width: usize,
    pub height: usize,
    pub holes: Vec<bool>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TerrainVersion {
    Terrain1,
    Terrain2,
}

#[derive(Debug, Clone, PartialEq)]
pub struct TerrainData {
    pub version: TerrainVersion,
    pub heights: HeightGrid,
    /// Border samples on each side of `heights` that are not geometry
    /// (2 for terrain2, 1 for terrain1).
    pub border: usize,
    pub holes: Option<HoleMap>,
}

/// Reads the terrain named by a chunk's `<terrain><resource>`: `cdata` is the
/// `.cdata` file's bytes and `entry` the part after it (`terrain2` or
/// `terrain`).
pub fn read_terrain(cdata: &[u8], entry: &str) -> Result<TerrainData, FormatError> {
    let _ = (cdata, entry);
    Err(FormatError::whole_file("terrain: not implemented yet"))
}

/// A terrain2 `.cdata` ZIP holding `terrain2/heights` (version 4 PNG) and,
/// if given, `terrain2/holes`. Byte-deterministic.
pub fn write_terrain2_cdata(heights: &HeightGrid, holes: Option<&HoleMap>) -> Vec<u8> {
    let _ = (heights, holes);
    Vec::new()
}
