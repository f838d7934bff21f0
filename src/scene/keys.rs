//! The content keys of a scene's models and terrain blocks: one hash per
//! distinct model and per block of exactly what the bake reads of it, so a
//! bake cache can tell an edited model or block from an unchanged one
//! without comparing geometry. Everything a cached result depends on
//! reaches it through these keys; a bake that reuses a loaded scene's
//! entries may fill [`SceneKeys`] from where it stored them instead.

use super::terrain::TerrainBlock;
use super::{Model, Scene};
use crate::cache::{Key, KeyHasher};
use rayon::prelude::*;

/// Per model (in `Scene::models` order) and per terrain block (in
/// `Scene::terrain` order), the key of its content.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SceneKeys {
    pub models: Vec<Key>,
    pub blocks: Vec<Key>,
}

impl SceneKeys {
    /// The keys of `scene`'s models and blocks, hashed in parallel.
    pub fn of(scene: &Scene) -> SceneKeys {
        SceneKeys {
            models: scene.models.par_iter().map(model_key).collect(),
            blocks: scene.terrain.par_iter().map(block_key).collect(),
        }
    }
}

/// What the bake uses of a model: its positions and triangles, each
/// group's triangles and flags, and the layout of its `<shadow>`.
pub fn model_key(model: &Model) -> Key {
    let mut hasher = KeyHasher::content("model");
    hasher.u64(model.positions.len() as u64);
    for p in &model.positions {
        hasher.f32(p.x).f32(p.y).f32(p.z);
    }
    hasher.u64(model.triangles.len() as u64);
    for t in &model.triangles {
        hasher.u32(t[0]).u32(t[1]).u32(t[2]);
    }
    hasher.u64(model.groups.len() as u64);
    for g in &model.groups {
        hasher
            .u64(g.render_set as u64)
            .u64(g.geometry as u64)
            .u64(g.primitive_group as u64)
            .u64(g.triangles.start as u64)
            .u64(g.triangles.end as u64)
            .bool(g.alpha_tested)
            .bool(g.double_sided);
    }
    hasher.u64(model.layout.len() as u64);
    for geometries in &model.layout {
        hasher.u64(geometries.len() as u64);
        for &groups in geometries {
            hasher.u64(groups as u64);
        }
    }
    hasher.finish()
}

/// What the bake uses of a terrain block apart from where it lies: its
/// samples and holes — as the content key of the file and entry they were
/// read from, which may not be decoded, or as themselves for a block made
/// in memory —, cells, diagonal rule and chunk size.
pub fn block_key(block: &TerrainBlock) -> Key {
    let grid = block.grid();
    let mut hasher = KeyHasher::content("terrain");
    hasher
        .f64(grid.chunk_size)
        .u64(grid.cells_x as u64)
        .u64(grid.cells_z as u64)
        .bool(grid.alternating);
    match block.source() {
        Some(source) => {
            hasher.str("read from").key(source);
        }
        None => {
            let heights = grid.heights.get();
            let holes: Vec<u8> = grid.holes.iter().map(|&hole| u8::from(hole)).collect();
            hasher
                .str("samples")
                .u64(heights.len() as u64)
                .f32s(heights)
                .bytes(&holes);
        }
    }
    hasher.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn a_model_key_changes_with_anything_the_bake_reads() {
        let model = Model {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            triangles: vec![[0, 1, 2]],
            groups: vec![super::super::Group {
                render_set: 0,
                geometry: 0,
                primitive_group: 0,
                triangles: 0..1,
                alpha_tested: false,
                double_sided: false,
            }],
            layout: vec![vec![1]],
            ..Model::default()
        };
        let key = model_key(&model);
        assert_eq!(key, model_key(&model.clone()));
        type Edit = Box<dyn Fn(&mut Model)>;
        let edits: Vec<Edit> = vec![
            Box::new(|m| m.positions[1].x = 2.0),
            Box::new(|m| m.triangles[0] = [0, 2, 1]),
            Box::new(|m| m.groups[0].alpha_tested = true),
            Box::new(|m| m.groups[0].double_sided = true),
            Box::new(|m| m.groups[0].triangles = 0..0),
            Box::new(|m| m.layout = vec![vec![1], vec![]]),
        ];
        for (n, edit) in edits.iter().enumerate() {
            let mut edited = model.clone();
            edit(&mut edited);
            assert_ne!(model_key(&edited), key, "edit {n}");
        }
        // The resource name is not content: the same geometry elsewhere.
        let renamed = Model {
            resource: "other.model".into(),
            ..model.clone()
        };
        assert_eq!(model_key(&renamed), key);
    }

    /// A block's key changes with any sample, any hole and its chunk size,
    /// and not with where it lies (its origin is the cell key's).
    #[test]
    fn a_block_key_changes_with_anything_the_bake_reads() {
        use crate::formats::terrain::{HeightMap, HoleMap, TerrainData, TerrainVersion};
        use glam::DVec3;
        let data = |heights: Vec<f32>, holes: Vec<bool>| TerrainData {
            version: TerrainVersion::Terrain2,
            heights: HeightMap {
                width: 7,
                height: 7,
                heights,
            },
            border: 2,
            holes: Some(HoleMap {
                width: 2,
                height: 2,
                holes,
            }),
        };
        let heights: Vec<f32> = (0..49).map(|i| i as f32 * 0.25).collect();
        let block = |d: &TerrainData, origin: DVec3, size: f64| {
            TerrainBlock::new(d, origin, size).expect("a valid block")
        };
        let plain = data(heights.clone(), vec![false; 4]);
        let key = block_key(&block(&plain, DVec3::ZERO, 4.0));
        assert_eq!(
            key,
            block_key(&block(&plain, DVec3::new(400.0, 3.0, 8.0), 4.0))
        );
        let mut raised = heights.clone();
        raised[3 * 7 + 3] += 0.5;
        let holed = data(heights.clone(), vec![false, false, true, false]);
        for (what, other) in [
            (
                "a sample",
                block(&data(raised, vec![false; 4]), DVec3::ZERO, 4.0),
            ),
            ("a hole", block(&holed, DVec3::ZERO, 4.0)),
            ("the chunk size", block(&plain, DVec3::ZERO, 8.0)),
        ] {
            assert_ne!(block_key(&other), key, "{what}");
        }
    }
}
