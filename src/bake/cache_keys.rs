//! The keys of the bake cache's cells and what a cell's entry holds.
//!
//! A cell's value (the casters its rays prove useful) is a pure function
//! of the light's settings, the bake options that change a ray's answer,
//! the world's bounds (which place a directional light's grid), the cell,
//! and everything in its reach (`cells`): each part's model content, world
//! transform and `castsShadow`, each terrain block's content and origin,
//! and the blocks the below-ground test may read. A cell's key hashes
//! exactly those, under the cache's build identity, in the reach's scene
//! order.
//!
//! A value names its casters by their place in the cell's reach (the nth
//! part's group g, the nth block), never by caster id: ids shift when an
//! unrelated chunk gains an instance, places in a reach the key fixes do
//! not.

use super::cells::{CellReach, GroundNear};
use super::config::{settings_lines, BakeConfig};
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::CasterSet;
use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{Cache, Key, KeyHasher, Kind};
use crate::scene::SceneKeys;

/// An input of the cache's keys, for the tests that leave one out and
/// check that a bake then goes wrong (every input is needed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyInput {
    /// A part's model content key.
    PartModel,
    /// A part's world transform.
    PartTransform,
    /// A part's `castsShadow`.
    PartCastsShadow,
    /// A terrain block's content key.
    BlockContent,
    /// A terrain block's origin.
    BlockOrigin,
    /// The blocks the below-ground test reads near a cell's parts.
    GroundBlocks,
    /// Which cell of the grid.
    CellIndex,
    /// The light's own settings.
    LightSettings,
    /// The world's bounds (which place a directional light's grid).
    WorldBounds,
    /// The bake options.
    Options,
    /// A refined caster's cells.
    RefineCells,
    /// A refined caster's id and the light's position among the lights
    /// baked (its surface points' seed).
    RefineSeed,
    /// The refinement options.
    RefineOptions,
}

impl KeyInput {
    pub const ALL: [KeyInput; 13] = [
        KeyInput::PartModel,
        KeyInput::PartTransform,
        KeyInput::PartCastsShadow,
        KeyInput::BlockContent,
        KeyInput::BlockOrigin,
        KeyInput::GroundBlocks,
        KeyInput::CellIndex,
        KeyInput::LightSettings,
        KeyInput::WorldBounds,
        KeyInput::Options,
        KeyInput::RefineCells,
        KeyInput::RefineSeed,
        KeyInput::RefineOptions,
    ];
}

/// The keys of a world's blocks and what its parts' keys are made of,
/// computed once per bake and shared by its lights.
#[derive(Debug, Clone)]
pub struct WorldKeys {
    pub scene: SceneKeys,
    /// Per terrain block: its content key and origin.
    pub blocks: Vec<Key>,
    /// Per terrain block: its chunk (into `Scene::chunks`).
    pub block_chunks: Vec<usize>,
    /// The blocks the below-ground test may read near each part.
    pub ground: GroundNear,
    /// An input every key leaves out (the tests' sabotage; `None` in a
    /// real bake).
    pub left_out: Option<KeyInput>,
}

impl WorldKeys {
    /// The keys of `world`'s blocks from its scene's content keys `scene`.
    pub fn new(world: &BakeWorld, scene: SceneKeys, left_out: Option<KeyInput>) -> WorldKeys {
        let s = world.scene;
        let keep = |input: KeyInput| left_out != Some(input);
        let mut block_chunks = vec![0; s.terrain.len()];
        for (index, chunk) in s.chunks.iter().enumerate() {
            if let Some(block) = chunk.terrain {
                block_chunks[block] = index;
            }
        }
        let blocks = (0..s.terrain.len())
            .map(|b| {
                let mut h = KeyHasher::content("block");
                if keep(KeyInput::BlockContent) {
                    h.key(&scene.blocks[b]);
                }
                if keep(KeyInput::BlockOrigin) {
                    let o = s.terrain[b].origin();
                    h.f64(o.x).f64(o.y).f64(o.z);
                }
                h.finish()
            })
            .collect();
        let ground = GroundNear::of(world);
        WorldKeys {
            scene,
            blocks,
            block_chunks,
            ground,
            left_out,
        }
    }

    /// Appends what a ray can meet of part `p` (`BakeWorld::parts` order)
    /// to `out`: its model's content key, world transform and
    /// `castsShadow` (the mirrored flag follows from the transform), the
    /// same number of bytes for every part of a bake. Its chunk, element
    /// and resource name are not: where a value names it, its place in a
    /// reach is the part this content's reach holds there. Cells hash
    /// their parts' bytes in one run rather than a key per part: a whole
    /// world's parts are too many for a hash each on every bake.
    pub fn part_content(&self, world: &BakeWorld, p: u32, out: &mut Vec<u8>) {
        let part = &world.parts[p as usize];
        let instance = &world.scene.instances[part.instance];
        if self.keeps(KeyInput::PartModel) {
            out.extend_from_slice(&self.scene.models[part.model].0);
        }
        if self.keeps(KeyInput::PartTransform) {
            let mut bytes = [0u8; 128];
            for (to, v) in bytes
                .chunks_exact_mut(8)
                .zip(instance.world.to_cols_array())
            {
                to.copy_from_slice(&v.to_bits().to_le_bytes());
            }
            out.extend_from_slice(&bytes);
        }
        if self.keeps(KeyInput::PartCastsShadow) {
            out.push(u8::from(instance.casts_shadow));
        }
    }

    /// The key of part `p`'s [`WorldKeys::part_content`].
    pub fn part_key(&self, world: &BakeWorld, p: u32) -> Key {
        let mut content = Vec::new();
        self.part_content(world, p, &mut content);
        KeyHasher::content("part").bytes(&content).finish()
    }

    pub fn keeps(&self, input: KeyInput) -> bool {
        self.left_out != Some(input)
    }
}

/// The parts of a light's key a manifest compares, and the key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LightKey {
    /// The light's own settings.
    pub light: Key,
    /// The bake options that change a ray's answer (supersampling, grid
    /// mode, filter radius, face culling, height bias, tie epsilon, the
    /// grid offset, brute force).
    pub options: Key,
    /// A directional light's: the world's bounds, which its grid covers
    /// (its origin, size and rays' span follow from them).
    pub bounds: Key,
    /// All three under the cache's build identity.
    pub key: Key,
}

impl LightKey {
    /// The key of light `setup.index` of `config` over `world`: what its
    /// grid (`TexelGrid::new`) and its rays' rules are made from.
    pub fn new(
        cache: &Cache,
        world: &BakeWorld,
        setup: &LightSetup,
        config: &BakeConfig,
        keys: &WorldKeys,
    ) -> LightKey {
        // One light alone: its lines say nothing of its place among the
        // lights, so a `--light` subset shares its cells.
        let alone = BakeConfig {
            lights: vec![config.lights[setup.index].clone()],
            bits: Vec::new(),
            ..config.clone()
        };
        let (mut light, mut options) = (KeyHasher::content("light"), KeyHasher::content("options"));
        for (name, value) in settings_lines(&alone) {
            let hasher = if name.starts_with("lights/") {
                &mut light
            } else {
                &mut options
            };
            hasher.str(&name).str(&value);
        }
        let mut bounds = KeyHasher::content("bounds");
        if setup.grid.direction().is_some() && keys.keeps(KeyInput::WorldBounds) {
            if let Some((min, max)) = world.bounds {
                for v in [min, max] {
                    bounds.f64(v.x).f64(v.y).f64(v.z);
                }
            }
        }
        let finish = |hasher: KeyHasher, input: KeyInput, domain: &str| match keys.keeps(input) {
            true => hasher.finish(),
            false => KeyHasher::content(domain).finish(),
        };
        let light = finish(light, KeyInput::LightSettings, "light");
        let options = finish(options, KeyInput::Options, "options");
        let bounds = bounds.finish();
        let key = cache
            .hasher(Kind::Cell)
            .key(&light)
            .key(&options)
            .key(&bounds)
            .finish();
        LightKey {
            light,
            options,
            bounds,
            key,
        }
    }
}

/// The key of cell `cell` of a light whose key is `light`.
/// `scratch` holds the parts' bytes (a megabyte or more for a big
/// world's cell): one buffer per thread, not one allocation per cell.
pub fn cell_key(
    light: &LightKey,
    cell: u64,
    reach: &CellReach,
    world: &BakeWorld,
    keys: &WorldKeys,
    scratch: &mut Vec<u8>,
) -> Key {
    let c = cell as usize;
    let mut h = KeyHasher::content("cell");
    h.key(&light.key);
    if keys.keeps(KeyInput::CellIndex) {
        h.u64(cell);
    }
    h.u64(reach.parts[c].len() as u64);
    scratch.clear();
    for &p in &reach.parts[c] {
        keys.part_content(world, p, scratch);
    }
    h.bytes(scratch);
    h.u64(reach.blocks[c].len() as u64);
    for &b in &reach.blocks[c] {
        h.key(&keys.blocks[b as usize]);
    }
    if keys.keeps(KeyInput::GroundBlocks) {
        h.u64(reach.ground[c].len() as u64);
        for &b in &reach.ground[c] {
            h.key(&keys.blocks[b as usize]);
        }
    }
    h.finish()
}

/// The casters a cell's rays prove useful, by their place in its reach.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CellValue {
    /// (position in the cell's parts, group of that part's model),
    /// ascending.
    pub parts: Vec<(u32, u32)>,
    /// Positions in the cell's blocks, ascending.
    pub blocks: Vec<u32>,
}

/// A cell's lists of what it reaches: the parts and the blocks it can hit.
#[derive(Clone, Copy)]
pub struct CellLists<'r> {
    pub parts: &'r [u32],
    pub blocks: &'r [u32],
}

impl<'r> CellLists<'r> {
    pub fn of(reach: &'r CellReach, cell: u64) -> CellLists<'r> {
        CellLists {
            parts: &reach.parts[cell as usize],
            blocks: &reach.blocks[cell as usize],
        }
    }
}

impl CellValue {
    /// The casters of `lists` that `useful` holds (a cell's rays can prove
    /// no other).
    pub fn of(useful: &CasterSet, world: &BakeWorld, lists: CellLists) -> CellValue {
        let mut value = CellValue::default();
        for (position, &p) in lists.parts.iter().enumerate() {
            let part = &world.parts[p as usize];
            let groups = world.scene.models[part.model].groups.len() as u32;
            for group in 0..groups {
                if useful.contains(part.first_caster + group) {
                    value.parts.push((position as u32, group));
                }
            }
        }
        for (position, &b) in lists.blocks.iter().enumerate() {
            if useful.contains(world.casters.of_block[b as usize]) {
                value.blocks.push(position as u32);
            }
        }
        value
    }

    /// Caster ids of the value, through the cell's `lists`.
    pub fn casters<'v>(
        &'v self,
        world: &'v BakeWorld,
        lists: CellLists<'v>,
    ) -> impl Iterator<Item = u32> + 'v {
        let parts = self.parts.iter().map(move |&(position, group)| {
            world.parts[lists.parts[position as usize] as usize].first_caster + group
        });
        let blocks = self
            .blocks
            .iter()
            .map(move |&position| world.casters.of_block[lists.blocks[position as usize] as usize]);
        parts.chain(blocks)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut e = Encoder::new();
        e.var(self.parts.len() as u64);
        let mut last = 0;
        for &(position, group) in &self.parts {
            e.var(u64::from(position - last)).var(u64::from(group));
            last = position;
        }
        e.var(self.blocks.len() as u64);
        let mut last = 0;
        for &position in &self.blocks {
            e.var(u64::from(position - last));
            last = position;
        }
        e.into_bytes()
    }

    /// The value `bytes` hold, if every place it names is in `lists`
    /// (and every group in its part's model): `None` for a value of
    /// another shape.
    pub fn decode(bytes: &[u8], world: &BakeWorld, lists: CellLists) -> Option<CellValue> {
        let mut d = Decoder::new(bytes);
        let mut value = CellValue::default();
        let n = d.len(2).ok()?;
        let mut position = 0u64;
        for _ in 0..n {
            position += d.var().ok()?;
            let group = d.var().ok()?;
            let &p = lists.parts.get(usize::try_from(position).ok()?)?;
            let model = world.parts[p as usize].model;
            if group >= world.scene.models[model].groups.len() as u64 {
                return None;
            }
            value.parts.push((position as u32, group as u32));
        }
        let n = d.len(1).ok()?;
        let mut position = 0u64;
        for _ in 0..n {
            position += d.var().ok()?;
            lists.blocks.get(usize::try_from(position).ok()?)?;
            value.blocks.push(position as u32);
        }
        d.is_done().then_some(value)
    }
}
