//! The world model the bake consumes: chunks, placed instances (models,
//! shells and speedtrees through their proxies), primitive groups with
//! their flags, terrain blocks, and the count of every chunk item kind.
//! `load` builds it from the `formats/` readers; everything else here is
//! plain data.

pub mod chunk_cache;
pub mod items;
pub mod keys;
pub mod load;
pub mod speedtree;
pub mod terrain;
pub mod terrain_cache;

use crate::cache::Key;
use crate::formats::chunk::InstanceKind;
use crate::formats::shadow_write::ShadowSites;
use crate::formats::space_settings::SpaceSettings;
use glam::{DMat4, DVec3, Vec3};
use rayon::prelude::*;
use std::ops::Range;
use std::path::PathBuf;
use std::sync::Arc;

pub use items::{ItemCount, ItemEntry, Treatment, UnproxiedTrees};
pub use keys::SceneKeys;
pub use load::{load_scene, load_scene_cached, load_scene_with, LoadConfig};
pub use terrain::TerrainBlock;

#[derive(Debug, Clone)]
pub struct Scene {
    /// The space folder and its settings.
    pub space_dir: PathBuf,
    pub settings: SpaceSettings,
    /// Sorted by name.
    pub chunks: Vec<Chunk>,
    /// Each distinct model resource, loaded once; sorted by resource name.
    pub models: Vec<Model>,
    /// Chunk by chunk; within a chunk its `<model>`/`<shell>` instances in
    /// document order, then its `<speedtree>`s in document order.
    pub instances: Vec<Instance>,
    pub terrain: Vec<TerrainBlock>,
    /// Every item kind the chunks hold (their roots' child tags), by kind.
    pub items: Vec<ItemCount>,
    /// What could not be loaded and was left out, in a stable order.
    pub problems: Vec<Problem>,
    /// Every file the load read, with its content hash, sorted by path
    /// (empty for a scene built in memory).
    pub inputs: Vec<InputFile>,
}

/// A file a load read and the hash of the bytes it read.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct InputFile {
    pub path: PathBuf,
    pub digest: crate::digest::Digest,
}

/// How far, in chunks, geometry may reach beyond the space's chunk grid
/// (horizontally) before it is a stray placement.
pub const STRAY_MARGIN_CHUNKS: f64 = 1.0;

/// How far above or below height 0 geometry may reach, in metres, before it
/// is a stray placement, in a space without terrain (real terrain spans a
/// few kilometres).
pub const STRAY_HEIGHT_LIMIT: f64 = 10_000.0;

/// How far above the highest and below the lowest terrain of a space
/// geometry may reach, in metres, before it is a stray placement. Real
/// content (towers, masts, cliffs and mountains placed as models) stays well
/// within it; a sun's grid grows with the height of what it covers (its
/// slant moves a box kilometres sideways at kilometres up), so the margin
/// is what one stray transform may cost at most.
pub const STRAY_HEIGHT_MARGIN: f64 = 2_000.0;

/// Where the geometry of a space may lie: its chunk grid (the space.settings
/// bounds × the chunk size) grown by [`STRAY_MARGIN_CHUNKS`] on every side,
/// and heights within [`STRAY_HEIGHT_MARGIN`] of its terrain (within
/// ±[`STRAY_HEIGHT_LIMIT`] without terrain). A placement whose world box is
/// not inside is *far outside the space*: a problem, left out (one bad
/// transform must not stretch a light's grid to the size of its error).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpaceRegion {
    pub min: DVec3,
    pub max: DVec3,
    /// The lowest and highest terrain the heights follow, or `None` (no
    /// terrain: ±[`STRAY_HEIGHT_LIMIT`]).
    pub terrain_heights: Option<(f64, f64)>,
}

impl SpaceRegion {
    /// The region of a space's chunk grid, heights ±[`STRAY_HEIGHT_LIMIT`]
    /// (what terrain blocks themselves must lie in).
    pub fn of(settings: &SpaceSettings) -> SpaceRegion {
        let size = settings.chunk_size;
        let margin = STRAY_MARGIN_CHUNKS * size;
        SpaceRegion {
            min: DVec3::new(
                f64::from(settings.min_x) * size - margin,
                -STRAY_HEIGHT_LIMIT,
                f64::from(settings.min_z) * size - margin,
            ),
            max: DVec3::new(
                f64::from(settings.max_x + 1) * size + margin,
                STRAY_HEIGHT_LIMIT,
                f64::from(settings.max_z + 1) * size + margin,
            ),
            terrain_heights: None,
        }
    }

    /// This region with its heights from [`STRAY_HEIGHT_MARGIN`] below the
    /// lowest to that much above the highest of `blocks` (unchanged when
    /// there is none): what placed instances must lie in.
    pub fn around_terrain(self, blocks: &[TerrainBlock]) -> SpaceRegion {
        let heights = blocks
            .iter()
            .map(|block| {
                let (min, max) = block.bounds();
                (min.y, max.y)
            })
            .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)));
        let Some((lowest, highest)) = heights else {
            return self;
        };
        let mut region = self;
        region.min.y = lowest - STRAY_HEIGHT_MARGIN;
        region.max.y = highest + STRAY_HEIGHT_MARGIN;
        region.terrain_heights = Some((lowest, highest));
        region
    }

    /// The box `min`–`max` lies inside (and is finite).
    pub fn contains(&self, min: DVec3, max: DVec3) -> bool {
        min.is_finite() && max.is_finite() && min.cmpge(self.min).all() && max.cmple(self.max).all()
    }

    /// The box reaches into the region's horizontal extent at all.
    pub fn overlaps_horizontally(&self, min: DVec3, max: DVec3) -> bool {
        min.x <= self.max.x && max.x >= self.min.x && min.z <= self.max.z && max.z >= self.min.z
    }

    /// Why a box that is not inside is a stray placement, for the problem.
    pub fn stray_reason(&self, min: DVec3, max: DVec3) -> String {
        format!(
            "far outside the space: its world box ({:.1}, {:.1}, {:.1})–({:.1}, {:.1}, {:.1}) m leaves the region geometry may occupy (the space's chunks grown by {STRAY_MARGIN_CHUNKS} chunk: x {:.1}..{:.1}, z {:.1}..{:.1}; {}); a stray transform? left out",
            min.x, min.y, min.z, max.x, max.y, max.z, self.min.x, self.max.x, self.min.z, self.max.z,
            self.heights_text()
        )
    }

    /// The vertical limit in words.
    fn heights_text(&self) -> String {
        match self.terrain_heights {
            None => format!("heights ±{STRAY_HEIGHT_LIMIT} m"),
            Some((lowest, highest)) => format!(
                "heights {:.1}..{:.1} m: the terrain's {lowest:.1}..{highest:.1} m ± {STRAY_HEIGHT_MARGIN} m",
                self.min.y, self.max.y
            ),
        }
    }
}

/// Something left out of the scene, with the file (and element) it came
/// from and why.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct Problem {
    pub what: String,
    pub why: String,
}

#[derive(Debug, Clone)]
pub struct Chunk {
    /// File stem, e.g. `ffff0000o` or `00am0002i`.
    pub name: String,
    pub file: PathBuf,
    /// The content key of the file's bytes as loaded (`None` for a scene
    /// not read from files).
    pub file_key: Option<Key>,
    /// Outdoor grid coordinates.
    pub grid: Option<(i32, i32)>,
    /// Chunk to world.
    pub transform: DMat4,
    /// Into `Scene::instances`.
    pub instances: Range<usize>,
    /// How many `<model>`/`<shell>` elements the chunk file holds, including
    /// those left out of the scene (bad transform, no resource).
    pub instance_elements: usize,
    /// How many `<speedtree>` elements it holds, likewise.
    pub speedtree_elements: usize,
    /// Into `Scene::terrain`.
    pub terrain: Option<usize>,
    /// Where the `<shadow>`s of the bytes loaded (`file_key`) go, for a
    /// text chunk: the output writes there without parsing the file.
    pub sites: Option<ShadowSites>,
}

/// A placed instance: a `<model>` or `<shell>` with its parts, or a
/// `<speedtree>` with its proxy as its one part.
#[derive(Debug, Clone)]
pub struct Instance {
    pub chunk: usize,
    /// Position among the chunk's `<model>`/`<shell>` elements, or among
    /// its `<speedtree>` elements for a speedtree.
    pub index: usize,
    pub kind: InstanceKind,
    /// The `<resource>`s, or a speedtree's `<spt>` alone.
    pub resources: Arc<[String]>,
    /// One entry per `<resource>`: the loaded model, or `None` when that
    /// resource could not be loaded (see `Scene::problems`). A speedtree's
    /// one entry is its proxy model; it has none when no proxy matches
    /// its `.spt` ([`Instance::is_unmodelled`]). Shared by the instances
    /// of a chunk that name the same resources.
    pub parts: Arc<[Option<usize>]>,
    /// Model to world, kept in f64 so worlds far from the origin stay exact.
    pub world: DMat4,
    /// Negative determinant: the engine flips the cull mode, so the bake
    /// flips facing.
    pub mirrored: bool,
    /// `castsShadow` false: a receiver only.
    pub casts_shadow: bool,
}

impl Instance {
    pub fn is_complete(&self) -> bool {
        self.parts.iter().all(Option::is_some)
    }

    /// A speedtree no proxy matches: a caster the bake cannot model, kept
    /// for every light and never occluding (docs/contract.md §4).
    pub fn is_unmodelled(&self) -> bool {
        self.kind == InstanceKind::SpeedTree && self.parts.is_empty()
    }
}

/// The geometry of one model resource, LOD 0, in model space.
#[derive(Debug, Clone, Default)]
pub struct Model {
    pub resource: String,
    pub file: PathBuf,
    /// Model-space positions (node transforms already applied).
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    /// In output order: renderSet, geometry, group.
    pub groups: Vec<Group>,
    /// The visual's structure: per renderSet, per geometry, its group
    /// count (the shape of the `<shadow>` element, empty geometries too).
    pub layout: Vec<Vec<usize>>,
    /// A parametric speedtree proxy built from the settings
    /// (`speedtree::parametric_model`), not read from a file.
    pub parametric: bool,
}

impl Model {
    /// Model-space bounds of the vertices the triangles use, or `None` when
    /// the model has no (finite) triangle. Vertices that are not finite or
    /// lie beyond [`crate::trace::MAX_COORDINATE`] (a damaged file: the bake
    /// leaves their triangles out and counts them) do not count, so one of
    /// them cannot blow the world's bounds up to an impossible shadow map.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut bounds: Option<(Vec3, Vec3)> = None;
        for &index in self.triangles.iter().flatten() {
            let Some(&p) = self.positions.get(index as usize) else {
                continue;
            };
            if !p.is_finite() || p.abs().max_element() > crate::trace::MAX_COORDINATE {
                continue;
            }
            bounds = Some(match bounds {
                Some((min, max)) => (min.min(p), max.max(p)),
                None => (p, p),
            });
        }
        bounds
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Group {
    pub render_set: usize,
    pub geometry: usize,
    /// Index into the index section's PrimitiveGroup table.
    pub primitive_group: usize,
    /// Into `Model::triangles`.
    pub triangles: Range<usize>,
    pub alpha_tested: bool,
    pub double_sided: bool,
}

/// Counts of what a scene holds (docs/contract.md §8, `inspect --json`).
/// `instances` to `receiver_only_instances` count `<model>`/`<shell>`
/// instances and their models; speedtrees are counted apart.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Stats {
    pub chunks: usize,
    pub instances: usize,
    pub models: usize,
    pub groups: usize,
    pub triangles: usize,
    pub terrain_blocks: usize,
    pub alpha_tested_groups: usize,
    pub double_sided_groups: usize,
    pub receiver_only_instances: usize,
    /// `<speedtree>` placements in the scene.
    pub speedtrees: usize,
    /// Of those, the ones no proxy matches (unmodelled casters).
    pub speedtrees_without_proxy: usize,
    /// Distinct proxies the placed speedtrees use (`.model` resources and
    /// parametric shapes).
    pub speedtree_proxies: usize,
}

/// [`Scene::stats`]'s tally over some of the instances: what depends on
/// the instance, and how often each model is placed, as a model or as a
/// speedtree's proxy (its groups and triangles are counted per model once).
struct Tally {
    instances: usize,
    receiver_only_instances: usize,
    speedtrees: usize,
    speedtrees_without_proxy: usize,
    placed: Vec<usize>,
    proxies: Vec<usize>,
}

impl Tally {
    fn new(models: usize) -> Tally {
        Tally {
            instances: 0,
            receiver_only_instances: 0,
            speedtrees: 0,
            speedtrees_without_proxy: 0,
            placed: vec![0; models],
            proxies: vec![0; models],
        }
    }

    fn add(mut self, instance: &Instance) -> Tally {
        let speedtree = instance.kind == InstanceKind::SpeedTree;
        let uses = if speedtree {
            self.speedtrees += 1;
            self.speedtrees_without_proxy += usize::from(instance.is_unmodelled());
            &mut self.proxies
        } else {
            self.instances += 1;
            self.receiver_only_instances += usize::from(!instance.casts_shadow);
            &mut self.placed
        };
        for &part in instance.parts.iter().flatten() {
            uses[part] += 1;
        }
        self
    }

    fn merge(mut self, other: Tally) -> Tally {
        self.instances += other.instances;
        self.receiver_only_instances += other.receiver_only_instances;
        self.speedtrees += other.speedtrees;
        self.speedtrees_without_proxy += other.speedtrees_without_proxy;
        for (mine, theirs) in [
            (&mut self.placed, &other.placed),
            (&mut self.proxies, &other.proxies),
        ] {
            mine.iter_mut().zip(theirs).for_each(|(a, b)| *a += b);
        }
        self
    }
}

impl Scene {
    /// Where the space's instances may lie (see [`SpaceRegion`]).
    pub fn region(&self) -> SpaceRegion {
        SpaceRegion::of(&self.settings).around_terrain(&self.terrain)
    }

    /// Counts over placed instances: a model placed twice counts its groups
    /// and triangles twice; `models` counts distinct resources in use
    /// (speedtrees and their proxies are counted apart).
    pub fn stats(&self) -> Stats {
        let models = self.models.len();
        // Instance by instance in parallel (millions on a large world), each
        // split with its own tally, merged in any order: sums.
        let tally = self
            .instances
            .par_iter()
            .fold(|| Tally::new(models), Tally::add)
            .reduce(|| Tally::new(models), Tally::merge);
        let mut stats = Stats {
            chunks: self.chunks.len(),
            instances: tally.instances,
            terrain_blocks: self.terrain.len(),
            receiver_only_instances: tally.receiver_only_instances,
            speedtrees: tally.speedtrees,
            speedtrees_without_proxy: tally.speedtrees_without_proxy,
            ..Stats::default()
        };
        for (model, &placed) in self.models.iter().zip(&tally.placed) {
            if placed == 0 {
                continue;
            }
            let groups = &model.groups;
            stats.models += 1;
            stats.groups += placed * groups.len();
            stats.triangles += placed * model.triangles.len();
            stats.alpha_tested_groups += placed * groups.iter().filter(|g| g.alpha_tested).count();
            stats.double_sided_groups += placed * groups.iter().filter(|g| g.double_sided).count();
        }
        stats.speedtree_proxies = tally.proxies.iter().filter(|&&n| n > 0).count();
        stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_bounds_ignore_unusable_vertices() {
        // Triangle 0 is sane; triangle 1 has a NaN, an infinite and a
        // 1e30 m vertex (beyond trace::MAX_COORDINATE) besides a sane one.
        let model = Model {
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 2.0, 0.0),
                Vec3::new(0.0, 0.0, 3.0),
                Vec3::new(f32::NAN, 0.0, 0.0),
                Vec3::new(0.0, f32::INFINITY, 0.0),
                Vec3::new(1e30, 0.0, 0.0),
                Vec3::new(-1.0, 0.5, 0.5),
            ],
            triangles: vec![[0, 1, 2], [3, 4, 5], [5, 6, 3]],
            ..Model::default()
        };
        assert_eq!(
            model.bounds(),
            Some((Vec3::new(-1.0, 0.0, 0.0), Vec3::new(1.0, 2.0, 3.0)))
        );
        let only_bad = Model {
            triangles: vec![[3, 4, 5]],
            ..model
        };
        assert_eq!(only_bad.bounds(), None);
    }
}
