//! `shadowcull bake`: load, bake, write the chunks and the report, print the
//! per-light table.

use super::progress::Reporter;
use super::{load_config, load_settings, SettingsArgs};
use anyhow::{Context, Result};
use shadowcull::bake::{self, output, BakeConfig};
use shadowcull::formats::bake_settings::{BakeSettings, FaceCulling};
use shadowcull::formats::resources::{self, ResPaths};
use shadowcull::scene::{self, Scene};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct BakeArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    #[command(flatten)]
    output: OutputArgs,
    #[command(flatten)]
    options: BakeOptions,
    #[command(flatten)]
    shard: super::shard::ShardArgs,
}

/// Where a bake's (or a merge's) results go.
#[derive(Debug, clap::Args)]
pub struct OutputArgs {
    /// Write every chunk of the space under DIR (at its path relative to its
    /// res root) instead of in place.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Bake and report, but write no chunk file.
    #[arg(long)]
    pub dry_run: bool,
    /// Write the machine-readable report (JSON) to FILE.
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
}

/// The options that decide a bake's answer: `bake`, `bake --shard` and
/// `merge` take the same ones.
#[derive(Debug, clap::Args)]
pub struct BakeOptions {
    /// Worker threads (default: one per core). Results are identical for any N.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    threads: Option<u16>,
    /// Override <faceCulling>.
    #[arg(long, value_name = "MODE", value_parser = ["back", "front", "none"])]
    face_culling: Option<String>,
    /// Override <heightBias> (metres).
    #[arg(long, value_name = "M")]
    height_bias: Option<f64>,
    /// Override <tieEpsilon> (metres along a ray).
    #[arg(long, value_name = "M")]
    tie_epsilon: Option<f64>,
    /// Rays per texel side: k traces a k×k pattern per texel.
    #[arg(long, value_name = "K", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    supersample: u32,
    /// After the grid, aim extra rays at the surfaces of casters not yet
    /// useful (catches casters smaller than a texel). A distributed bake
    /// refines in `merge`.
    #[arg(long)]
    pub refine: bool,
    /// Rays per caster for --refine.
    #[arg(long, value_name = "N", default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=4096))]
    refine_samples: u32,
    /// Trace every ray against every triangle instead of the BVH (the
    /// correctness oracle; slow).
    #[arg(long, hide = true)]
    brute_force: bool,
}

impl BakeOptions {
    /// The settings file's values with these overrides.
    pub fn config(&self, settings: &BakeSettings, settings_file: &Path) -> Result<BakeConfig> {
        let mut config = BakeConfig {
            brute_force: self.brute_force,
            supersample: self.supersample,
            refine_samples: if self.refine { self.refine_samples } else { 0 },
            ..BakeConfig::from_settings(settings)
        };
        if let Some(mode) = &self.face_culling {
            config.face_culling = FaceCulling::from_name(mode).context("face culling mode")?;
        }
        for (value, name) in [
            (self.height_bias, "--height-bias"),
            (self.tie_epsilon, "--tie-epsilon"),
        ] {
            if let Some(v) = value {
                anyhow::ensure!(
                    v.is_finite() && v >= 0.0,
                    "{name} must be a number ≥ 0, got {v}"
                );
            }
        }
        if let Some(bias) = self.height_bias {
            config.height_bias = bias;
        }
        if let Some(epsilon) = self.tie_epsilon {
            config.tie_epsilon = epsilon;
        }
        anyhow::ensure!(
            !config.lights.is_empty(),
            "{}: no <light> in <lights>: nothing to bake",
            settings_file.display()
        );
        Ok(config)
    }

    /// Runs `work` on a pool of `--threads` workers.
    pub fn in_pool<T: Send>(&self, work: impl FnOnce() -> Result<T> + Send) -> Result<T> {
        let threads = self.threads.map(usize::from).unwrap_or(0);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .context("cannot start worker threads")?;
        pool.install(work)
    }
}

pub fn run(args: BakeArgs) -> Result<()> {
    let settings = load_settings(&args.settings)?;
    let config = args.options.config(&settings, &args.settings.settings)?;
    if args.shard.is_set() {
        return args
            .options
            .in_pool(|| super::shard::run(&args.shard, &settings, &config));
    }
    args.options
        .in_pool(|| bake_with(&args, settings.res_paths.clone(), config, &settings))
}

/// Loads the scene of `settings`, telling what it holds and its problems.
pub(super) fn load_scene_told(settings: &BakeSettings) -> Result<Scene> {
    let started = Instant::now();
    let scene = scene::load_scene(&load_config(settings))?;
    let stats = scene.stats();
    eprintln!(
        "loaded {} chunks, {} instances, {} triangles, {} terrain blocks in {:.2} s{}",
        stats.chunks,
        stats.instances,
        stats.triangles,
        stats.terrain_blocks,
        started.elapsed().as_secs_f64(),
        if scene.problems.is_empty() {
            String::new()
        } else {
            format!(
                "; {} problems (see the report's `skipped`)",
                scene.problems.len()
            )
        }
    );
    for problem in scene.problems.iter().take(5) {
        eprintln!("  {}: {}", problem.what, problem.why);
    }
    if scene.problems.len() > 5 {
        eprintln!("  … and {} more", scene.problems.len() - 5);
    }
    Ok(scene)
}

fn bake_with(
    args: &BakeArgs,
    res_paths: Vec<PathBuf>,
    config: BakeConfig,
    settings: &shadowcull::formats::bake_settings::BakeSettings,
) -> Result<()> {
    let started = Instant::now();
    let scene = load_scene_told(settings)?;
    let reporter = Reporter::new();
    let result = bake::bake(&scene, &config, &reporter)
        .with_context(|| format!("{}", args.settings.settings.display()))?;
    write_results(&args.output, &scene, &result, &res_paths, &config, started)
}

/// Writes the chunks and the report of `result` as `output` says, and
/// prints the per-light table: the end of `bake` and of `merge`.
pub(super) fn write_results(
    output_args: &OutputArgs,
    scene: &Scene,
    result: &bake::BakeResult,
    res_paths: &[PathBuf],
    config: &BakeConfig,
    started: Instant,
) -> Result<()> {
    let res_paths = ResPaths::new(res_paths.to_vec());
    let outputs = output::chunk_outputs(scene, result, &res_paths, output_args.out.as_deref())?;
    let changed = outputs.iter().filter(|o| o.changed).count();
    let written = if output_args.dry_run {
        0
    } else {
        output::write_outputs(&outputs)?
    };
    if let Some(path) = &output_args.report {
        let report = output::report(scene, result);
        let json = serde_json::to_vec_pretty(&report).context("report")?;
        resources::write_atomic(path, &json)?;
    }
    println!(
        "{:<3} {:<16} {:<12} {:>11} {:>10} {:>9} {:>9} {:>8} {:>8} {:>8}",
        "#",
        "light",
        "kind",
        "rays",
        "triangles",
        "bvh s",
        "trace s",
        "Mrays/s",
        "useful",
        "culled"
    );
    for light in &result.lights {
        println!(
            "{:<3} {:<16} {:<12} {:>11} {:>10} {:>9.3} {:>9.3} {:>8.2} {:>8} {:>8}",
            light.index,
            light.name,
            light.kind,
            light.rays,
            light.triangles,
            light.bvh_seconds,
            light.trace_seconds,
            light.rays as f64 / light.trace_seconds.max(1e-9) / 1e6,
            light.useful_casters,
            light.culled_casters
        );
    }
    let skipped_lights = config.lights.len() - result.lights.len();
    if skipped_lights > 0 {
        println!("{skipped_lights} light(s) skipped: see the report's `skipped`");
    }
    let verb = if output_args.dry_run {
        "would change"
    } else {
        "wrote"
    };
    let count = if output_args.dry_run {
        changed
    } else {
        written
    };
    println!(
        "{verb} {count} of {} chunk files{}; {:.2} s in all",
        outputs.len(),
        match &output_args.out {
            Some(dir) => format!(" under {}", dir.display()),
            None => " in place".to_string(),
        },
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
