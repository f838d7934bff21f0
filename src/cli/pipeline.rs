//! The bake's pipeline flags: fail on broken input unless
//! `--keep-going`, a subset of lights, a memory ceiling, CI checks. Kept
//! apart from the bake's own settings so each stays small.

use super::messages::{self, ProblemOutcome};
use anyhow::{bail, Result};
use shadowcull::bake::BakeConfig;
use shadowcull::formats::bake_settings::UnmodelledCasters;
use shadowcull::scene::Scene;
use std::path::Path;

#[derive(Debug, Clone, clap::Args)]
pub struct PipelineArgs {
    /// Bake what loaded even when some input is broken (missing or
    /// damaged files, bad or stray transforms): those parts are left out
    /// and listed in the report; an unknown element of the settings file
    /// is only a warning. Without it any of these fails the bake (exit 1)
    /// and nothing is written.
    #[arg(long)]
    pub keep_going: bool,
    /// Bake only this light (repeatable); every other bit of the existing
    /// masks is kept.
    #[arg(long = "light", value_name = "NAME")]
    pub lights: Vec<String>,
    /// Refuse (exit 1, before tracing) when the plan's peak memory estimate
    /// is above SIZE (e.g. 512M, 8G, 1.5GiB, or bytes).
    #[arg(long, value_name = "SIZE", value_parser = parse_size)]
    pub max_memory: Option<u64>,
    /// Bake and list the chunk files that would change, but write none.
    #[arg(long)]
    pub dry_run: bool,
    /// Like --dry-run, and exit 1 when any chunk file would change (a
    /// staleness check for CI).
    #[arg(long, conflicts_with = "dry_run")]
    pub check: bool,
}

impl PipelineArgs {
    /// No chunk file is written.
    pub fn writes_nothing(&self) -> bool {
        self.dry_run || self.check
    }
}

/// "1 problem", "2 problems".
pub fn count(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// Applies `--light`: the named lights only, each keeping its bit.
pub fn select_lights(config: BakeConfig, names: &[String], file: &Path) -> Result<BakeConfig> {
    if names.is_empty() {
        return Ok(config);
    }
    config
        .select_lights(names)
        .map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))
}

/// Broken input fails the bake before any work unless `--keep-going`:
/// every problem is listed. So do casters the bake cannot model (speedtrees
/// without a proxy, each `.spt` listed) unless the settings say
/// `<unmodelledCasters> keep` or `--keep-going`; kept, they are baked
/// kept for every light. With `--keep-going`, a world of which nothing
/// loaded (no caster at all) still fails: there is nothing to bake.
pub fn refuse_problems(
    scene: &Scene,
    keep_going: bool,
    unmodelled: UnmodelledCasters,
) -> Result<()> {
    if keep_going {
        for problem in &scene.problems {
            messages::problem(&problem.what, &problem.why, ProblemOutcome::LeftOut);
        }
        return refuse_nothing_loaded(scene);
    }
    let unproxied = if unmodelled == UnmodelledCasters::Fail {
        scene.unproxied_trees()
    } else {
        Vec::new()
    };
    if scene.problems.is_empty() && unproxied.is_empty() {
        return Ok(());
    }
    for problem in &scene.problems {
        messages::problem(&problem.what, &problem.why, ProblemOutcome::Fails);
    }
    for trees in &unproxied {
        let why = format!(
            "{} in {}: {}",
            count(
                trees.placements,
                "<speedtree> placement",
                "<speedtree> placements"
            ),
            count(trees.chunks, "chunk", "chunks"),
            shadowcull::inspect::UNPROXIED_FAILS
        );
        messages::problem(&trees.spt, &why, ProblemOutcome::Fails);
    }
    let mut what = Vec::new();
    if !scene.problems.is_empty() {
        what.push(count(scene.problems.len(), "problem", "problems") + " in the input");
    }
    if !unproxied.is_empty() {
        what.push(format!(
            "{} without a proxy",
            count(
                scene.unmodelled_casters(),
                "speedtree placement",
                "speedtree placements"
            )
        ));
    }
    let how = match (scene.problems.is_empty(), unproxied.is_empty()) {
        (false, true) => "Fix them, or bake what loaded with --keep-going",
        (true, false) => "Declare the trees' proxies in <speedtrees> of the settings file (docs/contract.md §3), or keep them for every light with <unmodelledCasters> keep </unmodelledCasters> or --keep-going",
        _ => "Fix the problems and declare the trees' proxies in <speedtrees> (docs/contract.md §3), or bake what loaded, the trees kept for every light, with --keep-going",
    };
    bail!(
        "{} (listed above); nothing was written. {how}",
        what.join(" and ")
    )
}

/// `--keep-going` over a world of which nothing loaded fails: no caster
/// (no model part, speedtree or terrain block) means nothing to bake.
fn refuse_nothing_loaded(scene: &Scene) -> Result<()> {
    let loaded = scene.terrain.len() + scene.instances.iter().filter(|i| i.is_complete()).count();
    if loaded == 0 {
        bail!(
            "nothing loaded: the {} hold no model, speedtree or terrain block that could be read ({}); nothing to bake, nothing was written",
            count(scene.chunks.len(), "chunk", "chunks"),
            count(scene.problems.len(), "problem", "problems")
        );
    }
    Ok(())
}

/// `512M`, `8G`, `1.5GiB`, `100kB`, `1048576`: decimal (k, M, G, T) and
/// binary (Ki, Mi, Gi, Ti) units, an optional `B`.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("`{text}` is not a size (e.g. 512M, 8G, 1.5GiB)"))?;
    let unit = unit.trim();
    let unit = unit.strip_suffix(['B', 'b']).unwrap_or(unit);
    let factor: f64 = match unit {
        "" => 1.0,
        "k" | "K" => 1e3,
        "M" | "m" => 1e6,
        "G" | "g" => 1e9,
        "T" | "t" => 1e12,
        "Ki" | "KI" | "ki" => 1024.0,
        "Mi" | "MI" | "mi" => 1024.0 * 1024.0,
        "Gi" | "GI" | "gi" => 1024.0 * 1024.0 * 1024.0,
        "Ti" | "TI" | "ti" => 1024.0f64.powi(4),
        _ => {
            return Err(format!(
                "unknown unit in `{text}`; use k, M, G, T or Ki, Mi, Gi, Ti"
            ))
        }
    };
    let bytes = value * factor;
    if bytes.is_finite() && bytes >= 1.0 {
        Ok(bytes as u64)
    } else {
        Err(format!("`{text}` is not a positive size"))
    }
}
