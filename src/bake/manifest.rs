//! A light's manifest: what its cells' keys were made of at its last bake
//! with this cache, so a cell traced again can say which input changed
//! ("chunk 00010002o", "model sets/house.model", "terrain of chunk
//! 00000001o", "the light", "the options", "the world's bounds"). Only words come of
//! it: a manifest never decides a mask, and a missing or unreadable one
//! only makes the words vaguer ("no earlier bake").
//!
//! A cell's record keeps, besides its key, short digests of its inputs by
//! name: per chunk, the placements of its parts there (identity, resource,
//! transform, flags); per model, its content key; per terrain block, its
//! content and origin.

use super::cache_keys::{LightKey, WorldKeys};
use super::cells::CellReach;
use super::setup::BakeWorld;
use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{Cache, Key, KeyHasher, Kind};
use rayon::prelude::*;
use std::collections::BTreeMap;

/// What one cell's key was made of.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CellRecord {
    /// `None`: nothing in its reach.
    pub key: Option<Key>,
    /// Per chunk with parts in its reach: the digest of their placements.
    pub chunks: Vec<(String, u64)>,
    /// Per model placed in its reach: its content key.
    pub models: Vec<(String, u64)>,
    /// Per terrain block in its reach or read by its below-ground test
    /// (named by its chunk): its content and origin.
    pub terrain: Vec<(String, u64)>,
}

/// A light's cells as its last bake saw them.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Manifest {
    pub build: Key,
    pub light: LightDigests,
    pub cells: Vec<CellRecord>,
}

/// The parts of a light's key that concern every cell.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LightDigests {
    pub light: Key,
    pub options: Key,
    /// The world's bounds (a directional light's grid covers them).
    pub bounds: Key,
}

impl From<&LightKey> for LightDigests {
    fn from(key: &LightKey) -> Self {
        LightDigests {
            light: key.light,
            options: key.options,
            bounds: key.bounds,
        }
    }
}

/// Why a cell was traced again: an input that differs from its record.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
pub struct Because {
    /// `chunk`, `model`, `terrain`, `light`, `options`, `bounds`, `build`
    /// (another shadowcull), `new` (no earlier bake of this light in this
    /// cache, or a cell it did not have) or `missing` (same inputs, entry
    /// evicted or damaged).
    pub input: &'static str,
    /// The chunk, model, or terrain block's chunk.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
}

impl Because {
    fn of(input: &'static str) -> Because {
        Because { input, name: None }
    }

    fn named(input: &'static str, name: &str) -> Because {
        Because {
            input,
            name: Some(name.to_string()),
        }
    }

    /// For people: `chunk 00010002o`, `the light`.
    pub fn describe(&self) -> String {
        match (&self.name, self.input) {
            (Some(name), "terrain") => format!("terrain of chunk {name}"),
            (Some(name), input) => format!("{input} {name}"),
            (None, "new") => "no earlier bake".into(),
            (None, "missing") => "entry evicted or damaged".into(),
            (None, "build") => "another shadowcull build".into(),
            (None, "bounds") => "the world's bounds (the light's grid moved)".into(),
            (None, input) => format!("the {input}"),
        }
    }
}

/// The key of light `name`'s manifest (every build shares it: a new build
/// reads the old one to say so).
pub fn manifest_key(space: &str, name: &str) -> Key {
    KeyHasher::across_builds(Kind::Manifest)
        .str(space)
        .str(name)
        .finish()
}

/// The records of every cell of a light (in cell order). A cell whose key
/// is the one `old` recorded keeps its record: the same key holds the
/// same placements, models and blocks, and a world's parts are too many
/// to describe again on every bake.
pub fn records(
    world: &BakeWorld,
    keys: &WorldKeys,
    reach: &CellReach,
    cell_keys: &[Option<Key>],
    old: Option<&Manifest>,
) -> Vec<CellRecord> {
    let scene = world.scene;
    (0..cell_keys.len())
        .into_par_iter()
        .map(|c| {
            let recorded = old.and_then(|old| old.cells.get(c));
            if let Some(record) = recorded.filter(|r| r.key.is_some() && r.key == cell_keys[c]) {
                return record.clone();
            }
            let mut record = CellRecord {
                key: cell_keys[c],
                ..CellRecord::default()
            };
            let mut chunks: BTreeMap<usize, KeyHasher> = BTreeMap::new();
            let mut models: BTreeMap<usize, u64> = BTreeMap::new();
            for &p in &reach.parts[c] {
                let part = &world.parts[p as usize];
                let chunk = scene.instances[part.instance].chunk;
                chunks
                    .entry(chunk)
                    .or_insert_with(|| KeyHasher::content("chunk placements"))
                    .key(&placement_key(world, p));
                models.insert(part.model, keys.scene.models[part.model].short());
            }
            record.chunks = chunks
                .into_iter()
                .map(|(c, h)| (scene.chunks[c].name.clone(), h.finish().short()))
                .collect();
            record.models = models
                .into_iter()
                .map(|(m, k)| (scene.models[m].resource.clone(), k))
                .collect();
            let mut blocks: Vec<u32> = reach.blocks[c]
                .iter()
                .chain(&reach.ground[c])
                .copied()
                .collect();
            blocks.sort_unstable();
            blocks.dedup();
            record.terrain = blocks
                .into_iter()
                .map(|b| {
                    let chunk = &scene.chunks[keys.block_chunks[b as usize]];
                    (chunk.name.clone(), keys.blocks[b as usize].short())
                })
                .collect();
            record
        })
        .collect()
}

/// Part `p`'s chunk, element, part, resource name, transform and flags,
/// without its model's content (a manifest's words).
fn placement_key(world: &BakeWorld, p: u32) -> Key {
    let scene = world.scene;
    let part = &world.parts[p as usize];
    let instance = &scene.instances[part.instance];
    let mut h = KeyHasher::content("placement");
    h.str(&scene.chunks[instance.chunk].name)
        .u64(instance.index as u64)
        .u64(part.part as u64)
        .str(&scene.models[part.model].resource);
    for v in instance.world.to_cols_array() {
        h.f64(v);
    }
    h.bool(instance.casts_shadow).finish()
}

/// Why cell `cell` (now `record`) was traced again, given the manifest of
/// the light's last bake (`None`: none) and this bake's `light` digests
/// and `build`.
pub fn because(
    old: Option<&Manifest>,
    build: &Key,
    light: &LightDigests,
    cell: usize,
    record: &CellRecord,
) -> Vec<Because> {
    let Some(old) = old else {
        return vec![Because::of("new")];
    };
    if old.build != *build {
        return vec![Because::of("build")];
    }
    for (input, before, now) in [
        ("light", old.light.light, light.light),
        ("options", old.light.options, light.options),
        ("bounds", old.light.bounds, light.bounds),
    ] {
        if before != now {
            return vec![Because::of(input)];
        }
    }
    let Some(before) = old.cells.get(cell) else {
        return vec![Because::of("new")];
    };
    let mut why = Vec::new();
    for (input, a, b) in [
        ("chunk", &before.chunks, &record.chunks),
        ("terrain", &before.terrain, &record.terrain),
    ] {
        why.extend(differences(a, b).map(|name| Because::named(input, name)));
    }
    // A model placed or no longer placed here is its chunk's change; one
    // on both sides with other content is the model's.
    let before_models: BTreeMap<&str, u64> = before
        .models
        .iter()
        .map(|(n, k)| (n.as_str(), *k))
        .collect();
    for (name, key) in &record.models {
        if before_models.get(name.as_str()).is_some_and(|k| k != key) {
            why.push(Because::named("model", name));
        }
    }
    if why.is_empty() {
        why.push(Because::of(if before.key == record.key {
            "missing"
        } else {
            "new"
        }));
    }
    why
}

/// The names whose digests differ between `a` and `b`, or that only one
/// holds.
fn differences<'n>(
    a: &'n [(String, u64)],
    b: &'n [(String, u64)],
) -> impl Iterator<Item = &'n str> + 'n {
    let a_map: BTreeMap<&str, u64> = a.iter().map(|(n, k)| (n.as_str(), *k)).collect();
    let b_map: BTreeMap<&str, u64> = b.iter().map(|(n, k)| (n.as_str(), *k)).collect();
    let mut names: Vec<&str> = a_map.keys().chain(b_map.keys()).copied().collect();
    names.sort_unstable();
    names.dedup();
    names
        .into_iter()
        .filter(move |n| a_map.get(n) != b_map.get(n))
}

impl Manifest {
    /// The manifest stored under `key`, if there is one that decodes. One
    /// that passes its entry's checks but does not decode was written by
    /// a build that lays manifests out otherwise (every build shares the
    /// key): no earlier record, and no warning; this bake's replaces it.
    pub fn load(cache: &Cache, key: &Key) -> Option<Manifest> {
        Manifest::decode(&cache.get(Kind::Manifest, key)?)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut names: BTreeMap<&str, u64> = BTreeMap::new();
        for record in &self.cells {
            for (name, _) in record
                .chunks
                .iter()
                .chain(&record.models)
                .chain(&record.terrain)
            {
                let next = names.len() as u64;
                names.entry(name.as_str()).or_insert(next);
            }
        }
        let mut ordered: Vec<(&str, u64)> = names.iter().map(|(n, i)| (*n, *i)).collect();
        ordered.sort_unstable_by_key(|&(_, i)| i);
        let mut e = Encoder::new();
        for key in [
            &self.build,
            &self.light.light,
            &self.light.options,
            &self.light.bounds,
        ] {
            e.bytes(&key.0);
        }
        e.var(ordered.len() as u64);
        for (name, _) in &ordered {
            e.str(name);
        }
        e.var(self.cells.len() as u64);
        for record in &self.cells {
            match &record.key {
                Some(key) => e.u8(1).bytes(&key.0),
                None => e.u8(0),
            };
            for list in [&record.chunks, &record.models, &record.terrain] {
                e.var(list.len() as u64);
                for (name, digest) in list {
                    e.var(names[name.as_str()]).u64(*digest);
                }
            }
        }
        e.into_bytes()
    }

    pub fn decode(bytes: &[u8]) -> Option<Manifest> {
        let mut d = Decoder::new(bytes);
        let mut key = || -> Option<Key> { Some(Key(d.bytes().ok()?.try_into().ok()?)) };
        let (build, light, options, bounds) = (key()?, key()?, key()?, key()?);
        let names: Vec<String> = (0..d.len(1).ok()?)
            .map(|_| d.str().ok())
            .collect::<Option<_>>()?;
        let count = d.len(1).ok()?;
        let mut cells = Vec::with_capacity(count);
        for _ in 0..count {
            let key = match d.u8().ok()? {
                0 => None,
                1 => Some(Key(d.bytes().ok()?.try_into().ok()?)),
                _ => return None,
            };
            let mut lists: [Vec<(String, u64)>; 3] = Default::default();
            for list in &mut lists {
                for _ in 0..d.len(9).ok()? {
                    let name = names.get(usize::try_from(d.var().ok()?).ok()?)?;
                    list.push((name.clone(), d.u64().ok()?));
                }
            }
            let [chunks, models, terrain] = lists;
            cells.push(CellRecord {
                key,
                chunks,
                models,
                terrain,
            });
        }
        d.is_done().then_some(Manifest {
            build,
            light: LightDigests {
                light,
                options,
                bounds,
            },
            cells,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(
        chunks: &[(&str, u64)],
        models: &[(&str, u64)],
        terrain: &[(&str, u64)],
    ) -> CellRecord {
        let own = |l: &[(&str, u64)]| l.iter().map(|(n, k)| (n.to_string(), *k)).collect();
        CellRecord {
            key: Some(Key([7; 32])),
            chunks: own(chunks),
            models: own(models),
            terrain: own(terrain),
        }
    }

    #[test]
    fn a_manifest_reads_back_and_names_what_changed() {
        let light = LightDigests {
            light: Key([1; 32]),
            options: Key([2; 32]),
            bounds: Key([3; 32]),
        };
        let old = Manifest {
            build: Key([9; 32]),
            light,
            cells: vec![
                record(&[("a", 1), ("b", 2)], &[("m.model", 5)], &[("a", 3)]),
                CellRecord::default(),
            ],
        };
        let bytes = old.encode();
        assert_eq!(Manifest::decode(&bytes), Some(old.clone()));
        for cut in 0..bytes.len() {
            assert_eq!(Manifest::decode(&bytes[..cut]), None, "cut at {cut}");
        }
        let names = |why: Vec<Because>| why.iter().map(Because::describe).collect::<Vec<_>>();
        let build = Key([9; 32]);
        let moved = record(&[("a", 1), ("b", 4)], &[("m.model", 5)], &[("a", 3)]);
        assert_eq!(
            names(because(Some(&old), &build, &light, 0, &moved)),
            ["chunk b"]
        );
        let edited = record(&[("a", 1), ("b", 2)], &[("m.model", 6)], &[("a", 8)]);
        assert_eq!(
            names(because(Some(&old), &build, &light, 0, &edited)),
            ["terrain of chunk a", "model m.model"]
        );
        let same = record(&[("a", 1), ("b", 2)], &[("m.model", 5)], &[("a", 3)]);
        assert_eq!(
            names(because(Some(&old), &build, &light, 0, &same)),
            ["entry evicted or damaged"]
        );
        let other_light = LightDigests {
            options: Key([4; 32]),
            ..light
        };
        assert_eq!(
            names(because(Some(&old), &build, &other_light, 0, &same)),
            ["the options"]
        );
        assert_eq!(
            names(because(Some(&old), &Key([0; 32]), &light, 0, &same)),
            ["another shadowcull build"]
        );
        assert_eq!(
            names(because(None, &build, &light, 0, &same)),
            ["no earlier bake"]
        );
        assert_eq!(
            names(because(Some(&old), &build, &light, 5, &same)),
            ["no earlier bake"]
        );
    }
}
