//! The bake's memory model: what each thing the bake holds costs, so a
//! world's peak can be predicted before it is loaded, checked by a test
//! (`tests/it/memory.rs`) and shown by `shadowcull plan`. The figures are
//! heap bytes measured with heaptrack on `gen --chunks 20` and `gen
//! --preset bench` (release build); change them only with a new
//! measurement.
//!
//! Memory grows with distinct geometry, placed instances, height samples,
//! terrain blocks and threads, never with placed triangles: a model placed a thousand
//! times costs its bottom level once and a top-level entry per placement.

/// Heap bytes per distinct model triangle: its positions and indices in
/// the scene (~20) and its bottom-level BVH (~60: nodes, slot table, the
/// precomputed triangle).
pub const PER_DISTINCT_TRIANGLE: u64 = 80;
/// Heap bytes per placed instance in the scene: the 200-byte record
/// (f64 transform, chunk, index, flags) and its resource names and parts
/// (290 measured), and where its element's `<shadow>` goes in the chunk
/// file (a 20-byte place, `formats::shadow_write::Site`).
pub const PER_INSTANCE: u64 = 310;
/// Heap bytes per caster (primitive group or terrain block): the caster
/// table's 20-byte entry (u32 owner indices, flags) and its share of the
/// per-part index (34 bytes a part, 1.4 casters a part on `gen --chunks
/// 20`).
pub const PER_CASTER: u64 = 45;
/// Heap bytes per placed part in a light's reach while its top level is
/// built: the box (32), the obvhs build's temporaries (PLOC, BVH2,
/// compressed-wide conversion: ~300) and the bake's part record (34).
/// Once built, an entry holds 141 bytes (f64 inverse transform, node share).
pub const PER_PART_IN_REACH: u64 = 370;
/// Heap bytes per terrain height sample: the f32 sample (4) and its share
/// of the min/max pyramid (1.3: two u16 a 2×2-cell tile, a third more for
/// the levels above); hole flags add one byte per cell, only in blocks
/// that have holes.
pub const PER_HEIGHT_SAMPLE: f64 = 5.3;
/// Heap bytes per terrain block for the below-ground test's ceilings
/// (`bake::ground`): 64 squares a chunk of the blocks' grid, each a 4-byte
/// bound and a 4-byte start into the list of blocks near it, the starts
/// held twice while the list is built, with a one-chunk border (a third
/// more on a 10×10 grid, 4 % on 96×96); and the list, each block under the
/// 100 squares its cells come near (counted, not measured: 1 300 is
/// 1.17 × 64 × 12 + 400).
pub const PER_TERRAIN_BLOCK: u64 = 1300;
/// Resident bytes per worker thread beyond the heap: its malloc arena's
/// slack and the touched part of its stack (scratch hit lists and
/// traversal stacks are a few kilobytes).
pub const PER_THREAD: u64 = 2 << 20;
/// Resident bytes of a bake that holds nothing: the binary, its libraries,
/// the main thread.
pub const FIXED: u64 = 16 << 20;
/// Peak resident set over peak heap: allocator slack and fragmentation,
/// little since the binary hands freed pages back at every phase
/// (`malloc_trim`; see docs/performance.md).
pub const RESIDENT_PER_HEAP: f64 = 1.05;

/// What a world holds, as the memory model counts it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WorldSize {
    pub distinct_triangles: u64,
    pub instances: u64,
    pub casters: u64,
    /// Placed parts in the reach of the light that reaches most.
    pub parts_in_reach: u64,
    pub height_samples: u64,
    pub terrain_blocks: u64,
}

/// Predicted peak heap bytes: everything the scene and the bake's world
/// hold, plus the largest light's top level while it is built (lights are
/// set up one at a time).
pub fn peak_heap(world: &WorldSize) -> u64 {
    world.distinct_triangles * PER_DISTINCT_TRIANGLE
        + world.instances * PER_INSTANCE
        + world.casters * PER_CASTER
        + world.parts_in_reach * PER_PART_IN_REACH
        + (world.height_samples as f64 * PER_HEIGHT_SAMPLE) as u64
        + world.terrain_blocks * PER_TERRAIN_BLOCK
}

/// Predicted peak resident set of a bake with `threads` workers.
pub fn peak_resident(world: &WorldSize, threads: usize) -> u64 {
    (peak_heap(world) as f64 * RESIDENT_PER_HEAP) as u64 + FIXED + PER_THREAD * threads as u64
}

impl WorldSize {
    /// The counts of a loaded scene, taking every placed part as in reach
    /// (the sun of a world usually reaches all of it).
    pub fn of(scene: &crate::scene::Scene) -> WorldSize {
        let casters = crate::bake::casters::CasterTable::new(scene);
        WorldSize {
            distinct_triangles: scene.models.iter().map(|m| m.triangles.len() as u64).sum(),
            instances: scene.instances.len() as u64,
            casters: casters.len() as u64,
            parts_in_reach: casters.parts(scene).count() as u64,
            height_samples: scene.terrain.iter().map(|t| t.samples() as u64).sum(),
            terrain_blocks: scene.terrain.len() as u64,
        }
    }
}
