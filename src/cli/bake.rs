//! `shadowcull bake`: load, refuse broken input, plan, bake, write the
//! chunks and the report, print the per-light table; or, with `--shard`,
//! one shard of a distributed bake (`shard`). The options, the loading and
//! the writing it shares with `merge` and `shard` live in `bake_shared`,
//! the pipeline flags in `pipeline`, the estimate in `plan`, progress in
//! `progress`.

use super::bake_shared::{load_scene_told, warn_locked_chunks, write_results};
use super::bake_shared::{BakeOptions, OutputArgs, Results};
use super::messages::StderrForm;
use super::progress::Reporter;
use super::{load_settings_with, SettingsArgs, UnknownElements};
use anyhow::{Context, Result};
use shadowcull::bake::cached::BakeCache;
use shadowcull::bake::world_record::{self, Baked, Checked};
use shadowcull::bake::{self, BakeConfig};
use shadowcull::cache::KnownFiles;
use shadowcull::cache::{Cache, Key};
use shadowcull::formats::bake_settings::BakeSettings;
use shadowcull::scene::SceneKeys;
use std::path::Path;
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

impl BakeArgs {
    pub fn stderr_form(&self) -> StderrForm {
        self.options.progress.stderr_form()
    }
}

pub fn run(args: BakeArgs) -> Result<()> {
    let unknown = UnknownElements::for_bake(args.options.pipeline.keep_going);
    let settings = load_settings_with(&args.settings, unknown)?;
    let config = args.options.config(&settings, &args.settings.settings)?;
    if args.shard.is_set() {
        return args.options.in_pool(|| {
            let file = &args.settings.settings;
            super::shard::run(&args.shard, &args.options, file, &settings, &config)
        });
    }
    args.options
        .in_pool(|| bake_with(&args, &config, &settings))
}

fn bake_with(args: &BakeArgs, config: &BakeConfig, settings: &BakeSettings) -> Result<()> {
    let file = &args.settings.settings;
    let started = Instant::now();
    let cache = args.options.cache.open(file)?;
    let reporter = Reporter::new(&args.options.progress);
    let record_key = cache
        .as_ref()
        .filter(|_| {
            args.output.out.is_none() && args.output.report.is_none() && args.output.html.is_none()
        })
        .map(|cache| world_record_key(cache, file, settings, config));
    let mut known = KnownFiles::default();
    if let (Some(cache), Some(key)) = (&cache, &record_key) {
        match world_record::check(cache, key) {
            Checked::UpToDate(found) => {
                super::cache::say_up_to_date(&found, &args.options, started, &reporter);
                super::cache::finish(cache, &reporter);
                return Ok(());
            }
            Checked::Changed(recorded) => known = recorded,
            Checked::NoRecord => {}
        }
    }
    let scene = load_scene_told(settings, &args.options, &reporter, cache.as_ref(), &known)?;
    warn_locked_chunks(&scene, &args.output, &args.options);
    let world = bake::checked_world(&scene, config, &reporter)
        .with_context(|| file.display().to_string())?;
    let result = match &cache {
        None => {
            let plan = super::plan::make_plan(&scene, &world, config, started, &reporter, None)?;
            super::plan::say_plan(&plan, &reporter);
            super::plan::check_memory(&plan, args.options.pipeline.max_memory)?;
            // The plan's calibration tiles are not traced twice.
            bake::bake_from(&world, config, &reporter, &plan)
        }
        Some(cache) => {
            let bake_cache = BakeCache::new(cache, &world, SceneKeys::of(&scene), None);
            let plan = super::plan::make_plan(
                &scene,
                &world,
                config,
                started,
                &reporter,
                Some(&bake_cache),
            )?;
            super::plan::say_plan(&plan, &reporter);
            super::plan::check_memory(&plan, args.options.pipeline.max_memory)?;
            // The plan's calibration cells are stored: the bake reuses them.
            bake::bake_cached(&world, config, &reporter, &bake_cache)
        }
    };
    let result = result.with_context(|| file.display().to_string())?;
    // The output needs the scene and the masks only: the trees go first.
    drop(world);
    let results = Results {
        scene: &scene,
        res_paths: &settings.res_paths,
        config,
        settings_file: file,
        started,
        cache: cache.as_ref(),
    };
    let wrote = write_results(&args.output, &args.options, &results, result, &reporter)?;
    if let (Some(cache), Some(key)) = (&cache, &record_key) {
        // A dry run that would change files leaves a world not yet baked.
        if !(wrote.changed && args.options.pipeline.writes_nothing()) {
            let baked = Baked {
                scene: &scene,
                chunks: wrote
                    .outputs
                    .iter()
                    .filter_map(|o| Some((o.target.as_path(), o.key?)))
                    .collect(),
                res_roots: &settings.res_paths,
                lights: wrote.lights,
            };
            super::cache::keep_record(cache, key, &baked, &reporter);
        }
    }
    if let Some(cache) = &cache {
        super::cache::finish(cache, &reporter);
    }
    // Freeing a large world's millions of allocations takes a second the
    // user would wait for at exit; nothing reads the scene any more.
    std::thread::spawn(move || drop(scene));
    Ok(())
}

/// The key of the world's record: everything besides the files that
/// decides what the bake writes (the settings after every override, the
/// options, where the settings file is).
fn world_record_key(
    cache: &Cache,
    file: &Path,
    settings: &BakeSettings,
    config: &BakeConfig,
) -> Key {
    let place = std::path::absolute(file).unwrap_or_else(|_| file.to_path_buf());
    let facts = [
        format!("{}", place.display()),
        format!("{settings:?}"),
        format!("{config:?}"),
    ];
    world_record::record_key(cache, &facts.each_ref().map(String::as_str))
}
