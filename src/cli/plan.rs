//! `shadowcull plan SETTINGS`: what a bake will cost, printed before any
//! light is traced (also the first lines of `bake`), and `--max-memory`.

use super::messages::{self, ProblemOutcome, StderrForm};
use super::pipeline;
use super::progress::{ProgressArgs, Reporter};
use super::{load_config, load_settings_with, SettingsArgs, UnknownElements};
use anyhow::{Context, Result};
use shadowcull::bake::cached::BakeCache;
use shadowcull::bake::estimate::{self, human_bytes, Baseline, LightPlan, Plan};
use shadowcull::bake::setup::BakeWorld;
use shadowcull::bake::{self, BakeConfig};
use shadowcull::files;
use shadowcull::formats::bake_settings::UnmodelledCasters;
use shadowcull::scene::{self, Scene, SceneKeys};
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct PlanArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// Plan only this light (repeatable).
    #[arg(long = "light", value_name = "NAME")]
    lights: Vec<String>,
    /// Exit 1 when the peak memory estimate is above SIZE (e.g. 8G).
    #[arg(long, value_name = "SIZE", value_parser = pipeline::parse_size)]
    max_memory: Option<u64>,
    /// Rays per texel side, as for bake.
    #[arg(long, value_name = "K", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    supersample: u32,
    /// Worker threads (default: one per core).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    threads: Option<u16>,
    /// Print the plan as one JSON object instead of lines.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    progress: ProgressArgs,
    #[command(flatten)]
    cache: super::cache::CacheArgs,
}

impl PlanArgs {
    pub fn stderr_form(&self) -> StderrForm {
        self.progress.stderr_form()
    }
}

pub fn run(args: PlanArgs) -> Result<()> {
    let file = args.settings.settings.clone();
    // A plan answers for the bake it predicts, which refuses them.
    let settings = load_settings_with(&args.settings, UnknownElements::Refuse)?;
    let config = BakeConfig {
        supersample: args.supersample,
        ..BakeConfig::from_settings(&settings)
    };
    let config = pipeline::select_lights(config, &args.lights, &file)?;
    let pool = super::thread_pool(args.threads)?;
    pool.install(|| {
        let started = Instant::now();
        let reporter = Reporter::new(&args.progress);
        let cache = args.cache.open(&file)?;
        let scene = scene::load_scene_cached(
            &load_config(&settings),
            &reporter,
            cache.as_ref(),
            &shadowcull::cache::KnownFiles::default(),
        )?;
        for problem in &scene.problems {
            messages::problem(&problem.what, &problem.why, ProblemOutcome::Fails);
        }
        let world = bake::checked_world(&scene, &config, &reporter).with_context(|| file.display().to_string())?;
        let bake_cache = cache
            .as_ref()
            .map(|cache| BakeCache::new(cache, &world, SceneKeys::of(&scene), None));
        let plan = make_plan(
            &scene,
            &world,
            &config,
            started,
            &reporter,
            bake_cache.as_ref(),
        )?;
        if let Some(cache) = &cache {
            super::cache::warn_damaged(cache);
        }
        if args.json {
            println!("{}", serde_json::to_string_pretty(&plan)?);
        } else {
            for line in plan_lines(&plan) {
                println!("{line}");
            }
            for line in scene.left_out_lines() {
                println!("plan: {line}");
            }
        }
        check_memory(&plan, args.max_memory)?;
        anyhow::ensure!(
            scene.problems.is_empty(),
            "{} in the input (listed above): a bake fails unless --keep-going",
            pipeline::count(scene.problems.len(), "problem", "problems")
        );
        let unmodelled = scene.unmodelled_casters();
        anyhow::ensure!(
            unmodelled == 0 || settings.unmodelled_casters == UnmodelledCasters::Keep,
            "{} without a proxy (listed above): a bake fails unless the settings declare their proxies in <speedtrees>, \
             or say <unmodelledCasters> keep </unmodelledCasters>, or --keep-going",
            pipeline::count(unmodelled, "speedtree placement", "speedtree placements")
        );
        Ok(())
    })
}

/// Plans `config` over a built world, measuring this process first.
pub fn make_plan(
    scene: &Scene,
    world: &BakeWorld,
    config: &BakeConfig,
    started: Instant,
    progress: &dyn shadowcull::progress::Progress,
    cache: Option<&BakeCache>,
) -> Result<Plan> {
    let memory = files::resident_memory();
    let chunk_files = files::file_sizes(scene.chunks.iter().map(|c| c.file.as_path()));
    let baseline = Baseline {
        resident_bytes: memory.resident,
        peak_resident_bytes: memory.peak,
        elapsed_seconds: started.elapsed().as_secs_f64(),
        chunk_file_bytes: chunk_files.total,
        largest_chunk_file_bytes: chunk_files.largest,
        threads: rayon::current_num_threads(),
    };
    Ok(estimate::plan_with(
        world, config, baseline, progress, cache,
    )?)
}

/// `--max-memory`: refuse cleanly, before tracing, above the estimate.
pub fn check_memory(plan: &Plan, max_memory: Option<u64>) -> Result<()> {
    if let Some(limit) = max_memory {
        anyhow::ensure!(
            plan.estimated_peak_bytes <= limit,
            "the plan's peak memory estimate {} is above --max-memory {}; nothing was traced or written. \
             Bake fewer lights at a time (--light), coarsen <texelSize>/<resolution>, or allow more memory",
            human_bytes(plan.estimated_peak_bytes),
            human_bytes(limit)
        );
    }
    Ok(())
}

/// The plan as `bake` says it before tracing: its lines, or with
/// `--progress json` a `plan` event per light (the fields of `plan
/// --json`'s `lights`) and a `plan_total`.
pub fn say_plan(plan: &Plan, reporter: &Reporter) {
    for light in &plan.lights {
        let fields = serde_json::to_value(light).unwrap_or_default();
        reporter.say("plan", &light_line(light), fields);
    }
    let fields = serde_json::json!({
        "casters": plan.casters,
        "bottom_level_bytes": plan.bottom_level_bytes,
        "calibration_seconds": plan.calibration_seconds,
        "estimated_seconds": plan.estimated_seconds,
        "estimated_peak_bytes": plan.estimated_peak_bytes,
    });
    reporter.say("plan_total", &total_line(plan), fields);
}

/// One line per light and a total.
pub fn plan_lines(plan: &Plan) -> Vec<String> {
    let mut lines: Vec<String> = plan.lights.iter().map(light_line).collect();
    lines.push(total_line(plan));
    lines
}

/// A light's grid, rays, reach and estimate. Its reach is counted in model
/// parts (an instance with two `<resource>`s is two), terrain blocks, and
/// the hittable triangles of both, as the reach is built: so a sun over
/// everything counts more parts than the `loaded` line's instances, and
/// more triangles than its model triangles.
fn light_line(light: &LightPlan) -> String {
    let mut line = format!(
        "plan: light {} `{}` ({}, bit {}): ",
        light.index, light.name, light.kind, light.bit
    );
    match &light.nothing_to_trace {
        Some(why) => line += &format!("nothing to trace ({why})"),
        None => {
            // No ray rate when the cache holds every cell: nothing was
            // traced to measure one, and nothing is left to trace.
            let rate = match light.rays_per_second {
                r if r > 0.0 => format!(" at {:.2} Mrays/s", r / 1e6),
                _ => " (no ray left to trace)".to_string(),
            };
            line += &format!(
                "{} × {} × {} texels, {} rays; in reach {} model parts, {} terrain blocks, \
                 {} triangles (parts' and blocks'); est. {:.1} s{rate}, {} for its \
                 top level and tracing",
                light.faces,
                light.width,
                light.height,
                light.rays,
                light.instances,
                light.terrain_blocks,
                light.triangles,
                light.estimated_seconds,
                human_bytes(light.estimated_bytes)
            );
            if let (Some(cells), Some(stored)) = (light.cells, light.cells_stored) {
                line += &format!(
                    "; cache: {stored} of {cells} cells stored, a cached bake traces {}",
                    cells - stored
                );
            }
        }
    }
    line
}

/// The whole bake's estimate and how it was made.
fn total_line(plan: &Plan) -> String {
    if plan.lights.iter().any(|l| l.cells.is_some()) {
        return format!(
            "plan: total est. {:.1} s and peak memory {} for the whole bake ({} casters; bottom levels {}). \
             Time is a calibration: up to {} cells per light that the cache does not hold, traced on this \
             machine in {:.2} s and stored (the bake reuses them); memory is what this process holds now \
             plus the largest light's top level and tracing, the masks and a chunk file per thread",
            plan.estimated_seconds,
            human_bytes(plan.estimated_peak_bytes),
            plan.casters,
            human_bytes(plan.bottom_level_bytes as u64),
            shadowcull::bake::cached::CALIBRATION_CELLS,
            plan.calibration_seconds
        );
    }
    format!(
        "plan: total est. {:.1} s and peak memory {} for the whole bake ({} casters; bottom levels {}). \
         Time is a calibration: {} tiles of 32×32 texels per light and their neighbours traced on this machine in {:.2} s; \
         memory is what this process holds now plus the largest light's top level and tracing, the masks \
         and a chunk file per thread",
        plan.estimated_seconds,
        human_bytes(plan.estimated_peak_bytes),
        plan.casters,
        human_bytes(plan.bottom_level_bytes as u64),
        estimate::SAMPLE_TILES,
        plan.calibration_seconds
    )
}
