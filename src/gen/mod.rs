//! Synthetic BigWorld worlds for tests, fixtures and benchmarks
//! (`shadowcull gen`). Real worlds are few and cannot be committed; a
//! generator gives worlds of any size that exercise every feature the bake
//! handles (multi-group, nodefull, mirrored, alpha-tested, double-sided,
//! receiver-only, multi-part instances, terrain with holes), together with the
//! counts they must produce (`Expected`), decided by the generator itself.
//!
//! The generator does no file I/O: it returns every file as bytes, and is
//! deterministic (same preset and seed, same bytes). `packed.rs` turns a
//! world into its packed variant, as a shipped game holds it.

mod forest;
mod mesh;
mod models;
mod packed;
mod world;
mod xml;

#[cfg(test)]
mod tests;

pub use packed::{generate_packed, pack_file, typed_values, ENCRYPTED_TAG};
use std::collections::BTreeMap;

/// Size and content level of a generated world.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Preset {
    /// 2×2 chunks of 50 m, a dozen instances: a tiny fixture.
    Small,
    /// 3×3 chunks of 100 m, ~140 instances, every feature.
    Village,
    /// 10×10 chunks, ~30 000 instances, millions of triangles.
    Bench,
    /// 3×3 chunks of 50 m: small's showcase, speedtrees in every chunk (22
    /// in one chunk of terrain and trees only) with their proxies in the
    /// settings, every other chunk item kind, and packed chunks.
    Forest,
}

impl Preset {
    pub const ALL: [Preset; 4] = [
        Preset::Small,
        Preset::Village,
        Preset::Bench,
        Preset::Forest,
    ];

    /// Parses a preset name (`small`, `village`, `bench`; case-insensitive).
    pub fn from_name(name: &str) -> Option<Preset> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name.trim()))
    }

    pub fn name(self) -> &'static str {
        match self {
            Preset::Small => "small",
            Preset::Village => "village",
            Preset::Bench => "bench",
            Preset::Forest => "forest",
        }
    }
}

/// What a generated world holds, with the meanings of `inspect --json`
/// (docs/contract.md §8): counts over placed instances (a model placed twice counts its
/// groups and triangles twice; a two-resource instance counts both parts),
/// except `models`, the number of distinct model resources. Receiver-only
/// instances are instances too and count in `groups` and `triangles`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Expected {
    pub chunks: u64,
    pub instances: u64,
    pub models: u64,
    pub groups: u64,
    pub triangles: u64,
    pub terrain_blocks: u64,
    pub alpha_tested_groups: u64,
    pub double_sided_groups: u64,
    pub receiver_only_instances: u64,
    /// `<speedtree>` placements, those without a proxy in the settings,
    /// and the distinct proxies they use.
    pub speedtrees: u64,
    pub speedtrees_without_proxy: u64,
    pub speedtree_proxies: u64,
}

/// Every file of a world, paths relative to the output folder (which is the
/// res root and holds `bake.xml`), `/`-separated, sorted by path.
#[derive(Debug, Clone, PartialEq)]
pub struct GeneratedWorld {
    pub files: Vec<(String, Vec<u8>)>,
    pub expected: Expected,
}

impl GeneratedWorld {
    pub fn file(&self, path: &str) -> Option<&[u8]> {
        self.files
            .binary_search_by(|(p, _)| p.as_str().cmp(path))
            .ok()
            .and_then(|i| self.files.get(i))
            .map(|(_, b)| b.as_slice())
    }
}

/// Name of the settings file at the root of a generated world.
pub const SETTINGS_FILE: &str = "bake.xml";

/// The size of a generated world: a preset, or the bench's density over
/// any number of chunks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WorldSize {
    Preset(Preset),
    /// N × N chunks of 100 m at the bench's density, 128² terrain, a 1 m
    /// texel sun (`shadowcull gen --chunks N`).
    BenchChunks(u32),
}

/// Generates a complete world in memory, files sorted by path.
pub fn generate(preset: Preset, seed: u64) -> GeneratedWorld {
    let mut files: Vec<(String, Vec<u8>)> = Vec::new();
    let expected = generate_each(WorldSize::Preset(preset), seed, |path, bytes| {
        files.push((path.to_string(), bytes));
        Ok::<(), std::convert::Infallible>(())
    })
    .unwrap_or_else(|never| match never {});
    files.sort_by(|a, b| a.0.cmp(&b.0));
    GeneratedWorld { files, expected }
}

/// Generates a world file by file: `sink(path, bytes)` receives each file
/// as soon as it is made (settings first, then each chunk's `.chunk` and
/// `.cdata`, then the models), so a world of any size needs memory for one
/// chunk at a time. The bytes are those of [`generate`] for a preset.
pub fn generate_each<E>(
    size: WorldSize,
    seed: u64,
    mut sink: impl FnMut(&str, Vec<u8>) -> Result<(), E>,
) -> Result<Expected, E> {
    let params = match size {
        WorldSize::Preset(preset) => world::Params::of(preset),
        WorldSize::BenchChunks(n) => world::Params::bench_of_size(n),
    };
    let mut plan = world::plan_frame(params, seed);
    let catalog = models::catalog(plan.params.detail);
    let stats: BTreeMap<models::Kind, models::ModelStats> =
        catalog.iter().map(|d| (d.kind, d.stats())).collect();

    let mut expected = Expected {
        chunks: plan.chunks.len() as u64,
        terrain_blocks: plan.chunks.len() as u64,
        ..Expected::default()
    };
    let space = plan.params.space();
    let settings = world::bake_settings(&plan);
    let settings = if plan.params.forest {
        forest::with_proxies(settings)
    } else {
        settings
    };
    sink(SETTINGS_FILE, settings)?;
    sink(
        &format!("{space}/space.settings"),
        world::space_settings(&plan.params),
    )?;
    let mut used = std::collections::BTreeSet::new();
    let mut proxies = std::collections::BTreeSet::new();
    let mut rng = plan.scatter_rng.clone();
    for i in 0..plan.chunks.len() {
        let mut ch = std::mem::take(&mut plan.chunks[i]);
        world::scatter(&plan, &mut rng, &mut ch);
        let trees = if plan.params.forest {
            forest::add_models(&plan, &mut ch);
            forest::trees(&plan, &ch)
        } else {
            Vec::new()
        };
        for tree in &trees {
            expected.speedtrees += 1;
            proxies.insert(tree.proxy());
        }
        for p in &ch.placements {
            expected.instances += 1;
            if p.shadow.receiver_only() {
                expected.receiver_only_instances += 1;
            }
            for k in &p.parts {
                used.insert(*k);
                let s = stats.get(k).copied().unwrap_or_default();
                expected.groups += s.groups;
                expected.triangles += s.triangles;
                expected.alpha_tested_groups += s.alpha_tested_groups;
                expected.double_sided_groups += s.double_sided_groups;
            }
        }
        let name = ch.name();
        let chunk = world::chunk_xml(&ch, plan.seed);
        let chunk = if plan.params.forest {
            forest::chunk_file(chunk, &plan, &ch, &trees)
        } else {
            chunk
        };
        sink(&format!("{space}/{name}.chunk"), chunk)?;
        sink(
            &format!("{space}/{name}.cdata"),
            world::terrain_cdata(&plan, &ch),
        )?;
        // Keep the chunk's frame (grid position, hole) but not its
        // placements: memory stays one chunk's worth.
        ch.placements = Vec::new();
        plan.chunks[i] = ch;
    }
    expected.models = used.len() as u64;
    expected.speedtree_proxies = proxies.len() as u64;
    if proxies.contains(&forest::TreeProxy::Bush) {
        used.insert(models::Kind::Bush);
    }
    for def in catalog.iter().filter(|d| used.contains(&d.kind)) {
        for (path, bytes) in models::files(def) {
            sink(&path, bytes)?;
        }
    }
    Ok(expected)
}

/// A chunk's XML with its first `<model>` placed `copies` times at the same
/// transform: stacked coincident geometry, which a level editor's duplicate
/// key makes easily and which the bake must survive in time near-linear in
/// the copies (the `coincident` bench and the hardening tests). `None` when
/// the chunk holds no model.
pub fn stack_first_model(chunk_xml: &[u8], copies: usize) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(chunk_xml).ok()?;
    let start = text.find("<model>")?;
    let end = start + text[start..].find("</model>")? + "</model>".len();
    let model = &text[start..end];
    let mut out = String::with_capacity(text.len() + model.len() * copies);
    out.push_str(&text[..start]);
    for copy in 0..copies {
        if copy > 0 {
            out.push_str("\n\t");
        }
        out.push_str(model);
    }
    out.push_str(&text[end..]);
    Some(out.into_bytes())
}
