//! The caster table: every primitive group of every placed instance and
//! every terrain block gets a dense id, the unit the bake classifies and the
//! traced triangles point back to.

use crate::scene::Scene;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Owner {
    /// Group `group` of part `part` (its `<resource>` position) of
    /// `Scene::instances[instance]`.
    Group {
        instance: usize,
        part: usize,
        group: usize,
    },
    Terrain {
        block: usize,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Caster {
    pub owner: Owner,
    pub alpha_tested: bool,
    pub double_sided: bool,
    /// A group of a `castsShadow` false instance: hit, but never a caster.
    pub receiver_only: bool,
}

impl Caster {
    pub fn is_terrain(&self) -> bool {
        matches!(self.owner, Owner::Terrain { .. })
    }
}

#[derive(Debug, Clone, Default)]
pub struct CasterTable {
    pub casters: Vec<Caster>,
    /// Per instance: the id of its first group (its groups are contiguous,
    /// part by part in `<resource>` order), or `None` for an instance left
    /// out of the bake (a part failed to load).
    pub first_of_instance: Vec<Option<u32>>,
    /// Per terrain block: its id.
    pub of_block: Vec<u32>,
}

impl CasterTable {
    pub fn new(scene: &Scene) -> CasterTable {
        let mut table = CasterTable::default();
        for (index, instance) in scene.instances.iter().enumerate() {
            if !instance.is_complete() {
                table.first_of_instance.push(None);
                continue;
            }
            table
                .first_of_instance
                .push(Some(table.casters.len() as u32));
            for (part, model) in instance.parts.iter().flatten().enumerate() {
                for (group, flags) in scene.models[*model].groups.iter().enumerate() {
                    table.casters.push(Caster {
                        owner: Owner::Group {
                            instance: index,
                            part,
                            group,
                        },
                        alpha_tested: flags.alpha_tested,
                        double_sided: flags.double_sided,
                        receiver_only: !instance.casts_shadow,
                    });
                }
            }
        }
        for block in 0..scene.terrain.len() {
            table.of_block.push(table.casters.len() as u32);
            table.casters.push(Caster {
                owner: Owner::Terrain { block },
                alpha_tested: false,
                double_sided: false,
                receiver_only: false,
            });
        }
        table
    }

    pub fn len(&self) -> usize {
        self.casters.len()
    }

    pub fn is_empty(&self) -> bool {
        self.casters.is_empty()
    }

    /// Casters that can be useful (everything but receiver-only groups).
    pub fn real_casters(&self) -> usize {
        self.casters.iter().filter(|c| !c.receiver_only).count()
    }
}
