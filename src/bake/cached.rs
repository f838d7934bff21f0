//! A bake with a cache (`--cache`): each light's grid answer as the union
//! of its cells' (each found in the cache under its key, or traced alone
//! and stored), and refinement per chunk of the casters it refines (found,
//! or refined one by one and stored). The answer is the bake's without a
//! cache, always (docs/contract.md §5):
//!
//! - the grid's answer is the union over every ray of the casters it
//!   proves; a cell traced alone, with its own settled set
//!   ([`super::trace_light::PacketSkip::Settled`]), leaves out only rays
//!   that could prove casters the cell's own rays proved, so its value is
//!   exactly what its rays prove, a pure function of its key
//!   (`cache_keys`), and the union over cells is the grid's answer;
//! - a refined caster's rays and what they prove depend on its own inputs
//!   (`refine::refine_each`), which its key covers: its id and the light's
//!   position (the seed of its surface points), its own geometry, and the
//!   keys of every cell its footprint meets (everything its rays can meet,
//!   and whether the grid proved it).
//!
//! What changed is said per light ([`LightCacheReport`]) from the light's
//! manifest (`manifest`).

use super::cache_keys::{cell_key, CellLists, CellValue, KeyInput, LightKey, WorldKeys};
use super::cells::{CellReach, Cells};
use super::config::BakeConfig;
use super::grid_pass::GridPass;
use super::manifest::{self, Because, LightDigests, Manifest};
use super::refine::{self, OwnRefinement};
use super::setup::{BakeWorld, LightSetup, NoSetup};
use super::trace_light::{CasterSet, LightRays, RayCounter};
use super::GridSource;
use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{Cache, Fetched, Key, Kind};
use crate::progress::{Counter, Phase, Progress};
use crate::scene::SceneKeys;
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Mutex;

/// What a cached bake did in one phase.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct PhaseCounts {
    /// Found in the cache and used.
    pub reused: u64,
    /// Not in the cache: computed (and stored).
    pub computed: u64,
    /// Of `computed`, those whose entry failed its check.
    pub damaged: u64,
}

impl PhaseCounts {
    /// What `cache` did so far with entries of `kind`.
    pub fn of_kind(cache: &Cache, kind: Kind) -> PhaseCounts {
        let counts = cache
            .counts()
            .into_iter()
            .find(|(k, _)| *k == kind)
            .map(|(_, c)| c)
            .unwrap_or_default();
        PhaseCounts {
            reused: counts.reused,
            computed: counts.computed + counts.damaged,
            damaged: counts.damaged,
        }
    }

    pub fn add(&mut self, other: PhaseCounts) {
        self.reused += other.reused;
        self.computed += other.computed;
        self.damaged += other.damaged;
    }
}

/// Why cells were traced again, with how many.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct TracedBecause {
    #[serde(flatten)]
    pub because: Because,
    pub cells: u64,
}

/// What the cache did for one light.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct LightCacheReport {
    pub index: usize,
    pub name: String,
    /// Cells with something in reach (the others trace nothing).
    pub cells: PhaseCounts,
    /// Refined casters (found or refined with their chunk's).
    pub refine: PhaseCounts,
    /// Why the cells computed were traced again.
    pub traced_because: Vec<TracedBecause>,
}

impl LightCacheReport {
    /// One line for people.
    pub fn cells_line(&self) -> String {
        let c = &self.cells;
        let mut line = format!(
            "cache: light {}: {} cells, {} reused, {} traced",
            self.name,
            c.reused + c.computed,
            c.reused,
            c.computed
        );
        if c.damaged > 0 {
            line += &format!(" ({} damaged)", c.damaged);
        }
        if !self.traced_because.is_empty() {
            let why: Vec<String> = self
                .traced_because
                .iter()
                .take(MOST_REASONS_SAID)
                .map(|t| format!("{}: {}", t.because.describe(), t.cells))
                .collect();
            let more = self.traced_because.len().saturating_sub(MOST_REASONS_SAID);
            line += &format!(" ({}", why.join(", "));
            if more > 0 {
                line += &format!(", {more} more in the report");
            }
            line += ")";
        }
        line
    }

    pub fn refine_line(&self) -> String {
        let r = &self.refine;
        format!(
            "cache: light {}: refinement of {} casters, {} reused, {} refined{}",
            self.name,
            r.reused + r.computed,
            r.reused,
            r.computed,
            if r.damaged > 0 {
                format!(" ({} damaged)", r.damaged)
            } else {
                String::new()
            }
        )
    }
}

/// Cells of each light a plan's calibration traces (and stores).
pub const CALIBRATION_CELLS: usize = 2;

/// What a plan says of a light's cells with a cache.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PlannedCells {
    /// Cells with something in reach.
    pub cells: u64,
    /// Of them, those with an entry before the plan.
    pub stored: u64,
    /// Rays of the others, which a cached bake traces.
    pub rays_to_trace: u64,
    /// The calibration: rays of the cells it traced, and their seconds.
    pub sample_rays: u64,
    pub sample_seconds: f64,
}

/// Reasons a progress line names before pointing at the report.
const MOST_REASONS_SAID: usize = 4;

/// What the cache did in a whole bake (the report's `cache`).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheReport {
    pub dir: String,
    /// Chunk files whose items were read back (`reused`) or parsed.
    pub chunks: PhaseCounts,
    pub cells: PhaseCounts,
    pub refine: PhaseCounts,
    /// Chunk files kept without being parsed (`reused`) or prepared.
    pub output: PhaseCounts,
    pub lights: Vec<LightCacheReport>,
}

/// One light's cells as this bake sees them.
struct LightCells {
    key: LightKey,
    cells: Cells,
    reach: CellReach,
    /// Per cell; `None`: nothing in reach.
    keys: Vec<Option<Key>>,
    /// Per cell, the casters its rays prove (ascending ids), when the
    /// grid pass ran here (a merge has only the shards' answers).
    values: Option<Vec<Vec<u32>>>,
    /// Per cell, what the cache held for it when the light's setup was
    /// built over the cells it lacks (its `GridSource::build_setup`).
    held: Option<Vec<Held>>,
}

/// A cell's entry as a cached bake's setup found it.
#[derive(Debug, Clone)]
enum Held {
    /// Nothing in reach: no entry.
    Empty,
    /// The casters its entry holds (ascending ids).
    Value(Vec<u32>),
    /// No usable entry (`damaged`: one failed its check): traced again.
    Missing { damaged: bool },
}

/// A bake's use of a cache: the world's keys, and per light what its grid
/// pass found for its refinement and report.
pub struct BakeCache<'c> {
    pub cache: &'c Cache,
    keys: WorldKeys,
    /// The space, which names a light's manifest with the light.
    space: String,
    lights: Mutex<BTreeMap<usize, LightCells>>,
    reports: Mutex<BTreeMap<usize, LightCacheReport>>,
    /// (light, cell) of the cells a plan's calibration traced and stored:
    /// computed by this bake, though found in the cache.
    calibrated: Mutex<HashSet<(usize, u64)>>,
    /// The setups a plan built and kept for the bake.
    kept: Mutex<Vec<LightSetup>>,
}

impl<'c> BakeCache<'c> {
    /// `cache` for a bake of `world`, whose models' and blocks' content
    /// keys are `scene_keys`; `left_out`: an input every key leaves out
    /// (the tests' sabotage; `None`).
    pub fn new(
        cache: &'c Cache,
        world: &BakeWorld,
        scene_keys: SceneKeys,
        left_out: Option<KeyInput>,
    ) -> BakeCache<'c> {
        BakeCache {
            cache,
            keys: WorldKeys::new(world, scene_keys, left_out),
            space: world.scene.space_dir.display().to_string(),
            lights: Mutex::new(BTreeMap::new()),
            reports: Mutex::new(BTreeMap::new()),
            calibrated: Mutex::new(HashSet::new()),
            kept: Mutex::new(Vec::new()),
        }
    }

    /// What the cache did, per light and in all.
    pub fn report(&self) -> CacheReport {
        let lights: Vec<LightCacheReport> = lock(&self.reports).values().cloned().collect();
        let mut report = CacheReport {
            dir: self.cache.dir().display().to_string(),
            ..CacheReport::default()
        };
        for light in &lights {
            report.cells.add(light.cells);
            report.refine.add(light.refine);
        }
        report.lights = lights;
        report
    }

    /// What the cache did for light `index` so far (its grid pass ran
    /// here: a merge's has no cells).
    pub fn light_report(&self, index: usize) -> Option<LightCacheReport> {
        lock(&self.reports).get(&index).cloned()
    }

    fn light_cells(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        config: &BakeConfig,
    ) -> LightCells {
        let key = LightKey::new(self.cache, world, setup, config, &self.keys);
        let cells = Cells::of(&setup.grid);
        let halo = f64::from(config.filter_radius);
        let reach = CellReach::of(world, setup, &cells, halo, &self.keys.ground);
        let keys = (0..cells.count())
            .into_par_iter()
            .map_init(Vec::new, |scratch, cell| {
                let parts = &self.keys;
                (!reach.is_empty(cell)).then(|| cell_key(&key, cell, &reach, world, parts, scratch))
            })
            .collect();
        LightCells {
            key,
            cells,
            reach,
            keys,
            values: None,
            held: None,
        }
    }

    fn setup_over_missing(
        &self,
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
    ) -> Result<LightSetup, NoSetup> {
        let mut setup = LightSetup::without_top(world, config, index)?;
        if setup.is_empty() {
            return Ok(setup);
        }
        // A plan's look at the cache stands (its calibration may have
        // stored cells since, which the grid pass then finds).
        let stashed = lock(&self.lights).remove(&index);
        let light = match stashed {
            Some(light) if light.values.is_none() && light.held.is_some() => light,
            _ => {
                let mut light = self.light_cells(world, &setup, config);
                light.held = Some(self.held(world, &light));
                light
            }
        };
        let held = light.held.as_deref().unwrap_or_default();
        if config.refines() {
            setup.build_top(world, None);
        } else {
            let missing = |cell: &usize| matches!(held[*cell], Held::Missing { .. });
            let union = |lists: &[Vec<u32>]| -> Vec<u32> {
                let mut all: Vec<u32> = (0..lists.len())
                    .filter(missing)
                    .flat_map(|cell| lists[cell].iter().copied())
                    .collect();
                all.sort_unstable();
                all.dedup();
                all
            };
            let (parts, blocks) = (union(&light.reach.parts), union(&light.reach.blocks));
            setup.build_top(world, Some((&parts, &blocks)));
        }
        lock(&self.lights).insert(index, light);
        Ok(setup)
    }

    /// What the cache holds for each cell of `light`, read and checked.
    fn held(&self, world: &BakeWorld, light: &LightCells) -> Vec<Held> {
        (0..light.cells.count())
            .into_par_iter()
            .map(|cell| match light.keys[cell as usize] {
                None => Held::Empty,
                Some(key) => match self.reuse(world, &key, CellLists::of(&light.reach, cell)) {
                    Ok(ids) => Held::Value(ids),
                    Err(damaged) => Held::Missing { damaged },
                },
            })
            .collect()
    }

    /// The casters (ascending ids) the entry under `key` of a cell whose
    /// reach is `lists` holds; `Err(damaged)` when there is none or it
    /// failed its check (then removed and warned about).
    fn reuse(&self, world: &BakeWorld, key: &Key, lists: CellLists) -> Result<Vec<u32>, bool> {
        match self.cache.fetch(Kind::Cell, key) {
            Fetched::Value(bytes) => match CellValue::decode(&bytes, world, lists) {
                Some(value) => {
                    let mut ids: Vec<u32> = value.casters(world, lists).collect();
                    ids.sort_unstable();
                    Ok(ids)
                }
                None => {
                    self.cache.reject(Kind::Cell, key);
                    Err(true)
                }
            },
            Fetched::Damaged => Err(true),
            Fetched::Absent => Err(false),
        }
    }

    /// For a plan: the light of `setup`'s cells with something in reach,
    /// how many of them hold an entry now (not read nor checked: what a
    /// cached bake would reuse), and the rays and seconds of up to
    /// [`CALIBRATION_CELLS`] of the others traced now (as
    /// [`Phase::Calibrating`]) and stored, which the bake then reuses.
    pub fn plan_light(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        config: &BakeConfig,
        progress: &dyn Progress,
    ) -> PlannedCells {
        let stashed = lock(&self.lights).remove(&setup.index);
        let light = match stashed {
            Some(light) if light.values.is_none() => light,
            _ => self.light_cells(world, setup, config),
        };
        let held: Vec<(u64, bool)> = (0..light.cells.count())
            .into_par_iter()
            .filter_map(|cell| {
                let key = light.keys[cell as usize].as_ref()?;
                let stored = match light.held.as_ref().map(|held| &held[cell as usize]) {
                    Some(Held::Value(_)) => true,
                    Some(Held::Missing { .. }) => false,
                    Some(Held::Empty) | None => self.cache.contains(Kind::Cell, key),
                };
                Some((cell, stored))
            })
            .collect();
        let missing: Vec<u64> = held.iter().filter(|(_, h)| !h).map(|&(c, _)| c).collect();
        let samples = config.supersample.max(1);
        let mut planned = PlannedCells {
            cells: held.len() as u64,
            stored: (held.len() - missing.len()) as u64,
            rays_to_trace: missing.iter().map(|&c| light.cells.rays(c, samples)).sum(),
            ..PlannedCells::default()
        };
        let picked: Vec<u64> = (1..=CALIBRATION_CELLS)
            .filter_map(|k| {
                missing
                    .get(missing.len() * k / (CALIBRATION_CELLS + 1))
                    .copied()
            })
            .collect();
        if !picked.is_empty() {
            let name = Some(config.lights[setup.index].name.as_str());
            let total = picked.iter().map(|&c| light.cells.rays(c, samples)).sum();
            let counter = Counter::begin(progress, Phase::Calibrating, name, total);
            let rays = setup.rays(world, config);
            let pass = GridPass::new(world, setup, &rays, config);
            let started = std::time::Instant::now();
            let answer = Mutex::new(CasterSet::new(world.casters.len()));
            for &cell in &picked {
                self.cell(world, &light, &pass, cell, samples, &counter, &answer);
                lock(&self.calibrated).insert((setup.index, cell));
            }
            planned.sample_seconds = started.elapsed().as_secs_f64();
            planned.sample_rays = counter.done();
            counter.finish();
        }
        lock(&self.lights).insert(setup.index, light);
        planned
    }

    /// Keeps the setups a plan built for the bake.
    pub fn keep_setups(&self, setups: Vec<LightSetup>) {
        *lock(&self.kept) = setups;
    }

    /// Cell `cell` of `light`: its value from the cache, or traced by
    /// `pass` and stored; its casters go into `answer`.
    #[allow(clippy::too_many_arguments)]
    fn cell(
        &self,
        world: &BakeWorld,
        light: &LightCells,
        pass: &GridPass,
        cell: u64,
        samples: u32,
        rays_done: &dyn RayCounter,
        answer: &Mutex<CasterSet>,
    ) -> (CellOutcome, Vec<u32>) {
        let Some(key) = light.keys[cell as usize] else {
            rays_done.add(light.cells.rays(cell, samples));
            return (CellOutcome::Empty, Vec::new());
        };
        let mut was_damaged = false;
        match light.held.as_ref().map(|held| &held[cell as usize]) {
            Some(Held::Value(ids)) => {
                rays_done.add(light.cells.rays(cell, samples));
                return (CellOutcome::Reused, ids.clone());
            }
            // Looked for again: a plan's calibration may have stored it.
            Some(Held::Missing { damaged }) => was_damaged = *damaged,
            Some(Held::Empty) | None => {}
        }
        let tiles = light.cells.tiles(cell);
        let entry = Entry {
            key,
            lists: CellLists::of(&light.reach, cell),
            tiles: &tiles,
            rays: light.cells.rays(cell, samples),
        };
        match self.entry(world, pass, &entry, rays_done, answer) {
            (CellOutcome::Computed { damaged }, ids) => (
                CellOutcome::Computed {
                    damaged: damaged || was_damaged,
                },
                ids,
            ),
            outcome => outcome,
        }
    }

    /// An entry's value from the cache, or its tiles traced by `pass` and
    /// stored; its casters go into `answer`.
    fn entry(
        &self,
        world: &BakeWorld,
        pass: &GridPass,
        entry: &Entry,
        rays_done: &dyn RayCounter,
        answer: &Mutex<CasterSet>,
    ) -> (CellOutcome, Vec<u32>) {
        let (key, lists) = (&entry.key, entry.lists);
        let damaged = match self.reuse(world, key, lists) {
            Ok(ids) => {
                rays_done.add(entry.rays);
                return (CellOutcome::Reused, ids);
            }
            Err(damaged) => damaged,
        };
        let useful = pass.trace(entry.tiles.to_vec(), None, rays_done);
        let value = CellValue::of(&useful, world, lists);
        self.cache.put(Kind::Cell, key, &value.encode());
        let mut ids: Vec<u32> = value.casters(world, lists).collect();
        ids.sort_unstable();
        debug_assert_eq!(
            ids.len(),
            useful.len(),
            "a cell's rays proved a caster outside its reach"
        );
        // The traced answer whole: what this bake computes never depends
        // on the reach being right, only what a later bake reuses does.
        let mut all = lock(answer);
        *all = std::mem::replace(&mut *all, CasterSet::new(0)).union(&useful);
        (CellOutcome::Computed { damaged }, ids)
    }

    /// A distributed bake's shard with this cache: the answer of each of
    /// `units` (ranges of light `setup.index`'s tiles), each exactly what
    /// its tiles prove (as without a cache). A unit is cut at its cells'
    /// edges: a whole cell is the cell's entry, part of one an entry of
    /// its own keyed by the cell's key and the tiles (a plan's units move
    /// with the world's content, so those are few and cheap). Returns the
    /// answers and what the cache did.
    pub fn trace_units(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        config: &BakeConfig,
        units: &[std::ops::Range<u64>],
        rays_done: &dyn RayCounter,
    ) -> (Vec<CasterSet>, PhaseCounts) {
        let light = self.light_cells(world, setup, config);
        let pass = GridPass::new(world, setup, rays_of_light, config);
        let samples = config.supersample.max(1);
        let mut counts = PhaseCounts::default();
        let mut answers = Vec::with_capacity(units.len());
        for unit in units {
            let answer = Mutex::new(CasterSet::new(world.casters.len()));
            let mut pieces: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
            for tile in unit.clone() {
                pieces
                    .entry(light.cells.of_tile(tile))
                    .or_default()
                    .push(tile);
            }
            let outcomes: Vec<(CellOutcome, Vec<u32>)> = pieces
                .into_par_iter()
                .map(|(cell, tiles)| {
                    let whole = light.cells.tiles(cell);
                    if tiles == whole {
                        return self.cell(world, &light, &pass, cell, samples, rays_done, &answer);
                    }
                    let rays = tiles_rays(&setup.grid, &tiles, samples);
                    let Some(cell_key) = light.keys[cell as usize] else {
                        rays_done.add(rays);
                        return (CellOutcome::Empty, Vec::new());
                    };
                    let key = self
                        .cache
                        .hasher(Kind::Cell)
                        .key(&cell_key)
                        .u64(tiles[0])
                        .u64(tiles[tiles.len() - 1])
                        .u64(tiles.len() as u64)
                        .finish();
                    let entry = Entry {
                        key,
                        lists: CellLists::of(&light.reach, cell),
                        tiles: &tiles,
                        rays,
                    };
                    self.entry(world, &pass, &entry, rays_done, &answer)
                })
                .collect();
            let mut answer = answer.into_inner().unwrap_or_else(|e| e.into_inner());
            for (outcome, ids) in outcomes {
                match outcome {
                    CellOutcome::Empty => {}
                    CellOutcome::Reused => counts.reused += 1,
                    CellOutcome::Computed { damaged } => {
                        counts.computed += 1;
                        counts.damaged += u64::from(damaged);
                    }
                }
                for c in ids {
                    answer.insert(c);
                }
            }
            answers.push(answer);
        }
        (answers, counts)
    }

    /// Counts, reasons and the manifest of a light whose cells ended as
    /// `outcomes`.
    fn explain(
        &self,
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
        light: &LightCells,
        outcomes: &[CellOutcome],
    ) -> LightCacheReport {
        let name = &config.lights[index].name;
        let mut report = LightCacheReport {
            index,
            name: name.clone(),
            ..LightCacheReport::default()
        };
        for outcome in outcomes {
            match outcome {
                CellOutcome::Empty => {}
                CellOutcome::Reused => report.cells.reused += 1,
                CellOutcome::Computed { damaged } => {
                    report.cells.computed += 1;
                    report.cells.damaged += u64::from(*damaged);
                }
            }
        }
        let manifest_key = manifest::manifest_key(&self.space, name);
        let old = Manifest::load(self.cache, &manifest_key);
        let build = self.cache.hasher(Kind::Manifest).finish();
        let digests = LightDigests::from(&light.key);
        let unchanged = old.as_ref().is_some_and(|old| {
            old.build == build
                && old.light == digests
                && old.cells.len() == light.keys.len()
                && old.cells.iter().zip(&light.keys).all(|(r, k)| r.key == *k)
        });
        if unchanged && report.cells.computed == 0 {
            return report;
        }
        let records = manifest::records(world, &self.keys, &light.reach, &light.keys, old.as_ref());
        let mut counted: BTreeMap<Because, u64> = BTreeMap::new();
        for (cell, outcome) in outcomes.iter().enumerate() {
            if let CellOutcome::Computed { .. } = outcome {
                for why in manifest::because(old.as_ref(), &build, &digests, cell, &records[cell]) {
                    *counted.entry(why).or_default() += 1;
                }
            }
        }
        let mut because: Vec<TracedBecause> = counted
            .into_iter()
            .map(|(because, cells)| TracedBecause { because, cells })
            .collect();
        because.sort_by(|a, b| b.cells.cmp(&a.cells).then(a.because.cmp(&b.because)));
        report.traced_because = because;
        let manifest = Manifest {
            build,
            light: digests,
            cells: records,
        };
        self.cache
            .put(Kind::Manifest, &manifest_key, &manifest.encode());
        report
    }

    /// Refinement of light `setup.index` with this cache: the casters its
    /// rays prove beyond `grid` (the grid's answer) and the rays counted.
    pub fn refine(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        grid: &CasterSet,
        config: &BakeConfig,
        progress: &dyn Progress,
    ) -> (CasterSet, u64) {
        let light = lock(&self.lights)
            .remove(&setup.index)
            .unwrap_or_else(|| self.light_cells(world, setup, config));
        let candidates = refine::candidates(world, setup, grid);
        let name = Some(config.lights[setup.index].name.as_str());
        let counter = Counter::begin(progress, Phase::Refining, name, candidates.len() as u64);
        let refining = Refining::new(self, world, &light, setup, config, &candidates);
        let mut answer = CasterSet::new(world.casters.len());
        let mut rays = 0;
        let mut counts = PhaseCounts::default();
        let mut to_refine: Vec<usize> = Vec::new();
        for (b, bucket) in refining.buckets.iter().enumerate() {
            match refining.fetch(b) {
                Ok(members) => {
                    counts.reused += bucket.members.len() as u64;
                    counter.add(bucket.members.len() as u64);
                    for refined in members {
                        rays += refined.rays;
                        for c in refined.proven {
                            answer.insert(c);
                        }
                    }
                }
                Err(damaged) => {
                    counts.computed += bucket.members.len() as u64;
                    counts.damaged += if damaged {
                        bucket.members.len() as u64
                    } else {
                        0
                    };
                    to_refine.push(b);
                }
            }
        }
        let members: Vec<u32> = to_refine
            .iter()
            .flat_map(|&b| refining.buckets[b].members.iter().map(|m| m.caster))
            .collect();
        let known = |caster: u32| refining.known(caster);
        let refined = refine::refine_each(
            world,
            setup,
            rays_of_light,
            config,
            &members,
            &known,
            &counter,
        );
        let mut refined = refined.into_iter();
        for &b in &to_refine {
            let bucket: Vec<OwnRefinement> = refined
                .by_ref()
                .take(refining.buckets[b].members.len())
                .collect();
            for one in &bucket {
                rays += one.rays;
                for &c in &one.proven {
                    answer.insert(c);
                }
            }
            refining.store(b, &bucket);
        }
        counter.finish();
        let mut reports = lock(&self.reports);
        let report = reports
            .entry(setup.index)
            .or_insert_with(|| LightCacheReport {
                index: setup.index,
                name: config.lights[setup.index].name.clone(),
                ..LightCacheReport::default()
            });
        report.refine = counts;
        progress.note(
            "cache_refine",
            &report.refine_line(),
            &serde_json::json!({ "light": report.name, "refine": counts }),
        );
        (answer, rays)
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// What one entry of cell values covers: a whole cell, or the tiles of
/// one that a shard's unit holds.
struct Entry<'e> {
    key: Key,
    lists: CellLists<'e>,
    /// Its tiles, in tile order.
    tiles: &'e [u64],
    /// Its rays (counted as done when reused).
    rays: u64,
}

/// Rays of `tiles` of `grid` at `samples`² a texel.
fn tiles_rays(grid: &crate::light::TexelGrid, tiles: &[u64], samples: u32) -> u64 {
    tiles
        .iter()
        .map(|&t| {
            let (_, x0, y0, x1, y1) = super::trace_light::tile_rect(grid, t);
            u64::from(x1 - x0) * u64::from(y1 - y0) * u64::from(samples.max(1)).pow(2)
        })
        .sum()
}

/// How a cell's value was had.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CellOutcome {
    /// Nothing in reach: no rays can hit anything.
    Empty,
    Reused,
    Computed {
        damaged: bool,
    },
}

/// The grid of a light as the union of its cells' values: each reused
/// from the cache or traced alone and stored.
impl GridSource for BakeCache<'_> {
    fn grid(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        config: &BakeConfig,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let stashed = lock(&self.lights).remove(&setup.index);
        let mut light = match stashed {
            Some(light) if light.values.is_none() => light,
            _ => self.light_cells(world, setup, config),
        };
        let pass = GridPass::new(world, setup, rays_of_light, config);
        let samples = config.supersample.max(1);
        let answer = Mutex::new(CasterSet::new(world.casters.len()));
        let calibrated: HashSet<(usize, u64)> = {
            let mut all = lock(&self.calibrated);
            let mine = all
                .iter()
                .filter(|(light, _)| *light == setup.index)
                .copied()
                .collect();
            all.retain(|(light, _)| *light != setup.index);
            mine
        };
        let (outcomes, values): (Vec<CellOutcome>, Vec<Vec<u32>>) = (0..light.cells.count())
            .into_par_iter()
            .map(|cell| {
                let (outcome, ids) =
                    self.cell(world, &light, &pass, cell, samples, rays_done, &answer);
                // Traced by the plan: computed, and damaged if its entry
                // was when the setup looked.
                let held = light.held.as_ref().map(|held| &held[cell as usize]);
                let damaged = matches!(held, Some(Held::Missing { damaged: true }));
                match calibrated.contains(&(setup.index, cell)) {
                    true => (CellOutcome::Computed { damaged }, ids),
                    false => (outcome, ids),
                }
            })
            .unzip();
        let mut answer = answer.into_inner().unwrap_or_else(|e| e.into_inner());
        for &c in values.iter().flatten() {
            answer.insert(c);
        }
        let report = self.explain(world, config, setup.index, &light, &outcomes);
        lock(&self.reports).insert(setup.index, report);
        light.values = Some(values);
        lock(&self.lights).insert(setup.index, light);
        answer
    }

    fn take_setup(&self, index: usize, _config: &BakeConfig) -> Option<LightSetup> {
        let mut kept = lock(&self.kept);
        let at = kept.iter().position(|setup| setup.index == index)?;
        Some(kept.swap_remove(at))
    }

    /// Light `index`'s setup for a bake with this cache, as
    /// [`Phase::TopLevel`] of `progress`: its cells' keys and the values
    /// the cache holds for them, read now, and a top level over only what
    /// the cells it lacks can meet (the whole reach with `--refine`, whose
    /// rays go beyond the cells traced again). Tracing a cell over it
    /// gives what tracing it over the whole reach gives: a cell's rays can
    /// meet only its reach (`bake::cells`).
    fn build_setup(
        &self,
        world: &BakeWorld,
        config: &BakeConfig,
        index: usize,
        progress: &dyn Progress,
    ) -> Result<LightSetup, NoSetup> {
        LightSetup::in_phase(config, index, progress, || {
            self.setup_over_missing(world, config, index)
        })
    }
}

/// Refinement's entries of one light: a bucket per chunk of the casters
/// it refines (in id order), each caster with its cells.
struct Refining<'r> {
    world: &'r BakeWorld<'r>,
    cache: &'r BakeCache<'r>,
    light: &'r LightCells,
    buckets: Vec<Bucket>,
    /// Each refined caster's bucket and place in it.
    member_of: HashMap<u32, (usize, usize)>,
}

struct Bucket {
    key: Key,
    members: Vec<Member>,
}

struct Member {
    caster: u32,
    /// The cells whose reach holds it, ascending.
    cells: Vec<u64>,
}

/// A refined caster's proof, by its place: the `cell`th of the refined
/// caster's cells, and its place in that cell's parts (with the group) or
/// blocks.
enum Place {
    Part {
        cell: u32,
        position: u32,
        group: u32,
    },
    Block {
        cell: u32,
        position: u32,
    },
}

impl<'r> Refining<'r> {
    fn new(
        cache: &'r BakeCache<'r>,
        world: &'r BakeWorld<'r>,
        light: &'r LightCells,
        setup: &LightSetup,
        config: &BakeConfig,
        candidates: &[u32],
    ) -> Refining<'r> {
        let keys = &cache.keys;
        let mut wanted: Vec<u32> = candidates.to_vec();
        wanted.sort_unstable();
        // Each candidate's cells: the cells whose reach holds its part or
        // block.
        let mut of_part: HashMap<u32, Vec<u64>> = HashMap::new();
        let mut of_block: HashMap<u32, Vec<u64>> = HashMap::new();
        for &c in &wanted {
            match owner_of(world, c) {
                Owned::Part(p, _) => of_part.entry(p).or_default(),
                Owned::Block(b) => of_block.entry(b).or_default(),
            };
        }
        for cell in 0..light.cells.count() {
            let c = cell as usize;
            for p in &light.reach.parts[c] {
                if let Some(cells) = of_part.get_mut(p) {
                    cells.push(cell);
                }
            }
            for b in &light.reach.blocks[c] {
                if let Some(cells) = of_block.get_mut(b) {
                    cells.push(cell);
                }
            }
        }
        let mut by_chunk: BTreeMap<usize, Vec<Member>> = BTreeMap::new();
        for &caster in &wanted {
            let (chunk, cells) = match owner_of(world, caster) {
                Owned::Part(p, _) => {
                    let part = &world.parts[p as usize];
                    (
                        world.scene.instances[part.instance].chunk,
                        of_part[&p].clone(),
                    )
                }
                Owned::Block(b) => (keys.block_chunks[b as usize], of_block[&b].clone()),
            };
            by_chunk
                .entry(chunk)
                .or_default()
                .push(Member { caster, cells });
        }
        let buckets: Vec<Bucket> = by_chunk
            .into_values()
            .map(|members| {
                let mut h = cache.cache.hasher(Kind::Refine);
                h.key(&light.key.key);
                if keys.keeps(KeyInput::RefineOptions) {
                    h.u64(u64::from(config.refine_samples))
                        .u64(u64::from(config.refine_density));
                }
                if keys.keeps(KeyInput::RefineSeed) {
                    h.u64(setup.index as u64);
                }
                h.u64(members.len() as u64);
                for m in &members {
                    if keys.keeps(KeyInput::RefineSeed) {
                        h.u64(u64::from(m.caster));
                    }
                    match owner_of(world, m.caster) {
                        Owned::Part(p, group) => {
                            h.key(&keys.part_key(world, p)).u64(u64::from(group))
                        }
                        Owned::Block(b) => h.key(&keys.blocks[b as usize]),
                    };
                    if keys.keeps(KeyInput::RefineCells) {
                        h.u64(m.cells.len() as u64);
                        for &cell in &m.cells {
                            if let Some(key) = &light.keys[cell as usize] {
                                h.key(key);
                            }
                        }
                    }
                }
                Bucket {
                    key: h.finish(),
                    members,
                }
            })
            .collect();
        let member_of = buckets
            .iter()
            .enumerate()
            .flat_map(|(b, bucket): (usize, &Bucket)| {
                bucket
                    .members
                    .iter()
                    .enumerate()
                    .map(move |(m, member)| (member.caster, (b, m)))
            })
            .collect();
        Refining {
            world,
            cache,
            light,
            buckets,
            member_of,
        }
    }

    /// The casters the cells of `caster` proved (sorted lists), when the
    /// grid ran here.
    fn known(&self, caster: u32) -> Vec<Vec<u32>> {
        let Some(values) = &self.light.values else {
            return Vec::new();
        };
        let Some(&(b, m)) = self.member_of.get(&caster) else {
            return Vec::new();
        };
        let cells = &self.buckets[b].members[m].cells;
        cells.iter().map(|&c| values[c as usize].clone()).collect()
    }

    /// Bucket `b`'s members' refinement from the cache; `Err(damaged)`
    /// when it must be computed.
    fn fetch(&self, b: usize) -> Result<Vec<OwnRefinement>, bool> {
        let bucket = &self.buckets[b];
        let cache = self.cache.cache;
        match cache.fetch(Kind::Refine, &bucket.key) {
            Fetched::Value(bytes) => match self.decode(bucket, &bytes) {
                Some(members) => Ok(members),
                None => {
                    cache.reject(Kind::Refine, &bucket.key);
                    Err(true)
                }
            },
            Fetched::Damaged => Err(true),
            Fetched::Absent => Err(false),
        }
    }

    /// Stores bucket `b`'s members' refinement, when every proof has a
    /// place among its caster's cells (else only this bake uses it).
    fn store(&self, b: usize, refined: &[OwnRefinement]) {
        let bucket = &self.buckets[b];
        let mut e = Encoder::new();
        e.var(refined.len() as u64);
        for (member, one) in bucket.members.iter().zip(refined) {
            e.var(one.rays).var(one.proven.len() as u64);
            for &c in &one.proven {
                match self.place(member, c) {
                    Some(Place::Part {
                        cell,
                        position,
                        group,
                    }) => e
                        .var(0)
                        .var(u64::from(cell))
                        .var(u64::from(position))
                        .var(u64::from(group)),
                    Some(Place::Block { cell, position }) => {
                        e.var(1).var(u64::from(cell)).var(u64::from(position))
                    }
                    None => {
                        debug_assert!(
                            false,
                            "caster {c} proven outside the cells of {}",
                            member.caster
                        );
                        return;
                    }
                };
            }
        }
        self.cache
            .cache
            .put(Kind::Refine, &bucket.key, &e.into_bytes());
    }

    /// Where caster `c` lies among `member`'s cells.
    fn place(&self, member: &Member, c: u32) -> Option<Place> {
        let reach = &self.light.reach;
        match owner_of(self.world, c) {
            Owned::Part(p, group) => member.cells.iter().enumerate().find_map(|(k, &cell)| {
                let position = reach.parts[cell as usize].binary_search(&p).ok()?;
                Some(Place::Part {
                    cell: k as u32,
                    position: position as u32,
                    group,
                })
            }),
            Owned::Block(b) => member.cells.iter().enumerate().find_map(|(k, &cell)| {
                let position = reach.blocks[cell as usize].binary_search(&b).ok()?;
                Some(Place::Block {
                    cell: k as u32,
                    position: position as u32,
                })
            }),
        }
    }

    fn decode(&self, bucket: &Bucket, bytes: &[u8]) -> Option<Vec<OwnRefinement>> {
        let (world, reach) = (self.world, &self.light.reach);
        let mut d = Decoder::new(bytes);
        if d.len(2).ok()? != bucket.members.len() {
            return None;
        }
        let mut members = Vec::with_capacity(bucket.members.len());
        for member in &bucket.members {
            let rays = d.var().ok()?;
            let n = d.len(3).ok()?;
            let mut proven = Vec::with_capacity(n);
            for _ in 0..n {
                let kind = d.var().ok()?;
                let index = |v: u64| usize::try_from(v).ok();
                let &cell = member.cells.get(index(d.var().ok()?)?)?;
                let position = index(d.var().ok()?)?;
                let c = cell as usize;
                proven.push(match kind {
                    0 => {
                        let &p = reach.parts[c].get(position)?;
                        let part = &world.parts[p as usize];
                        let group = d.var().ok()?;
                        if group >= world.scene.models[part.model].groups.len() as u64 {
                            return None;
                        }
                        part.first_caster + group as u32
                    }
                    1 => world.casters.of_block[*reach.blocks[c].get(position)? as usize],
                    _ => return None,
                });
            }
            proven.sort_unstable();
            members.push(OwnRefinement { proven, rays });
        }
        d.is_done().then_some(members)
    }
}

/// What a caster id belongs to.
enum Owned {
    /// A part (into `BakeWorld::parts`) and the group.
    Part(u32, u32),
    Block(u32),
}

fn owner_of(world: &BakeWorld, caster: u32) -> Owned {
    match world.casters.casters[caster as usize].owner {
        super::casters::Owner::Terrain { block } => Owned::Block(block),
        super::casters::Owner::Group { .. } => {
            let p = world.parts.partition_point(|p| p.first_caster <= caster) - 1;
            Owned::Part(p as u32, caster - world.parts[p].first_caster)
        }
        // Refinement's candidates are the groups of placed parts.
        super::casters::Owner::Unmodelled { .. } => {
            unreachable!("an unmodelled caster has no geometry to refine")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::{bake_cached, bake_world, BakeResult, GridMode};
    use crate::cache::content_key;
    use crate::formats::bake_settings::{BakeSettings, LightKind};
    use crate::progress::Silent;
    use crate::scene::{load_scene, LoadConfig, Scene};

    /// A fixture and its settings, spot and point lights at `resolution`.
    fn fixture(name: &str, resolution: u32) -> (BakeSettings, Scene) {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("fixtures/worlds")
            .join(name);
        let mut settings = crate::files::read_bake_settings(&root.join("bake.xml")).unwrap();
        for light in &mut settings.lights {
            if let LightKind::Spot { resolution: r, .. } | LightKind::Point { resolution: r, .. } =
                &mut light.kind
            {
                *r = resolution;
            }
        }
        let scene = load_scene(&LoadConfig::from_settings(&settings)).unwrap();
        (settings, scene)
    }

    fn same(a: &BakeResult, b: &BakeResult, what: &str) {
        assert_eq!(a.masks, b.masks, "{what}: masks");
        for (x, y) in a.lights.iter().zip(&b.lights) {
            assert_eq!(
                (x.rays, x.refine_rays, x.useful_casters),
                (y.rays, y.refine_rays, y.useful_casters),
                "{what}: light {}",
                x.name
            );
        }
    }

    /// A bake with an empty cache, then with the cache it filled, gives the
    /// masks and ray counts of a bake without cache, in every grid mode and
    /// with refinement; the second reuses every cell and refined chunk.
    #[test]
    fn a_cached_bake_equals_a_bake_without_cache_in_every_mode() {
        let (settings, scene) = fixture("small", 300);
        let world = BakeWorld::new(&scene);
        let plain = BakeConfig::from_settings(&settings);
        let configs = [
            ("plain", plain.clone()),
            (
                "supersample",
                BakeConfig {
                    supersample: 2,
                    ..plain.clone()
                },
            ),
            (
                "filter",
                BakeConfig {
                    filter_radius: 1,
                    ..plain.clone()
                },
            ),
            (
                "conservative",
                BakeConfig {
                    grid_mode: GridMode::Conservative,
                    ..plain.clone()
                },
            ),
            (
                "refine",
                BakeConfig {
                    refine_samples: 16,
                    refine_density: 4,
                    ..plain.clone()
                },
            ),
            (
                "offset",
                BakeConfig {
                    grid_offset: (0.3, -0.2),
                    ..plain.clone()
                },
            ),
        ];
        for (what, config) in configs {
            let fresh = bake_world(&world, &config, &Silent).unwrap();
            let dir = tempfile::tempdir().unwrap();
            let cache = Cache::open(dir.path(), u64::MAX, content_key(b"test"));
            for round in ["empty cache", "full cache"] {
                let bake_cache = BakeCache::new(&cache, &world, SceneKeys::of(&scene), None);
                let cached = bake_cached(&world, &config, &Silent, &bake_cache).unwrap();
                same(&fresh, &cached, &format!("{what}, {round}"));
                let report = cached.cache.unwrap();
                assert!(report.cells.reused + report.cells.computed > 0, "{what}");
                match round {
                    "empty cache" => assert_eq!(report.cells.reused, 0, "{what}"),
                    _ => {
                        assert_eq!(report.cells.computed, 0, "{what}: {report:?}");
                        assert_eq!(report.refine.computed, 0, "{what}: {report:?}");
                    }
                }
            }
            assert!(cache.take_warnings().is_empty(), "{what}");
        }
    }

    /// Every caster a ray of a cell hits (a texel of the cell, or of its
    /// halo under a filter radius) is in the cell's reach: its part or
    /// block, and the blocks the below-ground test reads are the ground
    /// of some part in reach.
    #[test]
    fn every_hit_of_a_cells_rays_is_in_its_reach() {
        let (settings, scene) = fixture("small", 96);
        let world = BakeWorld::new(&scene);
        let halo = 2u32;
        let config = BakeConfig {
            filter_radius: halo,
            ..BakeConfig::from_settings(&settings)
        };
        let ground = super::super::cells::GroundNear::of(&world);
        let mut checked = 0;
        for index in 0..config.lights.len() {
            let setup = LightSetup::new(&world, &config, index).unwrap();
            let rays = setup.rays(&world, &config);
            let cells = Cells::of(&setup.grid);
            let reach = CellReach::of(&world, &setup, &cells, f64::from(halo), &ground);
            let grid = &setup.grid;
            let mut hits = Vec::new();
            for cell in 0..cells.count() {
                let (face, x0, y0, x1, y1) = cells.rect(cell);
                let grown = |lo: u32, hi: u32, n: u32| lo.saturating_sub(halo)..(hi + halo).min(n);
                for y in grown(y0, y1, grid.height()) {
                    for x in grown(x0, x1, grid.width()) {
                        for ray in grid.texel_rays(face, x, y, 2) {
                            rays.all_hits(&ray, &mut hits);
                            for hit in &hits {
                                checked += 1;
                                match owner_of(&world, hit.caster) {
                                    Owned::Part(p, _) => assert!(
                                        reach.parts[cell as usize].binary_search(&p).is_ok(),
                                        "light {index} cell {cell}: part {p} hit at ({x}, {y})"
                                    ),
                                    Owned::Block(b) => assert!(
                                        reach.blocks[cell as usize].binary_search(&b).is_ok(),
                                        "light {index} cell {cell}: block {b} hit at ({x}, {y})"
                                    ),
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(checked > 10_000, "{checked} hits");
    }

    /// A cell's ground is the blocks near any of its parts, ascending and
    /// each once; a light's reach counts its parts' triangles part by
    /// part and every part is in reach or out of it.
    #[test]
    fn a_cells_ground_and_a_lights_totals_are_those_of_its_parts() {
        let (mut settings, scene) = fixture("small", 96);
        for light in &mut settings.lights {
            // Many cells: the sun's grid thousands of texels across.
            if let LightKind::Directional { texel_size, .. } = &mut light.kind {
                *texel_size = 0.05;
            }
        }
        let world = BakeWorld::new(&scene);
        let config = BakeConfig::from_settings(&settings);
        let ground = super::super::cells::GroundNear::of(&world);
        let (mut grounds, mut cells_met) = (0, 0);
        for index in 0..config.lights.len() {
            let setup = LightSetup::new(&world, &config, index).unwrap();
            let reach = &setup.reach;
            assert_eq!(
                reach.parts.len() + reach.parts_out_of_reach,
                world.parts.len()
            );
            assert!(reach.parts.windows(2).all(|w| w[0] < w[1]));
            let models = reach.parts.iter().map(|&p| world.parts[p as usize].model);
            let (triangles, left_out) = models.fold((0, 0), |(t, l), m| {
                let t = t + world.bottom.model_triangles(m) as u64;
                (t, l + world.bottom.model_left_out(m) as u64)
            });
            let blocks = reach.blocks.iter();
            let terrain: u64 = blocks
                .map(|&b| scene.terrain[b as usize].visible_triangles() as u64)
                .sum();
            assert_eq!(reach.triangles, triangles + terrain, "light {index}");
            assert_eq!(reach.left_out_triangles, left_out, "light {index}");
            let cells = Cells::of(&setup.grid);
            let cell_reach = CellReach::of(&world, &setup, &cells, 0.0, &ground);
            for (parts, near) in cell_reach.parts.iter().zip(&cell_reach.ground) {
                let expected: std::collections::BTreeSet<u32> = parts
                    .iter()
                    .flat_map(|&p| ground.of_part(p).iter().copied())
                    .collect();
                assert_eq!(near, &expected.into_iter().collect::<Vec<_>>());
                grounds += near.len();
                cells_met += usize::from(!parts.is_empty());
            }
        }
        assert!(grounds > 0, "some cell has ground near its parts");
        assert!(cells_met > 4, "{cells_met} cells meet parts");
    }
}
