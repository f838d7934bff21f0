//! Command-line parsing and the subcommands' glue. Library errors become
//! messages here; nothing below this module prints. Standard error is
//! written through `messages`, which knows whether it takes text or JSON.

mod bake;
mod bake_shared;
mod cache;
mod diff;
mod explain;
pub mod memory;
mod merge;
mod messages;
mod pipeline;
mod plan;
mod progress;
mod render;
mod shard;
mod sweep;
mod xcheck;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use messages::{ProblemOutcome, StderrForm};
use shadowcull::files;
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
    /// The bake settings file (XML, its elements in docs/contract.md §3).
    /// Paths in it are relative to it.
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
    /// What changed between two bakes: per light and chunk, the casters
    /// whose bit flipped, appeared or disappeared (two reports or two
    /// folders of chunk files).
    Diff(diff::DiffArgs),
    /// Why one caster is kept or culled for one light: where it is the
    /// front hit, what lies behind it, what hides it; checked against a bake.
    Explain(explain::ExplainArgs),
    /// Print what the world holds, and every problem in it, without baking.
    Inspect {
        #[command(flatten)]
        settings: SettingsArgs,
        /// Print one JSON object instead of the readable summary.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        progress: progress::ProgressArgs,
    },
    /// Draw what the bake decides for one light: its shadow map or a camera view (PNG + legend).
    Render(render::RenderArgs),
    /// Compare the ray-cast bake with the rasterized method (cargo feature `raster`).
    Xcheck(xcheck::XcheckArgs),
    /// What a bake cache folder holds (stats), or empty it (clear).
    Cache(cache::CacheCommand),
    /// Write a synthetic world (BigWorld formats) and its settings file bake.xml.
    Gen {
        /// Output folder (created; existing files of the same names are replaced).
        dir: PathBuf,
        /// Size and content of the world.
        #[arg(long, default_value = "village", value_parser = ["small", "village", "bench", "forest"], conflicts_with = "chunks")]
        preset: String,
        /// Instead of a preset: N×N chunks of 100 m at the bench's density
        /// (128² terrain, 1 m sun texels), written chunk by chunk.
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
        chunks: Option<u32>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Write chunks, models, visuals and space.settings as packed binary
        /// XML, as a shipped game holds them, each chunk with audio,
        /// particle, user data and water items of every binary value type.
        #[arg(long)]
        packed: bool,
    },
}

pub fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(err) if err.use_stderr() && messages::json_asked(std::env::args_os()) => {
            messages::set_form(StderrForm::Json);
            let text = err.to_string();
            let text = text.trim_end();
            messages::error(text.strip_prefix("error: ").unwrap_or(text));
            return ExitCode::from(2);
        }
        Err(err) => {
            let _ = err.print();
            return if err.use_stderr() {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            };
        }
    };
    messages::set_form(cli.command.stderr_form());
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            messages::error(&format!("{err:#}"));
            let usage = err.downcast_ref::<UsageError>().is_some();
            ExitCode::from(if usage { 2 } else { 1 })
        }
    }
}

/// A usage error found after parsing (arguments that parse but do not go
/// together): exit status 2, as clap's own.
#[derive(Debug)]
pub(crate) struct UsageError(pub(crate) String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

impl Command {
    /// `--progress json` makes every line on standard error a JSON object
    /// (the commands without `--progress` write text).
    fn stderr_form(&self) -> StderrForm {
        match self {
            Command::Bake(args) => args.stderr_form(),
            Command::Merge(args) => args.stderr_form(),
            Command::Plan(args) => args.stderr_form(),
            Command::Inspect { progress, .. } => progress.stderr_form(),
            Command::Sweep(_)
            | Command::Render(_)
            | Command::Xcheck(_)
            | Command::Cache(_)
            | Command::Diff(_)
            | Command::Explain(_)
            | Command::Gen { .. } => StderrForm::Text,
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
        Command::Cache(args) => cache::run(args),
        Command::Diff(args) => diff::run(args),
        Command::Explain(args) => explain::run(args),
        Command::Inspect {
            settings,
            json,
            progress,
        } => inspect(&settings, json, &progress),
        Command::Gen {
            dir,
            preset,
            chunks,
            seed,
            packed,
        } => {
            use shadowcull::gen::{generate_each, pack_file, Preset, WorldSize};
            let size = match chunks {
                Some(n) => WorldSize::BenchChunks(n),
                None => WorldSize::Preset(Preset::from_name(&preset).with_context(|| {
                    format!("unknown preset `{preset}`: use small, village, bench or forest")
                })?),
            };
            let mut written = 0usize;
            let started = std::time::Instant::now();
            generate_each(size, seed, |path, bytes| {
                let bytes = if packed {
                    pack_file(path, bytes).map_err(|e| e.in_file(dir.join(path)))?
                } else {
                    bytes
                };
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

/// The command as typed (arguments with spaces quoted), for the render
/// legend and the HTML report.
pub(crate) fn command_line() -> String {
    std::env::args()
        .enumerate()
        .map(|(i, arg)| {
            let arg = if i == 0 {
                "shadowcull".to_string()
            } else {
                arg
            };
            if arg.is_empty() || arg.contains(char::is_whitespace) || arg.contains('"') {
                format!("\"{}\"", arg.replace('"', "\\\""))
            } else {
                arg
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// A worker pool of `threads` (default: one per core).
pub(crate) fn thread_pool(threads: Option<u16>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads.map(usize::from).unwrap_or(0))
        .build()
        .context("cannot start worker threads")
}

/// `shadowcull inspect`: what the world holds and every problem, the
/// settings file's unknown elements first; exit 1 when it lists any.
fn inspect(
    settings_args: &SettingsArgs,
    json: bool,
    progress: &progress::ProgressArgs,
) -> Result<()> {
    let settings = load_settings_with(settings_args, UnknownElements::LeaveToCaller)?;
    let reporter = progress::Reporter::new(progress);
    let scene = scene::load_scene_with(&load_config(&settings), &reporter)?;
    drop(reporter);
    let mut inspection = shadowcull::inspect::inspect(&scene, settings.unmodelled_casters);
    let file = settings_args.settings.display();
    let unknown = settings
        .unknown
        .iter()
        .map(|u| shadowcull::inspect::ProblemEntry {
            what: format!("{file}:{}", u.location()),
            why: u.reason(),
        });
    inspection.problems.splice(0..0, unknown);
    if json {
        println!("{}", inspection.to_json());
    } else {
        print!("{}", inspection.to_text());
    }
    anyhow::ensure!(
        inspection.problems.is_empty(),
        "{} listed: a bake of this world fails unless --keep-going",
        pipeline::count(inspection.problems.len(), "problem", "problems")
    );
    Ok(())
}

/// What a command does with the elements of its settings file that no
/// setting reads (a typo such as `<heightBais>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum UnknownElements {
    /// A strict bake, merge or plan: each is listed (`file:line:column`,
    /// the closest valid name) and the command fails before reading the
    /// world, so nothing is written.
    Refuse,
    /// Each is a warning and is ignored (`--keep-going`, and the commands
    /// that write no chunk: `render`, `sweep`, `xcheck`).
    Warn,
    /// Kept in [`BakeSettings::unknown`] for the caller to list (`inspect`).
    LeaveToCaller,
}

impl UnknownElements {
    /// A bake's or a merge's: refused unless `--keep-going`.
    pub(crate) fn for_bake(keep_going: bool) -> UnknownElements {
        if keep_going {
            UnknownElements::Warn
        } else {
            UnknownElements::Refuse
        }
    }
}

/// [`load_settings_with`] for the commands that write no chunk: unknown
/// elements are warnings.
pub(crate) fn load_settings(args: &SettingsArgs) -> Result<BakeSettings> {
    load_settings_with(args, UnknownElements::Warn)
}

/// Reads the settings file with the command line's overrides and deals
/// with the elements nothing reads as `unknown` says: every subcommand
/// reads its settings here, so each names them alike.
pub(crate) fn load_settings_with(
    args: &SettingsArgs,
    unknown: UnknownElements,
) -> Result<BakeSettings> {
    let mut settings = files::read_bake_settings(&args.settings)?;
    let file = args.settings.display();
    match unknown {
        UnknownElements::Warn => {
            for element in &settings.unknown {
                messages::warning(&format!(
                    "{file}:{}: {} is ignored; {}",
                    element.location(),
                    element.describe(),
                    element.hint()
                ));
            }
        }
        UnknownElements::Refuse if !settings.unknown.is_empty() => {
            for element in &settings.unknown {
                let what = format!("{file}:{}", element.location());
                messages::problem(&what, &element.reason(), ProblemOutcome::Fails);
            }
            anyhow::bail!(
                "{} in the settings file {file} (listed above); the world was not loaded and nothing was written. \
                 Correct the name, or bake with --keep-going to ignore such elements with a warning",
                pipeline::count(settings.unknown.len(), "unknown element", "unknown elements")
            );
        }
        UnknownElements::Refuse | UnknownElements::LeaveToCaller => {}
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
    LoadConfig::from_settings(settings)
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
    fn every_document_the_help_cites_is_in_the_repository() {
        // A document is cited by a path ending in `.md`, by the name before
        // a `§`, or as the README: each must name a file of the repository.
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut command = Cli::command();
        let mut helps = vec![command.render_long_help().to_string()];
        for sub in command.get_subcommands_mut() {
            helps.push(sub.render_long_help().to_string());
        }
        let mut cited = Vec::new();
        for help in &helps {
            let words: Vec<&str> = help
                .split(|c: char| c.is_whitespace() || "(),;:".contains(c))
                .filter(|w| !w.is_empty())
                .collect();
            for (i, word) in words.iter().enumerate() {
                let word = word.trim_end_matches('.');
                let before_section = words.get(i + 1).is_some_and(|w| w.starts_with('§'));
                if word.ends_with(".md") || before_section || word.eq_ignore_ascii_case("readme") {
                    cited.push(word.to_string());
                }
            }
        }
        assert!(cited.iter().any(|c| c == "docs/contract.md"), "{cited:?}");
        for document in &cited {
            assert!(
                root.join(document).is_file(),
                "the help cites `{document}`, which is not a file of the repository"
            );
        }
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
