//! What culling saves a light's shadow pass (docs/contract.md §8): the
//! casting instances, draw calls (primitive groups and terrain blocks)
//! and triangles in the light's reach, before culling (the game draws
//! every caster the light reaches when it has no masks) and after (those
//! whose bit the bake sets). Counted from the reach and the verdicts, no
//! ray traced. Receiver-only groups never enter a shadow pass; speedtrees
//! without a proxy have no geometry to count.

use super::casters::CasterTable;
use super::setup::{BakeWorld, Reach};
use super::trace_light::CasterSet;
use crate::scene::TerrainBlock;
use rayon::prelude::*;

/// One count before and after culling.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct BeforeAfter {
    pub before: u64,
    pub after: u64,
}

impl BeforeAfter {
    fn add(&mut self, amount: u64, kept: bool) {
        self.before += amount;
        if kept {
            self.after += amount;
        }
    }

    fn plus(self, other: BeforeAfter) -> BeforeAfter {
        BeforeAfter {
            before: self.before + other.before,
            after: self.after + other.after,
        }
    }
}

/// A light's shadow pass before and after culling.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Savings {
    /// Placed instances with a casting group in reach (an instance counts
    /// after culling while any of its groups is kept).
    pub instances: BeforeAfter,
    /// Primitive groups plus terrain blocks: the draw calls of the pass.
    pub draw_calls: BeforeAfter,
    pub triangles: BeforeAfter,
    /// The share of the pass's triangles culling removes, 0 to 1.
    pub triangles_removed: f64,
}

impl Savings {
    /// The counts of both (the share removed is found from the sum).
    fn plus(self, other: Savings) -> Savings {
        Savings {
            instances: self.instances.plus(other.instances),
            draw_calls: self.draw_calls.plus(other.draw_calls),
            triangles: self.triangles.plus(other.triangles),
            triangles_removed: 0.0,
        }
    }
}

/// The savings of a light whose reach is `reach` and whose kept casters
/// are `useful`.
pub fn of_light(world: &BakeWorld, reach: &Reach, useful: &CasterSet) -> Savings {
    // Parts come in caster id order, an instance's parts together: counted
    // instance by instance, in parallel (a world's millions of parts).
    let same_instance =
        |a: &u32, b: &u32| world.parts[*a as usize].instance == world.parts[*b as usize].instance;
    let mut savings = (reach.parts.par_chunk_by(same_instance))
        .map(|parts| of_instance(world, parts, useful))
        .reduce(Savings::default, Savings::plus);
    add_blocks(
        &mut savings,
        &world.casters,
        &world.scene.terrain,
        &reach.blocks,
        useful,
    );
    savings.triangles_removed = match savings.triangles.before {
        0 => 0.0,
        before => 1.0 - savings.triangles.after as f64 / before as f64,
    };
    savings
}

/// The savings of one instance's `parts` in reach (indices into
/// [`BakeWorld::parts`]): nothing for an instance that casts no shadow.
fn of_instance(world: &BakeWorld, parts: &[u32], useful: &CasterSet) -> Savings {
    let mut savings = Savings::default();
    let Some(&first) = parts.first() else {
        return savings;
    };
    let scene = world.scene;
    if !scene.instances[world.parts[first as usize].instance].casts_shadow {
        return savings;
    }
    let mut kept_any = false;
    for &index in parts {
        let part = &world.parts[index as usize];
        for (g, group) in scene.models[part.model].groups.iter().enumerate() {
            let kept = useful.contains(part.first_caster + g as u32);
            savings.draw_calls.add(1, kept);
            savings.triangles.add(group.triangles.len() as u64, kept);
            kept_any |= kept;
        }
    }
    savings.instances.add(1, kept_any);
    savings
}

fn add_blocks(
    savings: &mut Savings,
    casters: &CasterTable,
    terrain: &[TerrainBlock],
    blocks: &[u32],
    useful: &CasterSet,
) {
    for &block in blocks {
        let kept = useful.contains(casters.of_block[block as usize]);
        savings.draw_calls.add(1, kept);
        let triangles = terrain[block as usize].visible_triangles();
        savings.triangles.add(triangles as u64, kept);
    }
}
