//! What a bake will cost before it runs (`shadowcull plan`, and the first
//! lines of `bake`): per light its grid, rays and what lies in its reach,
//! and the time and peak memory to expect, so a build engineer can size a
//! machine or refuse a job (`--max-memory`) before hours are spent.
//!
//! Time comes from a calibration on this machine and this world: each
//! light's top level is built and a spread sample of its texel tiles is
//! traced; the light's rays divided by the sample's ray rate is its
//! tracing time. A bake that follows its plan ([`Plan`] is a
//! [`GridSource`]) keeps what the sample proved and traces only the other
//! tiles, and it takes over the first light's setup (its top level), which
//! the plan builds last, so calibrating costs a bake only the other lights'
//! second top-level build. Memory is what the process holds once the world is
//! loaded (the caller measures it) plus, for the largest light, its top
//! level and the tracing threads' working sets, plus the masks and every
//! chunk file's old and new bytes held for the write.

use super::cached::{BakeCache, PlannedCells};
use super::config::{BakeConfig, GridMode};
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays, RayCounter};
use super::{grid_pass, BakeError, GridSource, TraceGrid};
use crate::progress::{Counter, Phase, Progress};
use crate::scene::{ItemEntry, UnproxiedTrees};
use rayon::prelude::*;
use std::sync::Mutex;
use std::time::Instant;

/// Tiles (32×32 texels) of each light traced to measure the ray rate.
pub const SAMPLE_TILES: u64 = 48;

/// Chunk-file bytes one thread reads back, rewrites and stages per second
/// in the output phase, temporaries and syncs included; the phase runs on
/// every thread and was measured to scale with them (2 threads: 118 MB in
/// 0.55–0.69 s on `gen --chunks 30`, 1.3 GB in 6.6–8.4 s on 96×96).
const OUTPUT_BYTES_PER_THREAD_SECOND: f64 = 80e6;

/// What the caller measured before planning.
#[derive(Debug, Clone, Copy, Default)]
pub struct Baseline {
    /// Resident bytes now (the scene and the bottom levels are loaded).
    pub resident_bytes: u64,
    /// The process's peak resident bytes so far (loading may have peaked).
    pub peak_resident_bytes: u64,
    /// Seconds spent so far (loading, bottom levels).
    pub elapsed_seconds: f64,
    /// Bytes of every chunk file of the space (each read back and rewritten).
    pub chunk_file_bytes: u64,
    /// Bytes of the largest chunk file: each thread of the output holds one
    /// chunk read, parsed and rewritten at a time.
    pub largest_chunk_file_bytes: u64,
    /// Worker threads.
    pub threads: usize,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct LightPlan {
    pub index: usize,
    pub name: String,
    pub kind: &'static str,
    pub bit: u32,
    pub faces: usize,
    pub width: u32,
    pub height: u32,
    /// Texel rays (texels × supersample²) plus refinement rays.
    pub rays: u64,
    /// Model parts in reach, receiver-only ones too: one per `<resource>`
    /// of an instance (an instance with two is two), so more than the
    /// scene's instances when all are in reach. The report's `instances`
    /// counts the same.
    pub instances: usize,
    pub terrain_blocks: usize,
    /// Hittable triangles in reach: the parts' models' (each part counts
    /// its model's) plus two per visible terrain cell that is not a hole.
    pub triangles: u64,
    pub top_level_bytes: usize,
    /// The calibration: rays traced and their wall time.
    pub sample_rays: u64,
    pub sample_seconds: f64,
    pub rays_per_second: f64,
    pub estimated_seconds: f64,
    /// Memory this light needs on top of the loaded world while it is baked.
    pub estimated_bytes: u64,
    /// Why the light traces nothing, when it does not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nothing_to_trace: Option<String>,
    /// With a cache: the cells of its grid with something in reach, and
    /// how many of them the cache held before the plan.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cells: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cells_stored: Option<u64>,
    /// The calibration's tiles and what they proved, for the bake.
    #[serde(skip)]
    pub sample: Option<TracedSample>,
}

/// The tiles a light's calibration traced — of every `every` tiles of
/// `tile_count`, the first `held` — under `pass` (the grid settings they
/// were traced with), and the casters they proved useful.
#[derive(Debug, Clone)]
pub struct TracedSample {
    pub every: u64,
    pub held: u64,
    pub tile_count: u64,
    pub pass: GridPassSettings,
    pub rays: u64,
    pub useful: CasterSet,
}

/// What decides a tile's answer besides the light and the world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridPassSettings {
    supersample: u32,
    grid_mode: GridMode,
    filter_radius: u32,
    grid_offset: (f64, f64),
}

impl GridPassSettings {
    fn of(config: &BakeConfig) -> GridPassSettings {
        GridPassSettings {
            supersample: config.supersample.max(1),
            grid_mode: config.grid_mode,
            filter_radius: config.filter_radius,
            grid_offset: config.grid_offset,
        }
    }
}

impl TracedSample {
    fn holds(&self, tile: u64) -> bool {
        tile % self.every < self.held
    }
}

/// A bake after its plan: each light's grid is the calibration's answer OR
/// the other tiles' (the answer over a partition of the tiles is the
/// grid's, [`grid_pass::trace_tiles`]). A light whose grid or grid pass
/// differs from the sample's is traced whole.
impl GridSource for Plan {
    fn grid(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        rays_of_light: &LightRays<'_>,
        config: &BakeConfig,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let tile_count = rays_of_light.tile_count();
        let sample = self
            .lights
            .get(setup.index)
            .and_then(|light| light.sample.as_ref())
            .filter(|s| s.tile_count == tile_count && s.pass == GridPassSettings::of(config));
        let Some(sample) = sample else {
            return TraceGrid.grid(world, setup, rays_of_light, config, rays_done);
        };
        rays_done.add(sample.rays);
        let rest = (0..tile_count)
            .into_par_iter()
            .filter(|&t| !sample.holds(t));
        let known = Some(&sample.useful);
        grid_pass::trace_tiles(world, setup, rays_of_light, config, rest, known, rays_done)
            .union(&sample.useful)
    }

    fn seconds_before(&self, index: usize) -> f64 {
        self.lights
            .get(index)
            .filter(|light| light.sample.is_some())
            .map_or(0.0, |light| light.sample_seconds)
    }

    fn take_setup(&self, index: usize, config: &BakeConfig) -> Option<LightSetup> {
        let mut kept = self.kept.0.lock().unwrap_or_else(|e| e.into_inner());
        let planned = self.lights.get(index)?;
        let same_grid = planned.sample.as_ref()?.pass == GridPassSettings::of(config);
        kept.take_if(|setup| setup.index == index && same_grid)
    }
}

#[derive(Debug, serde::Serialize)]
pub struct Plan {
    pub lights: Vec<LightPlan>,
    pub casters: usize,
    pub bottom_level_bytes: usize,
    /// Seconds the calibration itself took (part of a bake's time).
    pub calibration_seconds: f64,
    pub estimated_seconds: f64,
    pub estimated_peak_bytes: u64,
    /// Every chunk item kind of the world with what the bake does with it
    /// (docs/contract.md §2).
    pub items: Vec<ItemEntry>,
    /// The speedtrees the bake cannot model (no proxy), per `.spt`.
    pub unproxied_speedtrees: Vec<UnproxiedTrees>,
    /// The setup of the first light the bake traces (built last, so no
    /// other light's top level is built while it is held), handed to the
    /// bake by [`GridSource::take_setup`] instead of being built again.
    #[serde(skip)]
    kept: KeptSetup,
}

/// The setup a [`Plan`] keeps for the bake (the first bake to ask takes
/// it; a `GridSource` is shared, hence the lock).
#[derive(Default)]
struct KeptSetup(Mutex<Option<LightSetup>>);

impl std::fmt::Debug for KeptSetup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kept = self.0.lock().unwrap_or_else(|e| e.into_inner());
        write!(f, "KeptSetup({:?})", kept.as_ref().map(|s| s.index))
    }
}

/// Plans `config`'s lights over a built world. Traces only samples.
pub fn plan(
    world: &BakeWorld,
    config: &BakeConfig,
    baseline: Baseline,
    progress: &dyn Progress,
) -> Result<Plan, BakeError> {
    plan_with(world, config, baseline, progress, None)
}

/// [`plan`] of a bake with `cache` when given: per light, how many of its
/// cells the cache holds, and a calibration on cells it does not (traced
/// and stored, so the bake reuses them); the bake takes the kept setup
/// from the cache.
pub fn plan_with(
    world: &BakeWorld,
    config: &BakeConfig,
    baseline: Baseline,
    progress: &dyn Progress,
    cache: Option<&BakeCache>,
) -> Result<Plan, BakeError> {
    let started = Instant::now();
    let mut lights = Vec::new();
    let mut kept: Vec<LightSetup> = Vec::new();
    // Last light first: the first light's setup, built last, is kept; with
    // a cache, so is every other whose top level is small beside its reach
    // (an edit's few cells), which the bake would otherwise find again.
    for index in (0..config.lights.len()).rev() {
        let planned = plan_light(world, config, index, baseline.threads, progress, cache)?;
        let (light, setup) = planned;
        lights.push(light);
        kept.extend(setup.filter(|s| index == 0 || (cache.is_some() && s.top_is_small())));
    }
    lights.reverse();
    let calibration_seconds = started.elapsed().as_secs_f64();
    let casters = world.casters.len();
    let masks = casters as u64 * 4;
    let threads = baseline.threads.max(1);
    let output = threads as u64 * baseline.largest_chunk_file_bytes * 3;
    let light_peak = lights.iter().map(|l| l.estimated_bytes).max().unwrap_or(0);
    let estimated_peak_bytes = baseline
        .peak_resident_bytes
        .max(baseline.resident_bytes + masks + light_peak.max(output));
    // The bake keeps the first light's setup, built during the
    // calibration, instead of building it again.
    let output_share = match cache {
        Some(_) => cached_output_share(&lights),
        None => 1.0,
    };
    let kept_setup_seconds: f64 = kept.iter().map(|s| s.reach_seconds + s.top_seconds).sum();
    let estimated_seconds = baseline.elapsed_seconds
        + calibration_seconds
        + lights.iter().map(|l| l.estimated_seconds).sum::<f64>()
        - kept_setup_seconds
        + output_share * baseline.chunk_file_bytes as f64
            / (OUTPUT_BYTES_PER_THREAD_SECOND * threads as f64);
    if let Some(cache) = cache {
        cache.keep_setups(std::mem::take(&mut kept));
    }
    Ok(Plan {
        lights,
        casters,
        bottom_level_bytes: world.bottom.heap_bytes(),
        calibration_seconds,
        estimated_seconds,
        estimated_peak_bytes,
        items: world.scene.item_entries(),
        unproxied_speedtrees: world.scene.unproxied_trees(),
        kept: KeptSetup(Mutex::new(kept.pop())),
    })
}

/// The share of the chunk files a cached bake's output prepares: a chunk
/// is prepared only when its masks may change, which takes a cell traced
/// again, so the largest share of cells a light's cache lacks.
fn cached_output_share(lights: &[LightPlan]) -> f64 {
    let cached = lights
        .iter()
        .filter_map(|l| Some((l.cells?, l.cells_stored?)));
    cached
        .map(|(cells, stored)| cells.saturating_sub(stored) as f64 / cells.max(1) as f64)
        .fold(0.0, f64::max)
}

/// One light's plan, and its setup when the light has something to trace.
fn plan_light(
    world: &BakeWorld,
    config: &BakeConfig,
    index: usize,
    threads: usize,
    progress: &dyn Progress,
    cache: Option<&BakeCache>,
) -> Result<(LightPlan, Option<LightSetup>), BakeError> {
    let mut plan = LightPlan::before_setup(config, index);
    let built = match cache {
        Some(cache) => cache.build_setup(world, config, index, progress),
        None => LightSetup::new_with_progress(world, config, index, progress),
    };
    let setup = match built {
        Ok(setup) => setup,
        Err(nothing) if nothing.is_nothing_to_trace() => {
            plan.nothing_to_trace = Some(nothing.to_string());
            return Ok((plan, None));
        }
        Err(super::setup::NoSetup::Grid(err)) => return Err(err.into()),
        Err(super::setup::NoSetup::NoGeometry) => unreachable!("no geometry is nothing to trace"),
    };
    let grid_rays = plan.size_from(world, config, &setup, threads);
    if setup.is_empty() {
        plan.nothing_to_trace = Some("its frustum holds no geometry".into());
        plan.estimated_seconds = setup.reach_seconds + setup.top_seconds;
        return Ok((plan, None));
    }
    if let Some(cache) = cache {
        plan.plan_cells(
            cache.plan_light(world, &setup, config, progress),
            grid_rays,
            &setup,
        );
        return Ok((plan, Some(setup)));
    }
    let calibration = calibrate(world, config, &setup, grid_rays, progress);
    plan.sample_seconds = calibration.seconds;
    plan.sample_rays = calibration.sample.rays;
    plan.rays_per_second = calibration.rays_per_second;
    plan.sample = Some(calibration.sample);
    // The bake keeps the sample's answer and traces the rest.
    let left = plan.rays.saturating_sub(plan.sample_rays);
    plan.estimated_seconds =
        setup.reach_seconds + setup.top_seconds + left as f64 / plan.rays_per_second;
    Ok((plan, Some(setup)))
}

impl LightPlan {
    /// A cached bake's estimate: the rays of the cells the cache does not
    /// hold (less those the calibration `cells` traced) and that share of
    /// the refinement rays, at the calibration's rate.
    fn plan_cells(&mut self, cells: PlannedCells, grid_rays: u64, setup: &LightSetup) {
        self.cells = Some(cells.cells);
        self.cells_stored = Some(cells.stored);
        self.sample_rays = cells.sample_rays;
        self.sample_seconds = cells.sample_seconds;
        self.estimated_seconds = setup.reach_seconds + setup.top_seconds;
        if cells.sample_rays == 0 {
            return;
        }
        self.rays_per_second = cells.sample_rays as f64 / cells.sample_seconds.max(1e-6);
        let missing = cells.rays_to_trace as f64 / grid_rays.max(1) as f64;
        let refine_rays = self.rays.saturating_sub(grid_rays) as f64 * missing;
        let left = cells.rays_to_trace.saturating_sub(cells.sample_rays) as f64 + refine_rays;
        self.estimated_seconds += left / self.rays_per_second;
    }

    /// Light `index`'s plan before its setup: what it is, nothing sized.
    fn before_setup(config: &BakeConfig, index: usize) -> LightPlan {
        let light = &config.lights[index];
        LightPlan {
            index,
            name: light.name.clone(),
            kind: light.kind.type_name(),
            bit: config.bit(index),
            faces: 0,
            width: 0,
            height: 0,
            rays: 0,
            instances: 0,
            terrain_blocks: 0,
            triangles: 0,
            top_level_bytes: 0,
            sample_rays: 0,
            sample_seconds: 0.0,
            rays_per_second: 0.0,
            estimated_seconds: 0.0,
            estimated_bytes: 0,
            nothing_to_trace: None,
            cells: None,
            cells_stored: None,
            sample: None,
        }
    }

    /// Sizes the plan from the light's `setup`: its grid, what it reaches,
    /// its rays, and the memory it needs while `threads` trace it. Returns
    /// the grid's rays (texels × supersample²).
    fn size_from(
        &mut self,
        world: &BakeWorld,
        config: &BakeConfig,
        setup: &LightSetup,
        threads: usize,
    ) -> u64 {
        let supersample = config.supersample.max(1) as u64;
        self.faces = setup.grid.faces();
        self.width = setup.grid.width();
        self.height = setup.grid.height();
        self.instances = setup.reach.parts.len();
        self.terrain_blocks = setup.reach.blocks.len();
        self.triangles = setup.reach.triangles;
        self.top_level_bytes = setup.top.heap_bytes();
        let grid_rays = setup.grid.texel_count() * supersample * supersample;
        let refine_rays = config.refine_samples as u64 * world.casters.len() as u64;
        self.rays = grid_rays + refine_rays;
        // A caster set per tracing job (rayon splits a few times per thread).
        let working = threads.max(1) as u64 * 8 * CasterSet::new(world.casters.len()).heap_bytes();
        // The top level peaks while it is built (the memory model's bytes per
        // part in reach), above what the finished tree holds.
        let building = setup.top.len() as u64 * super::memory::PER_PART_IN_REACH;
        self.estimated_bytes = building.max(self.top_level_bytes as u64) + working;
        grid_rays
    }
}

/// What a light's calibration traced and measured.
struct Calibration {
    sample: TracedSample,
    /// Wall time of the whole sample.
    seconds: f64,
    /// The rate of the tiles traced with the sample's answer known (the
    /// bake's), or of the sample's own when every tile is in it.
    rays_per_second: f64,
}

/// Traces a spread sample of the light's tiles (`setup`; `grid_rays` in
/// all) as [`Phase::Calibrating`] of `progress`, to measure its ray rate
/// on this machine.
fn calibrate(
    world: &BakeWorld,
    config: &BakeConfig,
    setup: &LightSetup,
    grid_rays: u64,
    progress: &dyn Progress,
) -> Calibration {
    let light = &config.lights[setup.index];
    let rays = setup.rays(world, config);
    let tiles = rays.tile_count();
    let every = sample_stride(tiles, setup.grid.width().div_ceil(super::trace_light::TILE));
    let sampled_tiles = tiles.div_ceil(every);
    let counter = Counter::begin(
        progress,
        Phase::Calibrating,
        Some(&light.name),
        grid_rays * sampled_tiles / tiles.max(1),
    );
    let started = Instant::now();
    let sample = (0..sampled_tiles).into_par_iter().map(|n| n * every);
    let mut useful = grid_pass::trace_tiles(world, setup, &rays, config, sample, None, &counter);
    let cold = (started.elapsed().as_secs_f64(), counter.done());
    // The bake leaves out the rays that can meet only casters already
    // proven, more of them the more it has proven: its rate is the rate of
    // tiles traced with the sample's answer known, not of the sample's
    // own. The tiles next to the sample's (part of the bake all the same)
    // measure it.
    let held = if every > 1 { 2 } else { 1 };
    let mut warm = cold;
    if held == 2 {
        let next = (0..sampled_tiles)
            .into_par_iter()
            .map(|n| n * every + 1)
            .filter(|&t| t < tiles);
        let warm_started = Instant::now();
        let known = Some(&useful);
        let found = grid_pass::trace_tiles(world, setup, &rays, config, next, known, &counter);
        warm = (
            warm_started.elapsed().as_secs_f64(),
            counter.done() - cold.1,
        );
        useful = useful.union(&found);
    }
    let seconds = started.elapsed().as_secs_f64();
    let sample_rays = counter.done();
    counter.finish();
    Calibration {
        sample: TracedSample {
            every,
            held,
            tile_count: tiles,
            pass: GridPassSettings::of(config),
            rays: sample_rays,
            useful,
        },
        seconds,
        rays_per_second: warm.1 as f64 / warm.0.max(1e-6),
    }
}

/// Every how many tiles the calibration traces one: about
/// [`SAMPLE_TILES`] spread over the grid, the stride coprime with the tile
/// rows so the sample walks across columns instead of down one.
fn sample_stride(tiles: u64, tiles_per_row: u32) -> u64 {
    let mut every = (tiles / SAMPLE_TILES).max(1);
    while every > 1 && gcd(every, tiles_per_row as u64) != 1 {
        every += 1;
    }
    every
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// Byte sizes for people: `512 B`, `3.4 MB`, `1.20 GB` (decimal units).
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= 1e9 {
        format!("{:.2} GB", b / 1e9)
    } else if b >= 1e6 {
        format!("{:.1} MB", b / 1e6)
    } else if b >= 1e3 {
        format!("{:.1} kB", b / 1e3)
    } else {
        format!("{bytes} B")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::ResPaths;
    use crate::progress::Silent;
    use crate::scene::{load_scene, LoadConfig};

    #[test]
    fn a_cached_bake_prepares_the_share_of_chunks_its_most_missing_light_lacks() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/worlds/small");
        let settings = crate::files::read_bake_settings(&root.join("bake.xml")).unwrap();
        let config = BakeConfig::from_settings(&settings);
        let light = |index, cells: Option<(u64, u64)>| LightPlan {
            cells: cells.map(|c| c.0),
            cells_stored: cells.map(|c| c.1),
            ..LightPlan::before_setup(&config, index)
        };
        let every_cell_stored = [light(0, Some((10, 10))), light(1, Some((4, 4)))];
        assert_eq!(cached_output_share(&every_cell_stored), 0.0);
        let half_missing = [
            light(0, Some((10, 9))),
            light(1, Some((8, 4))),
            light(2, None),
        ];
        assert_eq!(cached_output_share(&half_missing), 0.5);
    }

    /// The plan's calibration tiles are not traced again by the bake that
    /// follows it ([`GridSource`] for [`Plan`]): its masks must be those of
    /// a bake that traces every tile, on every fixture, light kind and
    /// supersampling.
    #[test]
    fn a_bake_after_its_plan_equals_a_bake_of_every_tile() {
        for name in ["small", "village"] {
            let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("fixtures/worlds")
                .join(name);
            let settings = crate::files::read_bake_settings(&root.join("bake.xml")).unwrap();
            let scene = load_scene(&LoadConfig {
                res_paths: ResPaths::new(settings.res_paths.clone()),
                space: settings.space.clone(),
                speedtrees: settings.speedtrees.clone(),
            })
            .unwrap();
            let world = BakeWorld::build(&scene, &Silent);
            let plain = BakeConfig::from_settings(&settings);
            let passes = [
                plain.clone(),
                BakeConfig {
                    supersample: 2,
                    ..plain.clone()
                },
                BakeConfig {
                    filter_radius: 1,
                    ..plain.clone()
                },
                BakeConfig {
                    grid_mode: GridMode::Conservative,
                    ..plain.clone()
                },
            ];
            // The beams and halos on the smaller fixture only (seconds).
            let passes = if name == "small" {
                &passes[..]
            } else {
                &passes[..1]
            };
            for config in passes.iter().cloned() {
                let plan = plan(&world, &config, Baseline::default(), &Silent).unwrap();
                let sampled = plan.lights.iter().filter(|l| l.sample.is_some()).count();
                assert_eq!(sampled, config.lights.len(), "{name}: every light sampled");
                assert!(
                    plan.lights.iter().all(|l| l.sample_rays < l.rays),
                    "{name}: a sample, not the grid"
                );
                let after_plan = super::super::bake_from(&world, &config, &Silent, &plan).unwrap();
                let whole = super::super::bake_world(&world, &config, &Silent).unwrap();
                assert_eq!(
                    after_plan.masks,
                    whole.masks,
                    "{name} with {:?}",
                    GridPassSettings::of(&config)
                );
                for (a, b) in after_plan.lights.iter().zip(&whole.lights) {
                    assert_eq!(a.rays, b.rays);
                }
            }
        }
    }

    #[test]
    fn the_sample_stride_spreads_over_columns() {
        assert_eq!(sample_stride(10, 4), 1);
        // 48 rows of 48 tiles: 48 would walk down one column; 49 does not.
        let every = sample_stride(48 * 48, 48);
        assert_eq!(every, 49);
        let columns: std::collections::BTreeSet<u64> = (0..48 * 48)
            .step_by(every as usize)
            .map(|t| t % 48)
            .collect();
        assert!(columns.len() > 40, "{columns:?}");
    }

    #[test]
    fn human_bytes_reads_well() {
        assert_eq!(human_bytes(512), "512 B");
        assert_eq!(human_bytes(3_400_000), "3.4 MB");
        assert_eq!(human_bytes(1_200_000_000), "1.20 GB");
    }
}
