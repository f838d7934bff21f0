//! Micro worlds built in memory for the rule tests (`bake_rules`,
//! `occlusion`, `ground`, `nomiss` and others): a few chunks, meshes placed
//! by hand, terrain from a height function, a directional light, and `run`,
//! which bakes a world and checks its masks against the brute-force oracle.
//! The tests that build them work out the expected masks from each world's
//! design.

use glam::{DMat4, DVec3, Vec3};
use shadowcull::bake::{self, BakeConfig, BakeResult, Silent};
use shadowcull::formats::bake_settings::{FaceCulling, LightKind, LightSettings};
use shadowcull::formats::chunk::InstanceKind;
use shadowcull::formats::space_settings::SpaceSettings;
use shadowcull::formats::terrain::{HeightMap, HoleMap, TerrainData, TerrainVersion};
use shadowcull::scene::{Chunk, Group, Instance, Model, Scene, TerrainBlock};

/// Chunk size of micro worlds (metres).
pub const CHUNK: f64 = 16.0;

#[derive(Clone, Copy, Default)]
pub struct Flags {
    pub alpha_tested: bool,
    pub double_sided: bool,
}

pub const OPAQUE: Flags = Flags {
    alpha_tested: false,
    double_sided: false,
};
pub const TWO_SIDED: Flags = Flags {
    alpha_tested: false,
    double_sided: true,
};
pub const CANOPY: Flags = Flags {
    alpha_tested: true,
    double_sided: true,
};

/// A mesh group: triangles as corner positions (front = counter-clockwise
/// seen from the side the normal points to).
pub struct Mesh {
    pub groups: Vec<(Vec<[Vec3; 3]>, Flags)>,
}

/// Axis-aligned closed box, outward-facing.
pub fn cube(min: Vec3, max: Vec3) -> Vec<[Vec3; 3]> {
    let c = |i: usize| {
        Vec3::new(
            if i & 1 == 0 { min.x } else { max.x },
            if i & 2 == 0 { min.y } else { max.y },
            if i & 4 == 0 { min.z } else { max.z },
        )
    };
    // Faces as corner index quads, wound outward.
    let faces = [
        [0, 2, 3, 1], // -z
        [4, 5, 7, 6], // +z
        [0, 4, 6, 2], // -x
        [1, 3, 7, 5], // +x
        [0, 1, 5, 4], // -y
        [2, 6, 7, 3], // +y
    ];
    let mut triangles = Vec::new();
    for [a, b, c2, d] in faces {
        triangles.push([c(a), c(b), c(c2)]);
        triangles.push([c(a), c(c2), c(d)]);
    }
    triangles
}

/// Horizontal quad at height y facing up (+y), from (x0, z0) to (x1, z1).
pub fn quad_up(x0: f32, z0: f32, x1: f32, z1: f32, y: f32) -> Vec<[Vec3; 3]> {
    let a = Vec3::new(x0, y, z0);
    let b = Vec3::new(x1, y, z0);
    let c = Vec3::new(x1, y, z1);
    let d = Vec3::new(x0, y, z1);
    // (d - a) × (b - a) points up: wind a, d, c / a, c, b.
    vec![[a, d, c], [a, c, b]]
}

pub fn flipped(triangles: Vec<[Vec3; 3]>) -> Vec<[Vec3; 3]> {
    triangles.into_iter().map(|[a, b, c]| [a, c, b]).collect()
}

pub struct World {
    pub scene: Scene,
    /// Grid of the chunk that tests call (0, 0): non-zero for a translated
    /// copy of a world (see [`World::new_at`]).
    origin: (i32, i32),
}

impl World {
    /// An empty world of `nx` × `nz` chunks starting at grid (0, 0).
    pub fn new(nx: i32, nz: i32) -> World {
        World::new_at(nx, nz, DVec3::ZERO)
    }

    /// The same empty world moved by `offset`: x and z by whole chunks (so
    /// the chunk grid and the below-ground lookup move with it; they must be
    /// multiples of [`CHUNK`]), y through the chunk transforms. Tests keep
    /// calling the chunks (0, 0), (1, 0), …: the offset is applied here, so
    /// one build function makes the world at the origin and far from it.
    pub fn new_at(nx: i32, nz: i32, offset: DVec3) -> World {
        let gx = offset.x / CHUNK;
        let gz = offset.z / CHUNK;
        assert!(
            gx.fract() == 0.0 && gz.fract() == 0.0,
            "offset {offset} is not a whole number of chunks"
        );
        let origin = (gx as i32, gz as i32);
        let mut chunks = Vec::new();
        for x in origin.0..origin.0 + nx {
            for z in origin.1..origin.1 + nz {
                chunks.push(Chunk {
                    name: shadowcull::formats::space_settings::outdoor_chunk_name(x, z),
                    file: format!("{x}_{z}.chunk").into(),
                    file_key: None,
                    grid: Some((x, z)),
                    transform: DMat4::from_translation(DVec3::new(
                        x as f64 * CHUNK,
                        offset.y,
                        z as f64 * CHUNK,
                    )),
                    instances: 0..0,
                    instance_elements: 0,
                    speedtree_elements: 0,
                    terrain: None,
                    sites: None,
                });
            }
        }
        chunks.sort_by(|a, b| a.name.cmp(&b.name));
        World {
            scene: Scene {
                space_dir: "micro".into(),
                settings: SpaceSettings {
                    min_x: origin.0,
                    max_x: origin.0 + nx - 1,
                    min_z: origin.1,
                    max_z: origin.1 + nz - 1,
                    chunk_size: CHUNK,
                    single_dir: false,
                    terrain_version: Some(200),
                    height_map_size: Some(8),
                },
                chunks,
                models: Vec::new(),
                instances: Vec::new(),
                terrain: Vec::new(),
                items: Vec::new(),
                problems: Vec::new(),
                inputs: Vec::new(),
            },
            origin,
        }
    }

    fn chunk_index(&self, grid: (i32, i32)) -> usize {
        let grid = (grid.0 + self.origin.0, grid.1 + self.origin.1);
        self.scene
            .chunks
            .iter()
            .position(|c| c.grid == Some(grid))
            .expect("chunk in the world")
    }

    pub fn model(&mut self, mesh: Mesh) -> usize {
        let mut model = Model {
            resource: format!("micro/{}.model", self.scene.models.len()),
            ..Model::default()
        };
        let mut layout = Vec::new();
        for (index, (triangles, flags)) in mesh.groups.into_iter().enumerate() {
            let first = model.triangles.len();
            for triangle in triangles {
                let base = model.positions.len() as u32;
                model.positions.extend(triangle);
                model.triangles.push([base, base + 1, base + 2]);
            }
            model.groups.push(Group {
                render_set: 0,
                geometry: 0,
                primitive_group: index,
                triangles: first..model.triangles.len(),
                alpha_tested: flags.alpha_tested,
                double_sided: flags.double_sided,
            });
            layout.push(1);
        }
        model.layout = vec![vec![layout.len()]];
        self.scene.models.push(model);
        self.scene.models.len() - 1
    }

    /// Places models in chunk `grid` with a chunk-local transform; returns
    /// the instance's index in the scene.
    pub fn place(
        &mut self,
        grid: (i32, i32),
        parts: &[usize],
        local: DMat4,
        casts_shadow: bool,
    ) -> usize {
        let chunk = self.chunk_index(grid);
        let world = self.scene.chunks[chunk].transform * local;
        // Keep instances grouped by chunk in chunk order.
        let insert_at = self.scene.chunks[chunk].instances.end;
        let index_in_chunk = self.scene.chunks[chunk].instance_elements;
        self.scene.instances.insert(
            insert_at,
            Instance {
                chunk,
                index: index_in_chunk,
                kind: InstanceKind::Model,
                resources: parts
                    .iter()
                    .map(|p| self.scene.models[*p].resource.clone())
                    .collect(),
                parts: parts.iter().map(|p| Some(*p)).collect(),
                world,
                mirrored: world.determinant() < 0.0,
                casts_shadow,
            },
        );
        for (i, c) in self.scene.chunks.iter_mut().enumerate() {
            if i == chunk {
                c.instances.end += 1;
                c.instance_elements += 1;
            } else if c.instances.start >= insert_at && i > chunk {
                c.instances.start += 1;
                c.instances.end += 1;
            }
        }
        insert_at
    }

    /// Terrain for chunk `grid`: 8×8 cells, height from `h(x, z)` (chunk-local).
    pub fn terrain(&mut self, grid: (i32, i32), h: impl Fn(f64, f64) -> f64) {
        self.terrain_of(grid, 8, h);
    }

    /// Terrain for chunk `grid` with `cells` × `cells` cells.
    pub fn terrain_of(&mut self, grid: (i32, i32), cells: usize, h: impl Fn(f64, f64) -> f64) {
        self.terrain_with_holes(grid, cells, h, |_, _| false);
    }

    /// [`World::terrain_of`] with a hole in every cell whose centre (chunk
    /// local) `hole` names.
    pub fn terrain_with_holes(
        &mut self,
        grid: (i32, i32),
        cells: usize,
        h: impl Fn(f64, f64) -> f64,
        hole: impl Fn(f64, f64) -> bool,
    ) {
        let chunk = self.chunk_index(grid);
        let width = cells + 5;
        let spacing = CHUNK / cells as f64;
        let mut heights = Vec::new();
        for z in 0..width {
            for x in 0..width {
                let lx = (x as f64 - 2.0) * spacing;
                let lz = (z as f64 - 2.0) * spacing;
                heights.push(h(lx, lz) as f32);
            }
        }
        let data = TerrainData {
            version: TerrainVersion::Terrain2,
            heights: HeightMap {
                width,
                height: width,
                heights,
            },
            border: 2,
            holes: None,
        };
        let spacing_holes = CHUNK / cells as f64;
        let holes: Vec<bool> = (0..cells * cells)
            .map(|i| {
                let (cx, cz) = (i % cells, i / cells);
                hole(
                    (cx as f64 + 0.5) * spacing_holes,
                    (cz as f64 + 0.5) * spacing_holes,
                )
            })
            .collect();
        let data = TerrainData {
            holes: holes.contains(&true).then_some(HoleMap {
                width: cells,
                height: cells,
                holes,
            }),
            ..data
        };
        let origin = self.scene.chunks[chunk].transform.w_axis.truncate();
        // Heights are chunk-local; the chunk's own y lifts the block.
        let block = TerrainBlock::new(&data, origin, CHUNK).expect("valid block");
        self.scene.chunks[chunk].terrain = Some(self.scene.terrain.len());
        self.scene.terrain.push(block);
    }
}

pub fn directional(direction: DVec3, texel: f64) -> LightSettings {
    LightSettings {
        name: "sun".into(),
        kind: LightKind::Directional {
            direction: direction.normalize(),
            texel_size: texel,
        },
    }
}

pub fn config(lights: Vec<LightSettings>) -> BakeConfig {
    BakeConfig {
        face_culling: FaceCulling::Back,
        height_bias: 0.05,
        tie_epsilon: 1e-4,
        lights,
        brute_force: false,
        ..Default::default()
    }
}

pub fn run(world: &World, config: &BakeConfig) -> BakeResult {
    let result = bake::bake(&world.scene, config, &Silent).expect("bake");
    // Every micro world must give the same masks with the brute-force
    // oracle: a second check of the BVH path on every rule.
    let oracle = bake::bake(
        &world.scene,
        &BakeConfig {
            brute_force: true,
            ..config.clone()
        },
        &Silent,
    )
    .expect("oracle bake");
    assert_eq!(result.masks, oracle.masks, "BVH and brute force disagree");
    result
}

/// The group masks of instance `instance` (all parts, in order).
pub fn instance_masks(result: &BakeResult, world: &World, instance: usize) -> Vec<u32> {
    let first = result.casters.first_of_instance[instance].expect("baked instance") as usize;
    let groups: usize = world.scene.instances[instance]
        .parts
        .iter()
        .flatten()
        .map(|m| world.scene.models[*m].groups.len())
        .sum();
    result.masks[first..first + groups].to_vec()
}

pub fn terrain_mask(result: &BakeResult, block: usize) -> u32 {
    result.masks[result.casters.of_block[block] as usize]
}
