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

/// The savings of a light whose reach is `reach` and whose kept casters
/// are `useful`.
pub fn of_light(world: &BakeWorld, reach: &Reach, useful: &CasterSet) -> Savings {
    let scene = world.scene;
    let mut savings = Savings::default();
    // Parts come in caster id order, an instance's parts together.
    let mut current: Option<(usize, bool)> = None;
    for &index in &reach.parts {
        let part = &world.parts[index as usize];
        let instance = &scene.instances[part.instance];
        if !instance.casts_shadow {
            continue;
        }
        let mut kept_any = false;
        for (g, group) in scene.models[part.model].groups.iter().enumerate() {
            let kept = useful.contains(part.first_caster + g as u32);
            savings.draw_calls.add(1, kept);
            savings.triangles.add(group.triangles.len() as u64, kept);
            kept_any |= kept;
        }
        current = match current {
            Some((at, kept)) if at == part.instance => Some((at, kept || kept_any)),
            previous => {
                count_instance(&mut savings, previous);
                Some((part.instance, kept_any))
            }
        };
    }
    count_instance(&mut savings, current);
    add_blocks(
        &mut savings,
        &world.casters,
        &scene.terrain,
        &reach.blocks,
        useful,
    );
    savings.triangles_removed = match savings.triangles.before {
        0 => 0.0,
        before => 1.0 - savings.triangles.after as f64 / before as f64,
    };
    savings
}

fn count_instance(savings: &mut Savings, instance: Option<(usize, bool)>) {
    if let Some((_, kept)) = instance {
        savings.instances.add(1, kept);
    }
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
