//! What a world holds, without baking (`shadowcull inspect`): counts for a
//! person or a script, every chunk item kind with what the bake does with
//! it, every resource that could not be loaded, and every caster the bake
//! cannot model (docs/contract.md §8).

use crate::formats::bake_settings::UnmodelledCasters;
use crate::scene::items::plural;
use crate::scene::{ItemEntry, Problem, Scene, Stats, Treatment, UnproxiedTrees};
use serde::Serialize;
use std::fmt::Write as _;

#[derive(Debug, Clone, Serialize)]
pub struct Inspection {
    pub space: String,
    #[serde(flatten)]
    pub stats: Stats,
    /// Every chunk item kind, with its count and treatment.
    pub items: Vec<ItemEntry>,
    /// The speedtrees without a proxy, per `.spt`.
    pub unproxied_speedtrees: Vec<UnproxiedTrees>,
    /// `<unmodelledCasters>`: whether those fail a strict bake.
    pub unmodelled_casters: &'static str,
    /// What fails a strict bake: missing or broken resources, and with
    /// `<unmodelledCasters> fail` each `.spt` without a proxy.
    pub problems: Vec<ProblemEntry>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ProblemEntry {
    pub what: String,
    pub why: String,
}

impl From<&Problem> for ProblemEntry {
    fn from(problem: &Problem) -> Self {
        ProblemEntry {
            what: problem.what.clone(),
            why: problem.why.clone(),
        }
    }
}

/// Why a `.spt` without a proxy fails a strict bake, and how to go on.
pub const UNPROXIED_FAILS: &str = "no proxy in <speedtrees> of the settings file matches this .spt, so the bake cannot model these trees (kept for every light, they would occlude nothing); declare a proxy (docs/contract.md §3), or accept that with <unmodelledCasters> keep </unmodelledCasters> or --keep-going";

pub fn inspect(scene: &Scene, unmodelled: UnmodelledCasters) -> Inspection {
    let unproxied = scene.unproxied_trees();
    let mut problems: Vec<ProblemEntry> = scene.problems.iter().map(ProblemEntry::from).collect();
    if unmodelled == UnmodelledCasters::Fail {
        problems.extend(unproxied.iter().map(|trees| ProblemEntry {
            what: trees.spt.clone(),
            why: format!(
                "{} in {}: {UNPROXIED_FAILS}",
                plural(
                    trees.placements,
                    "<speedtree> placement",
                    "<speedtree> placements"
                ),
                plural(trees.chunks, "chunk", "chunks")
            ),
        }));
    }
    Inspection {
        space: scene.space_dir.display().to_string(),
        stats: scene.stats(),
        items: scene.item_entries(),
        unproxied_speedtrees: unproxied,
        unmodelled_casters: unmodelled.name(),
        problems,
    }
}

impl Inspection {
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// The readable summary.
    pub fn to_text(&self) -> String {
        let s = &self.stats;
        let mut out = String::new();
        let _ = writeln!(out, "space {}", self.space);
        let rows: [(&str, usize); 12] = [
            ("chunks", s.chunks),
            ("instances", s.instances),
            (
                "  receiver-only (castsShadow false)",
                s.receiver_only_instances,
            ),
            ("distinct models", s.models),
            ("primitive groups", s.groups),
            ("  alpha-tested", s.alpha_tested_groups),
            ("  double-sided", s.double_sided_groups),
            ("triangles", s.triangles),
            ("terrain blocks", s.terrain_blocks),
            ("speedtrees", s.speedtrees),
            ("  without a proxy", s.speedtrees_without_proxy),
            ("distinct speedtree proxies", s.speedtree_proxies),
        ];
        for (label, value) in rows {
            let _ = writeln!(out, "  {label:<36} {value:>10}");
        }
        self.items_text(&mut out);
        self.conclusion(&mut out);
        out
    }

    /// Every item kind and what the bake does with it; the speedtrees
    /// without a proxy per `.spt`.
    fn items_text(&self, out: &mut String) {
        if !self.items.is_empty() {
            let _ = writeln!(out, "chunk items (docs/contract.md §2):");
        }
        for item in &self.items {
            let _ = writeln!(
                out,
                "  {:<24} {:>8} in {:>12}  {}: {}",
                format!("<{}>", item.kind),
                item.count,
                plural(item.chunks, "chunk", "chunks"),
                item.treatment.label(),
                item.why
            );
        }
        if !self.unproxied_speedtrees.is_empty() {
            let _ = writeln!(
                out,
                "speedtrees without a proxy (not modelled: kept for every light, they occlude nothing):"
            );
            for trees in &self.unproxied_speedtrees {
                let _ = writeln!(
                    out,
                    "  {}: {} in {}",
                    trees.spt,
                    plural(trees.placements, "placement", "placements"),
                    plural(trees.chunks, "chunk", "chunks")
                );
            }
        }
    }

    /// The last lines: the problems, or why there is none; "no problems"
    /// only when nothing that may cast is left out.
    fn conclusion(&self, out: &mut String) {
        let unknown: Vec<&str> = self
            .items
            .iter()
            .filter(|i| i.treatment == Treatment::Unknown)
            .map(|i| i.kind.as_str())
            .collect();
        if !self.problems.is_empty() {
            let _ = writeln!(
                out,
                "{} {}; a bake fails unless --keep-going, which leaves out what they name:",
                self.problems.len(),
                if self.problems.len() == 1 {
                    "problem"
                } else {
                    "problems"
                }
            );
            for problem in &self.problems {
                let _ = writeln!(out, "  {}: {}", problem.what, problem.why);
            }
        } else if self.stats.speedtrees_without_proxy > 0 {
            let _ = writeln!(
                out,
                "no problems that fail a bake, but {} not modelled (kept for every light as <unmodelledCasters> keep says)",
                plural(self.stats.speedtrees_without_proxy, "speedtree placement is", "speedtree placements are")
            );
        } else if !unknown.is_empty() {
            let _ = writeln!(
                out,
                "no problems that fail a bake, but {} unknown to shadowcull (<{}>): if one draws into shadow maps, its shadows are missing",
                plural(unknown.len(), "item kind is", "item kinds are"),
                unknown.join(">, <")
            );
        } else {
            let _ = writeln!(
                out,
                "no problems: every resource loaded and every chunk item that casts is modelled"
            );
        }
    }
}
