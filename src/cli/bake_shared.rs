//! What `bake`, `bake --shard` and `merge` share: the options that decide
//! a bake's answer (`VerdictOptions`, which `explain` takes too), loading
//! the scene (with the refusal of broken input), and writing the chunks,
//! the report and the per-light table.

use super::cache::{self, CacheArgs};
use super::load_config;
use super::messages;
use super::pipeline::{self, count, PipelineArgs};
use super::progress::{ProgressArgs, Reporter};
use anyhow::{Context, Result};
use rayon::prelude::*;
use shadowcull::bake::cached::{CacheReport, PhaseCounts};
use shadowcull::bake::world_record::LightLine;
use shadowcull::bake::{output, BakeConfig, BakeResult, GridMode};
use shadowcull::cache::{Cache, Kind, KnownFiles};
use shadowcull::files::{self, ResPaths};
use shadowcull::formats::bake_settings::{BakeSettings, FaceCulling};
use shadowcull::scene::{self, Scene};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where a bake's (or a merge's) results go.
#[derive(Debug, clap::Args)]
pub struct OutputArgs {
    /// Write every chunk of the space under DIR (at its path relative to its
    /// res root) instead of in place.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Write the machine-readable report (JSON) to FILE (`-`: standard
    /// output; the table then goes to standard error).
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    /// Write a self-contained HTML page to FILE: per light its totals,
    /// savings and map, the culled casters (a table that sorts and
    /// filters), what was skipped, the settings and the command.
    #[arg(long, value_name = "FILE")]
    pub html: Option<PathBuf>,
}

/// The options that decide which casters a bake keeps: `bake`, `bake
/// --shard`, `merge` and `explain` take the same ones, so an explanation
/// can be asked for exactly the bake it explains.
#[derive(Debug, clap::Args)]
pub struct VerdictOptions {
    /// Override <faceCulling>.
    #[arg(long, value_name = "MODE", value_parser = ["back", "front", "none"])]
    face_culling: Option<String>,
    /// Override <heightBias> (metres).
    #[arg(long, value_name = "M", allow_negative_numbers = true)]
    height_bias: Option<f64>,
    /// Override <tieEpsilon> (metres along a ray).
    #[arg(long, value_name = "M", allow_negative_numbers = true)]
    tie_epsilon: Option<f64>,
    /// Rays per texel side: k traces a k×k pattern per texel.
    #[arg(long, value_name = "K", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    supersample: u32,
    /// After the grid, aim extra rays at the surfaces of casters not yet
    /// useful (catches casters smaller than a texel). A distributed bake
    /// refines in `merge`.
    #[arg(long)]
    pub refine: bool,
    /// Rays per caster for --refine, at area-weighted points of its surface
    /// (64: the sweep reference's; they find slivers thinner than the
    /// footprint lattice).
    #[arg(long, value_name = "N", default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=4096))]
    refine_samples: u32,
    /// Rays per texel side with which --refine samples the light-space
    /// footprint of every caster the grid did not prove useful (8: the
    /// lattice of a grid 8× denser).
    #[arg(long, value_name = "D", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    refine_density: u32,
    /// Trace each texel's beam instead of its centre ray: keep every caster
    /// that some placement of the shadow-map grid could make useful (never a
    /// missing shadow at any grid offset; keeps more).
    #[arg(long)]
    conservative: bool,
    /// PCF margin in texels: a caster front-most at a texel is also useful
    /// for surfaces behind its depth up to K texels away (0: docs/contract.md §4).
    #[arg(long, value_name = "K", default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=16))]
    filter_radius: u32,
    /// Trace every ray against every triangle instead of the BVH (the
    /// correctness oracle; slow).
    #[arg(long, hide = true)]
    brute_force: bool,
}

impl VerdictOptions {
    /// The settings file's values with these overrides, every light kept.
    pub fn config(&self, settings: &BakeSettings) -> Result<BakeConfig> {
        let mut config = BakeConfig {
            brute_force: self.brute_force,
            supersample: self.supersample,
            refine_samples: if self.refine { self.refine_samples } else { 0 },
            refine_density: if self.refine { self.refine_density } else { 0 },
            grid_mode: if self.conservative {
                GridMode::Conservative
            } else {
                GridMode::Centres
            },
            filter_radius: self.filter_radius,
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
        Ok(config)
    }
}

/// The options that decide a bake's answer and how it runs: `bake`, `bake
/// --shard` and `merge` take the same ones.
#[derive(Debug, clap::Args)]
pub struct BakeOptions {
    /// Worker threads (default: one per core). Results are identical for any N.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    threads: Option<u16>,
    #[command(flatten)]
    pub verdict: VerdictOptions,
    #[command(flatten)]
    pub pipeline: PipelineArgs,
    #[command(flatten)]
    pub progress: ProgressArgs,
    #[command(flatten)]
    pub cache: CacheArgs,
}

impl BakeOptions {
    /// The settings file's values with these overrides and the `--light`
    /// selection.
    pub fn config(&self, settings: &BakeSettings, settings_file: &Path) -> Result<BakeConfig> {
        let config = self.verdict.config(settings)?;
        let config = pipeline::select_lights(config, &self.pipeline.lights, settings_file)?;
        anyhow::ensure!(
            !config.lights.is_empty(),
            "{}: no <light> in <lights>: nothing to bake",
            settings_file.display()
        );
        Ok(config)
    }

    /// Runs `work` on a pool of `--threads` workers.
    pub fn in_pool<T: Send>(&self, work: impl FnOnce() -> Result<T> + Send) -> Result<T> {
        super::thread_pool(self.threads)?.install(work)
    }
}

/// Loads the scene of `settings` with progress, says what it holds, and
/// refuses it when it has problems (unless `--keep-going`). Chunk files
/// `known` vouches for are read back from `cache` without being read.
pub fn load_scene_told(
    settings: &BakeSettings,
    options: &BakeOptions,
    reporter: &Reporter,
    cache: Option<&Cache>,
    known: &KnownFiles,
) -> Result<Scene> {
    let started = Instant::now();
    let scene = scene::load_scene_cached(&load_config(settings), reporter, cache, known)?;
    let keep_going = options.pipeline.keep_going;
    say_loaded(&scene, started, keep_going, reporter);
    if let Some(cache) = cache {
        say_chunks_cached(cache, reporter);
    }
    pipeline::refuse_problems(&scene, keep_going, settings.unmodelled_casters)?;
    Ok(scene)
}

/// How many chunks the load read back from the cache and how many it
/// parsed.
fn say_chunks_cached(cache: &Cache, reporter: &Reporter) {
    let chunks = PhaseCounts::of_kind(cache, Kind::Chunk);
    reporter.say(
        "cache_chunks",
        &format!(
            "cache: chunks: {} of {} read back without parsing, {} parsed",
            chunks.reused,
            chunks.reused + chunks.computed,
            chunks.computed
        ),
        serde_json::json!({ "chunks": chunks }),
    );
}

/// The `loaded` line: what loading found, how long it took, and how many
/// problems follow (`refuse_problems` lists them either way; no report is
/// written when they fail the bake).
fn say_loaded(scene: &Scene, started: Instant, keep_going: bool, reporter: &Reporter) {
    let stats = scene.stats();
    let parts = placed_parts(scene);
    let seconds = started.elapsed().as_secs_f64();
    let problems = match (scene.problems.len(), keep_going) {
        (0, _) => String::new(),
        (n, false) => format!("; {} (listed below)", count(n, "problem", "problems")),
        (n, true) => format!(
            "; {} (listed below), left out by --keep-going",
            count(n, "problem", "problems")
        ),
    };
    let trees = match (stats.speedtrees, stats.speedtrees_without_proxy) {
        (0, _) => String::new(),
        (n, 0) => format!(", {n} speedtrees"),
        (n, unproxied) => format!(", {n} speedtrees ({unproxied} without a proxy)"),
    };
    let text = format!(
        "loaded {} chunks, {} instances ({} model parts){trees}, {} model triangles, {} terrain blocks in {seconds:.2} s{problems}",
        stats.chunks, stats.instances, parts, stats.triangles, stats.terrain_blocks,
    );
    let fields = serde_json::json!({
        "chunks": stats.chunks,
        "instances": stats.instances,
        "model_parts": parts,
        "model_triangles": stats.triangles,
        "terrain_blocks": stats.terrain_blocks,
        "speedtrees": stats.speedtrees,
        "speedtrees_without_proxy": stats.speedtrees_without_proxy,
        "seconds": seconds,
        "problems": scene.problems.len(),
        "keep_going": keep_going,
    });
    reporter.say("loaded", &text, fields);
}

/// The model parts a bake places: one per `<resource>` of every model or
/// shell instance whose resources all loaded (an instance with two is two
/// parts); a light's reach counts these and the speedtrees' proxies.
pub fn placed_parts(scene: &Scene) -> usize {
    scene
        .instances
        .par_iter()
        .filter(|i| i.is_complete() && i.kind.names_models())
        .map(|i| i.parts.len())
        .sum()
}

/// Warns, before any ray is traced, about every chunk of the space an
/// in-place bake could not replace (read-only as version control leaves
/// files not checked out, another user's, not a regular file). Which chunks
/// change is known only after tracing: a locked chunk whose bytes stay the
/// same is no problem, one that must change makes the write refuse the
/// whole batch (nothing written, every such file named), so a build
/// engineer can stop here instead of after hours of tracing.
pub fn warn_locked_chunks(scene: &Scene, output_args: &OutputArgs, options: &BakeOptions) {
    if output_args.out.is_some() || options.pipeline.writes_nothing() {
        return;
    }
    let checked = files::check_replaceable(scene.chunks.iter().map(|c| c.file.as_path()));
    if let Err(shadowcull::error::Error::Refused { files }) = checked {
        let mut text = format!(
            "{} chunk file(s) cannot be replaced; if the bake changes any of them it writes nothing and fails at the end (make them writable, e.g. check them out, or bake with --out DIR):",
            files.len()
        );
        for (file, why) in &files {
            text += &format!("\n  {}: {why}", file.display());
        }
        messages::warning(&text);
    }
}

/// What [`write_results`] writes from.
pub struct Results<'a> {
    pub scene: &'a Scene,
    pub res_paths: &'a [PathBuf],
    pub config: &'a BakeConfig,
    /// The settings file, shown in the HTML report.
    pub settings_file: &'a Path,
    pub started: Instant,
    /// The bake's cache: chunks whose `<shadow>`s it knows are kept
    /// without being parsed.
    pub cache: Option<&'a Cache>,
}

/// Keeps the bits of lights not baked, writes the chunks (unless
/// `--dry-run`/`--check`) and the report as `output_args` says, and prints
/// the per-light table: the end of `bake` and of `merge`.
/// What [`write_results`] leaves behind for a record of the world: every
/// chunk file's new bytes, whether any changes, and the per-light table.
pub struct Wrote {
    pub outputs: Vec<output::ChunkOutput>,
    pub changed: bool,
    pub lights: Vec<LightLine>,
}

pub fn write_results(
    output_args: &OutputArgs,
    options: &BakeOptions,
    results: &Results,
    mut result: BakeResult,
    reporter: &Reporter,
) -> Result<Wrote> {
    let scene = results.scene;
    let res_paths = ResPaths::new(results.res_paths.to_vec());
    let to = output::Destination {
        out_dir: output_args.out.as_deref(),
        bytes: match options.pipeline.writes_nothing() {
            true => output::OutputBytes::Dropped,
            false => output::OutputBytes::Kept,
        },
    };
    // The load's counts: the output reads entries only to copy them.
    let loaded = results
        .cache
        .map(|cache| PhaseCounts::of_kind(cache, Kind::Chunk));
    let (outputs, kept) =
        output::chunk_outputs_cached(scene, &mut result, &res_paths, to, reporter, results.cache)?;
    if let Some(cache) = results.cache {
        let report = result.cache.get_or_insert_with(|| CacheReport {
            dir: cache.dir().display().to_string(),
            ..CacheReport::default()
        });
        report.output = kept;
        report.chunks = loaded.unwrap_or_default();
        reporter.say(
            "cache_output",
            &format!(
                "cache: output: {} of {} chunk files kept without parsing, {} prepared",
                kept.reused,
                outputs.len(),
                kept.computed
            ),
            serde_json::json!({ "output": kept }),
        );
        cache::warn_damaged(cache);
    }
    let changed: Vec<&output::ChunkOutput> = outputs.iter().filter(|o| o.changed).collect();
    // A copy under --out holds the space's settings too, so that it is a
    // res root of the space (`--res-path DIR` then reads the baked chunks).
    let space_settings = match &output_args.out {
        Some(dir) if !options.pipeline.writes_nothing() => {
            Some(output::space_settings_output(scene, &res_paths, dir)?)
        }
        _ => None,
    };
    let written = if options.pipeline.writes_nothing() {
        Vec::new()
    } else {
        output::write_outputs(outputs.iter().chain(&space_settings), reporter)?;
        changed
            .iter()
            .map(|o| o.target.display().to_string())
            .collect()
    };
    let wrote_space_settings = space_settings.is_some_and(|o| o.changed);
    let to_stdout = output_args.report.as_deref() == Some(Path::new("-"));
    if let Some(path) = &output_args.report {
        let mut report = output::report(scene, &result);
        report.files_changed = changed
            .iter()
            .map(|o| o.target.display().to_string())
            .collect();
        report.files_written = written.clone();
        // Written as it is made: the casters of a large world never sit
        // in memory whole, neither as values nor as JSON.
        if to_stdout {
            let mut stdout = std::io::BufWriter::new(std::io::stdout().lock());
            serde_json::to_writer_pretty(&mut stdout, &report).context("report")?;
            writeln!(stdout)?;
            stdout.flush()?;
        } else {
            files::write_atomic_streamed(path, &mut |out| {
                serde_json::to_writer_pretty(out, &report).map_err(std::io::Error::other)
            })?;
        }
    }
    if let Some(path) = &output_args.html {
        write_html(path, results, &result)?;
    }
    let summary = summary(
        output_args,
        options,
        results,
        &result,
        &outputs,
        &changed,
        Written {
            chunks: written.len(),
            space_settings: wrote_space_settings,
        },
    );
    if to_stdout {
        for line in summary.lines() {
            messages::say("summary", line, serde_json::json!({}));
        }
    } else {
        print!("{summary}");
    }
    if options.pipeline.check && !changed.is_empty() {
        anyhow::bail!(
            "--check: {} would change (listed above); the baked masks are stale",
            count(changed.len(), "chunk file", "chunk files")
        );
    }
    let changed = !changed.is_empty();
    let lights = result
        .lights
        .iter()
        .map(|light| LightLine {
            bit: light.bit,
            name: light.name.clone(),
            kind: light.kind.to_string(),
            useful: light.useful_casters as u64,
            culled: light.culled_casters as u64,
        })
        .collect();
    Ok(Wrote {
        outputs,
        changed,
        lights,
    })
}

/// Writes the HTML report of `result` to `path`.
fn write_html(path: &Path, results: &Results, result: &BakeResult) -> Result<()> {
    let settings_text = files::read_file(results.settings_file)?;
    let page = shadowcull::report_html::page(&shadowcull::report_html::PageInput {
        scene: results.scene,
        config: results.config,
        result,
        command: &super::command_line(),
        settings_file: &results.settings_file.display().to_string(),
        settings_text: &String::from_utf8_lossy(&settings_text),
    });
    files::write_atomic(path, &page)?;
    Ok(())
}

/// Each light's shadow pass before and after culling: instances, draw
/// calls, triangles, and the share of triangles removed.
fn write_savings(out: &mut String, result: &BakeResult) {
    use std::fmt::Write as _;
    if result.lights.is_empty() {
        return;
    }
    let _ = writeln!(
        out,
        "{:<3} {:<16} {:>21} {:>21} {:>25} {:>8}",
        "bit", "shadow pass", "instances", "draw calls", "triangles", "removed"
    );
    let pair = |c: &shadowcull::bake::savings::BeforeAfter| format!("{} → {}", c.before, c.after);
    for light in &result.lights {
        let s = &light.savings;
        let _ = writeln!(
            out,
            "{:<3} {:<16} {:>21} {:>21} {:>25} {:>7.1}%",
            light.bit,
            light.name,
            pair(&s.instances),
            pair(&s.draw_calls),
            pair(&s.triangles),
            100.0 * s.triangles_removed
        );
    }
}

/// What a bake wrote, for its closing line.
struct Written {
    chunks: usize,
    /// `space.settings` was copied under `--out`.
    space_settings: bool,
}

/// The per-light table, the files that would change (`--dry-run`,
/// `--check`) and the closing line.
fn summary(
    output_args: &OutputArgs,
    options: &BakeOptions,
    results: &Results,
    result: &BakeResult,
    outputs: &[output::ChunkOutput],
    changed: &[&output::ChunkOutput],
    written: Written,
) -> String {
    let (config, started) = (results.config, results.started);
    use std::fmt::Write as _;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<3} {:<16} {:<12} {:>11} {:>10} {:>9} {:>9} {:>8} {:>8} {:>8}",
        "bit",
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
        let _ = writeln!(
            out,
            "{:<3} {:<16} {:<12} {:>11} {:>10} {:>9.3} {:>9.3} {:>8.2} {:>8} {:>8}",
            light.bit,
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
    write_savings(&mut out, result);
    let skipped_lights = config.lights.len() - result.lights.len();
    if skipped_lights > 0 {
        let _ = writeln!(
            out,
            "{} skipped: see the report's `skipped`",
            count(skipped_lights, "light", "lights")
        );
    }
    for line in results.scene.left_out_lines() {
        let _ = writeln!(out, "{line}");
    }
    let dry = options.pipeline.writes_nothing();
    if dry {
        for o in changed {
            let _ = writeln!(out, "would change {}", o.target.display());
        }
    }
    let _ = writeln!(
        out,
        "{} {} of {} chunk files{}{}; {:.2} s in all",
        if dry { "would change" } else { "wrote" },
        if dry { changed.len() } else { written.chunks },
        outputs.len(),
        if written.space_settings {
            " and space.settings"
        } else {
            ""
        },
        match &output_args.out {
            Some(dir) => format!(" under {}", dir.display()),
            None => " in place".to_string(),
        },
        started.elapsed().as_secs_f64()
    );
    out
}
