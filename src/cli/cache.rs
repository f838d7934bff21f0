//! The bake cache on the command line: `--cache DIR`, `--no-cache`,
//! `--cache-max SIZE` (on `bake`, `bake --shard`, `merge` and `plan`), what
//! happens to the folder after a bake (eviction, warnings about damaged
//! entries), the world's record (a bake that finds it holding says so and
//! stops), and `shadowcull cache DIR stats|clear`.

use super::bake_shared::BakeOptions;
use super::messages;
use super::pipeline::{count, parse_size};
use super::progress::Reporter;
use anyhow::{Context, Result};
use shadowcull::bake::estimate::human_bytes;
use shadowcull::bake::world_record::{self, Baked, NotRecorded, UpToDate};
use shadowcull::cache::{self, Cache, Key};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The folder a bake keeps its cache in by default, beside its settings
/// file.
pub const DEFAULT_FOLDER: &str = ".shadowcull-cache";

/// The cache flags.
#[derive(Debug, Clone, clap::Args)]
pub struct CacheArgs {
    /// Keep what a later bake can reuse in DIR, and reuse what it holds
    /// (default: .shadowcull-cache beside the settings file). The result
    /// is byte-identical to a bake without cache.
    #[arg(long, value_name = "DIR")]
    cache: Option<PathBuf>,
    /// Bake without a cache: trace everything, keep nothing.
    #[arg(long, conflicts_with = "cache")]
    no_cache: bool,
    /// Size limit of the cache folder: after the bake the least recently
    /// used entries are removed until the rest fit (e.g. 500M, 2G).
    #[arg(long, value_name = "SIZE", value_parser = parse_size)]
    cache_max: Option<u64>,
}

impl CacheArgs {
    /// The cache a command with settings file `settings` uses, `None` with
    /// `--no-cache`. Its build identity is the running executable's hash.
    pub fn open(&self, settings: &Path) -> Result<Option<Cache>> {
        if self.no_cache {
            return Ok(None);
        }
        let dir = match &self.cache {
            Some(dir) => dir.clone(),
            None => settings
                .parent()
                .filter(|dir| !dir.as_os_str().is_empty())
                .unwrap_or(Path::new("."))
                .join(DEFAULT_FOLDER),
        };
        let build = cache::executable_build_in(&dir).context("the bake cache's build identity")?;
        let max = self.cache_max.unwrap_or(cache::DEFAULT_MAX_BYTES);
        Ok(Some(Cache::open(dir, max, build)))
    }
}

/// Warns about every damaged entry met so far (one line each).
pub fn warn_damaged(cache: &Cache) {
    for warning in cache.take_warnings() {
        messages::warning(&warning);
    }
}

/// After a bake: the folder kept under its limit, and what went wrong
/// with it said (never an error of the bake: the cache only saves work).
pub fn finish(cache: &Cache, reporter: &Reporter) {
    warn_damaged(cache);
    match cache.evict() {
        Ok(0) => {}
        Ok(removed) => reporter.say(
            "cache_evicted",
            &format!(
                "cache: {} removed from {} to keep it under its size limit",
                count(
                    removed,
                    "least recently used entry",
                    "least recently used entries"
                ),
                cache.dir().display()
            ),
            serde_json::json!({ "removed": removed }),
        ),
        Err(err) => messages::warning(&format!("cache: {err}")),
    }
}

/// A bake that found the world as its record left it: what it checked,
/// the recorded table, and the closing line a bake prints.
pub fn say_up_to_date(
    found: &UpToDate,
    options: &BakeOptions,
    started: Instant,
    reporter: &Reporter,
) {
    reporter.say(
        "up_to_date",
        &format!(
            "cache: up to date: no file the last bake read changed ({}, {} checked, {} read again); nothing to load, trace or write",
            count(found.files, "file", "files"),
            count(found.folders, "folder", "folders"),
            found.files_read
        ),
        serde_json::json!({
            "files": found.files,
            "folders": found.folders,
            "files_read": found.files_read,
        }),
    );
    let mut out = format!(
        "{:<3} {:<16} {:<12} {:>8} {:>8}\n",
        "bit", "light", "kind", "useful", "culled"
    );
    for light in &found.lights {
        out += &format!(
            "{:<3} {:<16} {:<12} {:>8} {:>8}\n",
            light.bit, light.name, light.kind, light.useful, light.culled
        );
    }
    let verb = if options.pipeline.writes_nothing() {
        "would change"
    } else {
        "wrote"
    };
    out += &format!(
        "{verb} 0 of {} chunk files in place (as the last bake left them); {:.2} s in all\n",
        found.chunk_files,
        started.elapsed().as_secs_f64()
    );
    print!("{out}");
}

/// Keeps the record of a finished bake in place, or says why not when a
/// file changed while it ran.
pub fn keep_record(cache: &Cache, key: &Key, baked: &Baked, reporter: &Reporter) {
    match world_record::record(cache, key, baked) {
        Ok(()) | Err(NotRecorded::Problems) => {}
        Err(NotRecorded::Changed(path)) => reporter.say(
            "cache_not_recorded",
            &format!(
                "cache: {} changed while the bake ran: the next bake loads the world again",
                path.display()
            ),
            serde_json::json!({ "changed": path.display().to_string() }),
        ),
    }
}

/// `shadowcull cache DIR stats|clear`.
#[derive(Debug, clap::Args)]
pub struct CacheCommand {
    /// The cache folder (a bake's is .shadowcull-cache beside its settings
    /// file).
    dir: PathBuf,
    #[arg(value_enum)]
    action: CacheAction,
    /// Print stats as one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum CacheAction {
    /// Entries and bytes per kind, and temporaries left by killed bakes.
    Stats,
    /// Remove every entry and temporary (the folder stays).
    Clear,
}

pub fn run(args: CacheCommand) -> Result<()> {
    match args.action {
        CacheAction::Stats => {
            let stats = cache::folder_stats(&args.dir)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&stats)?);
                return Ok(());
            }
            println!("{}", args.dir.display());
            for (kind, entries, bytes) in &stats.kinds {
                println!(
                    "  {kind:<9} {entries:>8} entries {:>10}",
                    human_bytes(*bytes)
                );
            }
            println!(
                "  {:<9} {:>8} entries {:>10}; {} left by killed bakes",
                "all",
                stats.entries,
                human_bytes(stats.bytes),
                count(stats.temporaries as usize, "temporary", "temporaries")
            );
            Ok(())
        }
        CacheAction::Clear => {
            let removed = cache::clear_folder(&args.dir)?;
            println!(
                "removed {} from {}",
                count(removed, "file", "files"),
                args.dir.display()
            );
            Ok(())
        }
    }
}
