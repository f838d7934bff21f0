//! Command-line parsing and the subcommands' glue. Library errors become
//! messages here; nothing below this module prints.

mod bake;
mod bake_shared;
pub mod memory;
mod merge;
mod pipeline;
mod plan;
mod progress;
mod render;
mod shard;
mod sweep;
mod xcheck;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use shadowcull::files::{self, ResPaths};
use shadowcull::formats::bake_settings::BakeSettings;
use shadowcull::scene::{self, LoadConfig};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "shadowcull",
    version,
    about = "GPU-free shadow caster culling for BigWorld worlds"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Values of the settings file that every subcommand may override.
#[derive(Debug, clap::Args)]
pub(crate) struct SettingsArgs {
    /// The bake settings file (XML, see README). Paths in it are relative to it.
    settings: PathBuf,
    /// Replace the settings file's <resPaths> (repeatable, searched in order).
    #[arg(long = "res-path", value_name = "DIR")]
    res_paths: Vec<PathBuf>,
    /// Replace the settings file's <space> (a resource name, e.g. spaces/arctic).
    #[arg(long, value_name = "NAME")]
    space: Option<String>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Bake every light and write the masks into the chunk files (or one
    /// shard of a distributed bake: --shard).
    Bake(bake::BakeArgs),
    /// Estimate a bake's time and peak memory, per light, without baking.
    Plan(plan::PlanArgs),
    /// OR the partial results of a distributed bake's shards and write the
    /// chunks as `bake` does.
    Merge(merge::MergeArgs),
    /// Classification error against run time over a ladder of settings.
    Sweep(sweep::SweepArgs),
    /// Print what the world holds, without baking.
    Inspect {
        #[command(flatten)]
        settings: SettingsArgs,
        /// Print one JSON object instead of the readable summary.
        #[arg(long)]
        json: bool,
    },
    /// Draw what the bake decides for one light: its shadow map or a camera view (PNG + legend).
    Render(render::RenderArgs),
    /// Compare the ray-cast bake with the rasterized method (cargo feature `raster`).
    Xcheck(xcheck::XcheckArgs),
    /// Write a synthetic world (BigWorld formats) and its settings file bake.xml.
    Gen {
        /// Output folder (created; existing files of the same names are replaced).
        dir: PathBuf,
        /// Size and content of the world.
        #[arg(long, default_value = "village", value_parser = ["small", "village", "bench"], conflicts_with = "chunks")]
        preset: String,
        /// Instead of a preset: N×N chunks of 100 m at the bench's density
        /// (128² terrain, 1 m sun texels), written chunk by chunk.
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
        chunks: Option<u32>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(err) => {
            let _ = err.print();
            return if err.use_stderr() {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            };
        }
    };
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::from(1)
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Bake(args) => bake::run(args),
        Command::Plan(args) => plan::run(args),
        Command::Merge(args) => merge::run(args),
        Command::Sweep(args) => sweep::run(args),
        Command::Render(args) => render::run(args),
        Command::Xcheck(args) => xcheck::run(args),
        Command::Inspect { settings, json } => {
            let settings = load_settings(&settings)?;
            let scene = scene::load_scene(&load_config(&settings))?;
            let inspection = shadowcull::inspect::inspect(&scene);
            if json {
                println!("{}", inspection.to_json());
            } else {
                print!("{}", inspection.to_text());
            }
            anyhow::ensure!(
                scene.problems.is_empty(),
                "{} listed: a bake of this world fails unless --keep-going",
                pipeline::count(scene.problems.len(), "problem", "problems")
            );
            Ok(())
        }
        Command::Gen {
            dir,
            preset,
            chunks,
            seed,
        } => {
            use shadowcull::gen::{generate_each, Preset, WorldSize};
            let size = match chunks {
                Some(n) => WorldSize::BenchChunks(n),
                None => WorldSize::Preset(Preset::from_name(&preset).with_context(|| {
                    format!("unknown preset `{preset}`: use small, village or bench")
                })?),
            };
            let mut written = 0usize;
            let started = std::time::Instant::now();
            generate_each(size, seed, |path, bytes| {
                files::write_atomic(&dir.join(path), &bytes)?;
                written += 1;
                if written.is_multiple_of(2000) {
                    eprintln!(
                        "gen: {written} files written ({:.0} s)",
                        started.elapsed().as_secs_f64()
                    );
                }
                Ok::<(), shadowcull::error::Error>(())
            })?;
            // A command that works as this program was run: not every
            // user has it on PATH.
            println!(
                "wrote {written} files to {}; bake it with: {} bake {}",
                dir.display(),
                files::Invocation::of_this_program("shadowcull").command(),
                dir.join("bake.xml").display()
            );
            Ok(())
        }
    }
}

/// A worker pool of `threads` (default: one per core).
pub(crate) fn thread_pool(threads: Option<u16>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads.map(usize::from).unwrap_or(0))
        .build()
        .context("cannot start worker threads")
}

/// Reads the settings file with the command line's overrides, and warns
/// (`file:line:column`) about the elements in it that no setting reads (a
/// typo such as `<heightBais>`): every subcommand reads its settings here,
/// so each warns alike.
pub(crate) fn load_settings(args: &SettingsArgs) -> Result<BakeSettings> {
    let mut settings = files::read_bake_settings(&args.settings)?;
    for unknown in &settings.unknown {
        eprintln!("warning: {}:{unknown}", args.settings.display());
    }
    if !args.res_paths.is_empty() {
        settings.res_paths = args.res_paths.clone();
    }
    if let Some(space) = &args.space {
        settings.space = space.clone();
    }
    Ok(settings)
}

pub(crate) fn load_config(settings: &BakeSettings) -> LoadConfig {
    LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_command_line_definition_is_consistent() {
        // Every argument a conflict, requirement or default names exists,
        // and no two arguments share a name or a short flag.
        Cli::command().debug_assert();
    }

    #[test]
    fn a_shard_refuses_the_flags_of_a_whole_bake() {
        for flag in ["--out=x", "--dry-run", "--report=r.json", "--refine"] {
            let parsed = Cli::try_parse_from([
                "shadowcull",
                "bake",
                "bake.xml",
                "--shard=0/2",
                "--partial=p",
                flag,
            ]);
            let err = parsed.expect_err(flag);
            assert_eq!(
                err.kind(),
                clap::error::ErrorKind::ArgumentConflict,
                "{flag}"
            );
        }
        assert!(Cli::try_parse_from(["shadowcull", "bake", "bake.xml", "--shard=0/2"]).is_err());
    }
}
