//! `shadowcull bake --shard I/N --partial FILE` (or `--shard auto` inside
//! a Slurm, Kubernetes or AWS Batch array job): one shard of a distributed
//! bake, written as a partial result for `merge`.

use super::bake_shared::{load_scene_told, BakeOptions};
use super::messages;
use super::progress::Reporter;
use anyhow::{Context, Result};
use shadowcull::bake::cached::BakeCache;
use shadowcull::bake::shard::{self, Plan, ShardIndex};
use shadowcull::bake::{self, BakeConfig};
use shadowcull::files::{self, ResPaths};
use shadowcull::formats::bake_settings::BakeSettings;
use shadowcull::formats::partial::Partial;
use shadowcull::scene::SceneKeys;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct ShardArgs {
    /// Bake only shard I of N (I from 0) and write a partial result for
    /// `merge`; `auto`: the index and count from the array job's variables
    /// (Slurm, Kubernetes Indexed Job with --shards, AWS Batch).
    #[arg(long, value_name = "I/N|auto", requires = "partial",
          conflicts_with_all = ["out", "dry_run", "report", "html", "refine"])]
    shard: Option<String>,
    /// The number of shards when the scheduler does not say it
    /// (Kubernetes: the Job's completions).
    #[arg(long, value_name = "N", requires = "shard",
          value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    shards: Option<u32>,
    /// Where --shard writes its partial result; `{index}` and `{count}` in
    /// the name become the shard's index and the shard count.
    #[arg(long, value_name = "FILE", requires = "shard")]
    partial: Option<PathBuf>,
}

impl ShardArgs {
    pub fn is_set(&self) -> bool {
        self.shard.is_some()
    }

    /// The shard to bake, and where the index came from.
    fn shard(&self) -> Result<(ShardIndex, String)> {
        let spec = self.shard.as_deref().unwrap_or_default();
        if spec == "auto" {
            return Ok(shard::shard_from_env(
                &|name| std::env::var(name).ok(),
                self.shards,
            )?);
        }
        let shard = ShardIndex::parse(spec)?;
        if let Some(n) = self.shards.filter(|&n| n != shard.count) {
            anyhow::bail!("--shard {spec} but --shards {n}: drop --shards or make them agree");
        }
        Ok((shard, format!("shard {shard} from --shard")))
    }
}

/// `FILE` with `{index}` and `{count}` replaced.
fn partial_path(template: &Path, shard: ShardIndex) -> PathBuf {
    PathBuf::from(
        template
            .to_string_lossy()
            .replace("{index}", &shard.index.to_string())
            .replace("{count}", &shard.count.to_string()),
    )
}

pub fn run(
    args: &ShardArgs,
    options: &BakeOptions,
    settings_file: &Path,
    settings: &BakeSettings,
    config: &BakeConfig,
) -> Result<()> {
    let (shard, said) = args.shard()?;
    messages::say(
        "shard",
        &said,
        serde_json::json!({ "index": shard.index, "count": shard.count }),
    );
    let path = partial_path(args.partial.as_deref().unwrap_or(Path::new("")), shard);
    let started = Instant::now();
    let cache = options.cache.open(settings_file)?;
    let reporter = Reporter::new(&options.progress);
    let scene = load_scene_told(
        settings,
        options,
        &reporter,
        cache.as_ref(),
        &shadowcull::cache::KnownFiles::default(),
    )?;
    let world = bake::checked_world(&scene, config, &reporter)?;
    let plan = Plan::new(&world, config, shard.count)?;
    let mean = plan.costs.iter().sum::<u64>() as f64 / shard.count as f64;
    let own = plan.units[shard.index as usize].len();
    let mrays = |cost: u64| cost as f64 / shard::COST_SCALE / 1e6;
    let said = format!(
        "plan of {} shards: this one bakes {own} unit(s), estimated cost {:.1} M ray-equivalents \
         ({:.2}× the mean; shards from {:.1} to {:.1}, mean {:.1})",
        shard.count,
        mrays(plan.costs[shard.index as usize]),
        plan.costs[shard.index as usize] as f64 / mean.max(1.0),
        mrays(plan.costs.iter().copied().min().unwrap_or(0)),
        mrays(plan.costs.iter().copied().max().unwrap_or(0)),
        mean / shard::COST_SCALE / 1e6,
    );
    messages::say("shard_plan", &said, serde_json::json!({ "units": own }));
    let cpu_before = cpu_seconds();
    let bake_cache = cache
        .as_ref()
        .map(|cache| BakeCache::new(cache, &world, SceneKeys::of(&scene), None));
    let (units, cached) = shard::bake_shard_cached(
        &world,
        config,
        &plan,
        shard.index,
        &reporter,
        bake_cache.as_ref(),
    )?;
    if let Some(cache) = &cache {
        reporter.say(
            "cache_cells",
            &format!(
                "cache: {} cells or parts of cells reused, {} traced{}",
                cached.reused,
                cached.computed,
                match cached.damaged {
                    0 => String::new(),
                    n => format!(" ({n} damaged)"),
                }
            ),
            serde_json::json!({ "cells": cached }),
        );
        super::cache::finish(cache, &reporter);
    }
    let cpu = cpu_seconds() - cpu_before;
    let rays: u64 = units.iter().map(|u| u.rays).sum();
    let trace: f64 = units.iter().map(|u| u.seconds).sum();
    let partial = Partial {
        fingerprint: shard::fingerprint(&scene, config, &ResPaths::new(settings.res_paths.clone())),
        shard: shard.index,
        shards: shard.count,
        plan: plan.digest,
        casters: world.casters.len() as u64,
        units,
    };
    files::write_partial(&path, &partial).with_context(|| format!("shard {shard}"))?;
    println!(
        "shard {shard}: {own} unit(s), {rays} rays traced in {trace:.2} s ({cpu:.1} CPU s); wrote {}; {:.2} s in all",
        path.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// User + system CPU seconds of this process so far (0 where unknown): a
/// shard's work measured apart from what else the machine runs.
fn cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage fills the struct it is given; RUSAGE_SELF is valid.
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0 {
            // SAFETY: initialised by the successful call above.
            let usage = unsafe { usage.assume_init() };
            let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
            return seconds(usage.ru_utime) + seconds(usage.ru_stime);
        }
    }
    0.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(shard: &str, shards: Option<u32>) -> ShardArgs {
        ShardArgs {
            shard: Some(shard.to_string()),
            shards,
            partial: None,
        }
    }

    #[test]
    fn the_partial_path_names_the_shard_and_the_count() {
        let shard = ShardIndex { index: 3, count: 8 };
        assert_eq!(
            partial_path(Path::new("parts/{index}-of-{count}.partial"), shard),
            PathBuf::from("parts/3-of-8.partial")
        );
        assert_eq!(
            partial_path(Path::new("one.partial"), shard),
            PathBuf::from("one.partial")
        );
    }

    #[test]
    fn shards_must_agree_with_an_explicit_shard() {
        let (shard, said) = args("1/4", Some(4)).shard().expect("agreeing --shards");
        assert_eq!(shard, ShardIndex { index: 1, count: 4 });
        assert!(said.contains("--shard"), "{said}");
        let err = args("1/4", Some(3))
            .shard()
            .expect_err("disagreeing --shards");
        assert!(err.to_string().contains("--shards 3"), "{err}");
        assert!(args("4/4", None).shard().is_err());
    }
}
