//! placeholder until the terrain branch lands
use crate::formats::terrain::TerrainData;
use glam::DVec3;
#[derive(Debug, Clone)]
pub struct TerrainBlock;
impl TerrainBlock {
    pub fn new(data: &TerrainData, origin: DVec3, chunk_size: f64) -> Result<TerrainBlock, String> {
        let _ = (data, origin, chunk_size);
        Err("x".into())
    }
}
