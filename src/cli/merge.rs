//! `shadowcull merge SETTINGS PARTIAL...`: checks the partial results of a
//! distributed bake against this machine's inputs, ORs them (no grid ray
//! is traced here: its grid phase is `merging`), refines if asked (those
//! rays are traced here), and writes the chunks and report exactly as
//! `bake` does.

use super::bake_shared::{
    load_scene_told, warn_locked_chunks, write_results, BakeOptions, OutputArgs, Results,
};
use super::messages::{self, StderrForm};
use super::progress::{GridAnswers, Reporter};
use super::{load_settings_with, SettingsArgs, UnknownElements};
use anyhow::Result;
use shadowcull::bake::cached::BakeCache;
use shadowcull::bake::{self, shard};
use shadowcull::files::{self, ResPaths};
use shadowcull::formats::{self, Section};
use shadowcull::scene::SceneKeys;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// The partial results of every shard (`bake --shard I/N --partial
    /// FILE`); a shard given twice must agree with itself.
    #[arg(required = true, value_name = "PARTIAL")]
    partials: Vec<PathBuf>,
    #[command(flatten)]
    output: OutputArgs,
    #[command(flatten)]
    options: BakeOptions,
}

impl MergeArgs {
    pub fn stderr_form(&self) -> StderrForm {
        self.options.progress.stderr_form()
    }
}

pub fn run(args: MergeArgs) -> Result<()> {
    let unknown = UnknownElements::for_bake(args.options.pipeline.keep_going);
    let settings = load_settings_with(&args.settings, unknown)?;
    let config = args.options.config(&settings, &args.settings.settings)?;
    args.options.in_pool(|| {
        let started = Instant::now();
        let mut partials = Vec::new();
        let mut damaged = Vec::new();
        for path in &args.partials {
            match files::read_partial(path) {
                Ok(p) => partials.push((path.clone(), p)),
                Err(err) => damaged.push(err.to_string()),
            }
        }
        if !damaged.is_empty() {
            return Err(shard::ShardError::Refused(damaged).into());
        }
        let cache = args.options.cache.open(&args.settings.settings)?;
        let reporter = Reporter::with_grid(&args.options.progress, GridAnswers::Merged);
        let scene = load_scene_told(
            &settings,
            &args.options,
            &reporter,
            cache.as_ref(),
            &shadowcull::cache::KnownFiles::default(),
        )?;
        warn_locked_chunks(&scene, &args.output, &args.options);
        let world = bake::checked_world(&scene, &config, &reporter)?;
        let own = shard::fingerprint(&scene, &config, &ResPaths::new(settings.res_paths.clone()));
        let command = format!("shadowcull bake {}", args.settings.settings.display());
        let locate = setting_locator(&args.settings.settings);
        let (merged, plan) = shard::merge(&world, &config, &own, &partials, &command, &locate)?;
        let units = partials.iter().flat_map(|(_, p)| &p.units);
        let (rays, seconds) = units.fold((0u64, 0f64), |(r, s), u| (r + u.rays, s + u.seconds));
        let refining = if args.options.verdict.refine {
            "; --refine: refinement rays are traced here, after each light's merge"
        } else {
            ""
        };
        messages::say(
            "merge",
            &format!(
                "merge: OR-ing the grid answers of {} partial(s) of {} shards ({rays} rays traced \
                 in {seconds:.1} s, summed over the shards); no grid ray is traced here{refining}",
                partials.len(),
                plan.shards
            ),
            serde_json::json!({
                "partials": partials.len(),
                "shards": plan.shards,
                "shard_rays": rays,
                "shard_seconds": seconds,
                "refine": args.options.verdict.refine,
            }),
        );
        // With a cache, refinement is reused or refined per chunk and
        // stored; the grid answers are the shards'.
        let bake_cache = cache
            .as_ref()
            .map(|cache| BakeCache::new(cache, &world, SceneKeys::of(&scene), None));
        let result = bake::bake_with(&world, &config, &reporter, &merged, bake_cache.as_ref())?;
        drop((bake_cache, merged, world));
        let results = Results {
            scene: &scene,
            res_paths: &settings.res_paths,
            config: &config,
            settings_file: &args.settings.settings,
            started,
            cache: cache.as_ref(),
        };
        write_results(&args.output, &args.options, &results, result, &reporter)?;
        if let Some(cache) = &cache {
            super::cache::finish(cache, &reporter);
        }
        Ok(())
    })
}

/// Where the settings file at `path` sets `key` (an element path such as
/// `lights/light[0]/texelSize`), as `file:line`; `None` for flags and
/// elements the file does not hold.
fn setting_locator(path: &Path) -> impl Fn(&str) -> Option<String> + '_ {
    let bytes = files::read_file(path).ok();
    let root = bytes
        .as_deref()
        .and_then(|b| formats::parse_data_section(b).ok());
    move |key| {
        let (bytes, root) = (bytes.as_deref()?, root.as_ref()?);
        let element = key.split('/').try_fold(root, |section: &Section, step| {
            let (name, nth) = match step.split_once('[') {
                Some((name, rest)) => (name, rest.trim_end_matches(']').parse().ok()?),
                None => (step, 0),
            };
            section.children_named(name).nth(nth)
        })?;
        let position = formats::text_position(bytes, element.location().offset()?)?;
        Some(format!("{}:{}", path.display(), position.line))
    }
}
