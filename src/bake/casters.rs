//! The caster table: every primitive group of every placed instance and
//! every terrain block gets a dense id, the unit the bake classifies and the
//! traced hits point back to.
//!
//! This is the one place that defines the id order (docs/contract.md §2):
//! complete instances in scene order, their parts in `<resource>` order,
//! each part's groups in model order; then terrain blocks in scene order.
//! Scene order is chunk by chunk, a chunk's `<model>`/`<shell>` instances
//! in document order, then its `<speedtree>`s in document order: a tree's
//! one part is its proxy, and a tree without a proxy has one id of its own
//! ([`Owner::Unmodelled`]) that no ray can hit. Everything that needs a
//! part's ids walks [`CasterTable::parts`].

use crate::scene::{Instance, Scene};
use rayon::prelude::*;

/// What a caster is. Indices are u32 (the caster ids themselves are):
/// a table entry is 20 bytes, held for every group of every placed
/// instance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Owner {
    /// Group `group` of part `part` (its `<resource>` position) of
    /// `Scene::instances[instance]`.
    Group {
        instance: u32,
        part: u32,
        group: u32,
    },
    Terrain {
        block: u32,
    },
    /// `Scene::instances[instance]`, a speedtree without a proxy: no
    /// geometry, kept for every light (docs/contract.md §4).
    Unmodelled {
        instance: u32,
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

    /// A caster the bake cannot model: kept for every light, never hit.
    pub fn is_unmodelled(&self) -> bool {
        matches!(self.owner, Owner::Unmodelled { .. })
    }
}

/// One model part of a placed instance and its first caster id.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PartCasters {
    /// Into `Scene::instances`.
    pub instance: usize,
    /// Position among the instance's `<resource>` parts.
    pub part: usize,
    /// Into `Scene::models`.
    pub model: usize,
    pub first_caster: u32,
}

#[derive(Debug, Clone, Default)]
pub struct CasterTable {
    pub casters: Vec<Caster>,
    /// Per instance: the id of its first group (its groups are contiguous,
    /// part by part in `<resource>` order; an unmodelled speedtree's one
    /// id), or `None` for an instance left out of the bake (a part failed
    /// to load).
    pub first_of_instance: Vec<Option<u32>>,
    /// Per terrain block: its id.
    pub of_block: Vec<u32>,
    /// The double-sided casters as bits of their ids (64 a word): the ones
    /// face culling never drops (`trace::FaceCull`).
    pub double_sided: Vec<u64>,
    /// The receiver-only casters as bits of their ids: settled from the
    /// start of every grid pass (they are never useful), copied rather than
    /// found caster by caster for each of a cached bake's cells.
    pub receiver_only: Vec<u64>,
    /// The unmodelled casters ([`Owner::Unmodelled`]) as bits of their ids:
    /// kept for every light, set word by word in each light's verdicts.
    pub unmodelled_bits: Vec<u64>,
}

impl CasterTable {
    pub fn new(scene: &Scene) -> CasterTable {
        // An instance's first id is the sum of the counts before it: counted
        // and filled in parallel (millions of instances on a large world),
        // summed in order.
        let counts: Vec<Option<u32>> = scene
            .instances
            .par_iter()
            .map(|instance| caster_count(scene, instance))
            .collect();
        let mut first_of_instance = Vec::with_capacity(counts.len());
        let mut next = 0u32;
        for count in counts {
            first_of_instance.push(count.map(|_| next));
            next += count.unwrap_or(0);
        }
        // Exact sizes: the table is held for the whole bake, and growing
        // by doubling left up to half of it unused.
        let mut casters = Vec::with_capacity(next as usize + scene.terrain.len());
        casters.par_extend(
            scene
                .instances
                .par_iter()
                .enumerate()
                .flat_map_iter(|(index, instance)| instance_casters(scene, index, instance)),
        );
        let mut of_block = Vec::with_capacity(scene.terrain.len());
        for block in 0..scene.terrain.len() {
            of_block.push(casters.len() as u32);
            casters.push(Caster {
                owner: Owner::Terrain {
                    block: block as u32,
                },
                alpha_tested: false,
                double_sided: false,
                receiver_only: false,
            });
        }
        let bits = |flag: fn(&Caster) -> bool| -> Vec<u64> {
            let words = casters.par_chunks(64).map(|word| {
                let set = word.iter().enumerate().filter(|(_, c)| flag(c));
                set.fold(0u64, |bits, (bit, _)| bits | 1 << bit)
            });
            words.collect()
        };
        CasterTable {
            double_sided: bits(|c| c.double_sided),
            receiver_only: bits(|c| c.receiver_only),
            unmodelled_bits: bits(Caster::is_unmodelled),
            casters,
            first_of_instance,
            of_block,
        }
    }

    pub fn len(&self) -> usize {
        self.casters.len()
    }

    /// The ids of instance `index` (`Scene::instances`): its groups part by
    /// part, or an unmodelled speedtree's one id; empty for an instance
    /// left out of the bake.
    pub fn of_instance(&self, scene: &Scene, index: usize) -> std::ops::Range<u32> {
        let Some(first) = self.first_of_instance[index] else {
            return 0..0;
        };
        let instance = &scene.instances[index];
        let count = if instance.is_unmodelled() {
            1
        } else {
            instance
                .parts
                .iter()
                .flatten()
                .map(|&m| scene.models[m].groups.len() as u32)
                .sum()
        };
        first..first + count
    }

    /// The ids of the casters the bake cannot model, kept for every light.
    pub fn unmodelled(&self) -> impl Iterator<Item = u32> + '_ {
        set_bits(&self.unmodelled_bits)
    }

    /// Every model part of every instance in the bake, in id order, with the
    /// id of its group 0 (group g of the part is `first_caster + g`).
    pub fn parts<'s>(&'s self, scene: &'s Scene) -> impl Iterator<Item = PartCasters> + 's {
        scene
            .instances
            .iter()
            .enumerate()
            .flat_map(move |(index, instance)| self.instance_parts(scene, index, instance))
    }

    /// [`CasterTable::parts`] in parallel (collected, still in id order):
    /// millions of instances on a large world.
    pub fn par_parts<'s>(
        &'s self,
        scene: &'s Scene,
    ) -> impl ParallelIterator<Item = PartCasters> + 's {
        scene
            .instances
            .par_iter()
            .enumerate()
            .flat_map_iter(move |(index, instance)| self.instance_parts(scene, index, instance))
    }

    /// The parts of instance `index`, in id order.
    fn instance_parts<'s>(
        &'s self,
        scene: &'s Scene,
        index: usize,
        instance: &'s Instance,
    ) -> impl Iterator<Item = PartCasters> + 's {
        let first = self.first_of_instance[index];
        let mut next = first.unwrap_or(0);
        let models = first.map(|_| instance.parts.iter().flatten());
        models
            .into_iter()
            .flatten()
            .enumerate()
            .map(move |(part, &model)| {
                let first_caster = next;
                next += scene.models[model].groups.len() as u32;
                PartCasters {
                    instance: index,
                    part,
                    model,
                    first_caster,
                }
            })
    }

    pub fn is_empty(&self) -> bool {
        self.casters.is_empty()
    }

    /// Casters that can be useful (everything but receiver-only groups).
    pub fn real_casters(&self) -> usize {
        let receivers: u32 = self.receiver_only.iter().map(|w| w.count_ones()).sum();
        self.casters.len() - receivers as usize
    }
}

/// The positions of the set bits of `words` (64 a word), ascending.
pub(crate) fn set_bits(words: &[u64]) -> impl Iterator<Item = u32> + '_ {
    words.iter().enumerate().flat_map(|(w, &word)| {
        let mut rest = word;
        std::iter::from_fn(move || {
            (rest != 0).then(|| {
                let bit = rest.trailing_zeros();
                rest &= rest - 1;
                w as u32 * 64 + bit
            })
        })
    })
}

/// How many ids `instance` takes: `None` when it is left out of the bake,
/// one for an unmodelled speedtree, else one per group of each part.
fn caster_count(scene: &Scene, instance: &Instance) -> Option<u32> {
    if !instance.is_complete() {
        return None;
    }
    let groups = instance.parts.iter().flatten();
    let groups: usize = groups.map(|&m| scene.models[m].groups.len()).sum();
    Some((groups + usize::from(instance.is_unmodelled())) as u32)
}

/// The casters of instance `index`, in id order.
fn instance_casters<'a>(
    scene: &'a Scene,
    index: usize,
    instance: &'a Instance,
) -> impl Iterator<Item = Caster> + 'a {
    let complete = instance.is_complete();
    let unmodelled = (complete && instance.is_unmodelled()).then_some(Caster {
        owner: Owner::Unmodelled {
            instance: index as u32,
        },
        alpha_tested: false,
        double_sided: false,
        receiver_only: false,
    });
    let parts = instance.parts.iter().flatten().enumerate();
    let groups = parts
        .filter(move |_| complete)
        .flat_map(move |(part, &model)| {
            let groups = scene.models[model].groups.iter().enumerate();
            groups.map(move |(group, flags)| Caster {
                owner: Owner::Group {
                    instance: index as u32,
                    part: part as u32,
                    group: group as u32,
                },
                alpha_tested: flags.alpha_tested,
                double_sided: flags.double_sided,
                receiver_only: !instance.casts_shadow,
            })
        });
    unmodelled.into_iter().chain(groups)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::ResPaths;
    use crate::formats::chunk::InstanceKind;
    use crate::scene::{load_scene, LoadConfig};

    /// The committed `village` fixture, speedtrees without proxies.
    fn village() -> Scene {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/worlds/village");
        load_scene(&LoadConfig {
            res_paths: ResPaths::new(vec![root]),
            space: "spaces/village".into(),
            speedtrees: Default::default(),
        })
        .expect("the village fixture loads")
    }

    #[test]
    fn parts_walk_the_ids_in_table_order() {
        let scene = village();
        let table = CasterTable::new(&scene);
        let mut expected = 0u32;
        for part in table.parts(&scene) {
            assert_eq!(part.first_caster, expected);
            for group in 0..scene.models[part.model].groups.len() {
                let caster = &table.casters[part.first_caster as usize + group];
                assert_eq!(
                    caster.owner,
                    Owner::Group {
                        instance: part.instance as u32,
                        part: part.part as u32,
                        group: group as u32
                    }
                );
            }
            expected += scene.models[part.model].groups.len() as u32;
        }
        assert_eq!(
            expected,
            table.of_block.first().copied().unwrap_or(expected)
        );
        assert!(expected > 100);
        let in_parallel: Vec<PartCasters> = table.par_parts(&scene).collect();
        assert_eq!(in_parallel, table.parts(&scene).collect::<Vec<_>>());
    }

    #[test]
    fn real_casters_are_those_not_receiver_only() {
        let scene = village();
        let table = CasterTable::new(&scene);
        let receivers = table.casters.iter().filter(|c| c.receiver_only).count();
        assert!(receivers > 0, "the village has castsShadow false instances");
        assert_eq!(table.real_casters(), table.len() - receivers);
    }

    #[test]
    fn speedtrees_take_ids_after_their_chunks_models_whatever_the_file_order() {
        let dir = tempfile::tempdir().unwrap();
        let world = crate::gen::generate(crate::gen::Preset::Forest, 3);
        crate::files::write_tree(dir.path(), &world.files).unwrap();
        let settings =
            crate::files::read_bake_settings(&dir.path().join(crate::gen::SETTINGS_FILE)).unwrap();
        let scene = load_scene(&LoadConfig::from_settings(&settings)).unwrap();
        assert!(scene.problems.is_empty(), "{:?}", scene.problems);
        let table = CasterTable::new(&scene);
        let first_terrain = table.of_block[0];
        let mut next = 0;
        let mut trees_before_models_in_a_file = false;
        for chunk in &scene.chunks {
            let ids = |kind: InstanceKind| -> Vec<std::ops::Range<u32>> {
                chunk
                    .instances
                    .clone()
                    .filter(|&i| scene.instances[i].kind.names_models() == kind.names_models())
                    .map(|i| table.of_instance(&scene, i))
                    .collect()
            };
            let (models, trees) = (ids(InstanceKind::Model), ids(InstanceKind::SpeedTree));
            // Models, then trees, each in document order, without gaps.
            for range in models.iter().chain(&trees) {
                assert_eq!(range.start, next, "{}", chunk.name);
                next = range.end;
            }
            let tree_indices: Vec<usize> = chunk
                .instances
                .clone()
                .filter(|&i| scene.instances[i].kind == InstanceKind::SpeedTree)
                .map(|i| scene.instances[i].index)
                .collect();
            assert_eq!(
                tree_indices,
                (0..chunk.speedtree_elements).collect::<Vec<_>>()
            );
            let text = std::fs::read(&chunk.file).unwrap();
            if !models.is_empty() && !trees.is_empty() && text.starts_with(b"<") {
                let text = String::from_utf8(text).unwrap();
                trees_before_models_in_a_file |=
                    text.find("<speedtree>").unwrap() < text.find("<model>").unwrap();
            }
        }
        assert_eq!(next, first_terrain, "terrain blocks last");
        assert!(
            trees_before_models_in_a_file,
            "the order is the ids', not the file's"
        );
        assert!(scene.stats().speedtrees > 22);
        let mut expected = 0u32;
        for part in table.parts(&scene) {
            assert_eq!(part.first_caster, expected);
            expected += scene.models[part.model].groups.len() as u32;
        }
        assert_eq!(expected, first_terrain);
    }

    #[test]
    fn a_speedtree_without_a_proxy_has_one_id_no_ray_can_hit() {
        let dir = tempfile::tempdir().unwrap();
        let world = crate::gen::generate(crate::gen::Preset::Forest, 3);
        crate::files::write_tree(dir.path(), &world.files).unwrap();
        let settings =
            crate::files::read_bake_settings(&dir.path().join(crate::gen::SETTINGS_FILE)).unwrap();
        let config = LoadConfig {
            speedtrees: Default::default(),
            ..LoadConfig::from_settings(&settings)
        };
        let scene = load_scene(&config).unwrap();
        let table = CasterTable::new(&scene);
        let trees = scene.instances.iter().filter(|i| i.is_unmodelled()).count();
        assert_eq!(trees, scene.stats().speedtrees);
        let unmodelled: Vec<u32> = (0..table.len() as u32)
            .filter(|&id| table.casters[id as usize].is_unmodelled())
            .collect();
        assert_eq!(unmodelled.len(), trees);
        assert_eq!(table.unmodelled().collect::<Vec<_>>(), unmodelled);
        for (index, instance) in scene.instances.iter().enumerate() {
            let ids = table.of_instance(&scene, index);
            if instance.is_unmodelled() {
                assert_eq!(ids.len(), 1);
                assert_eq!(
                    table.casters[ids.start as usize].owner,
                    Owner::Unmodelled {
                        instance: index as u32
                    }
                );
            }
        }
        assert!(table
            .parts(&scene)
            .all(|p| !scene.instances[p.instance].is_unmodelled()));
    }
}
