//! What a world holds, without baking (`shadowcull inspect`): counts for a
//! person or a script, and every resource that could not be loaded.

use crate::scene::{Problem, Scene, Stats};
use serde::Serialize;
use std::fmt::Write as _;

#[derive(Debug, Clone, Serialize)]
pub struct Inspection {
    pub space: String,
    #[serde(flatten)]
    pub stats: Stats,
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

pub fn inspect(scene: &Scene) -> Inspection {
    Inspection {
        space: scene.space_dir.display().to_string(),
        stats: scene.stats(),
        problems: scene.problems.iter().map(ProblemEntry::from).collect(),
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
        let rows: [(&str, usize); 9] = [
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
        ];
        for (label, value) in rows {
            let _ = writeln!(out, "  {label:<36} {value:>10}");
        }
        if self.problems.is_empty() {
            let _ = writeln!(out, "no problems: every resource loaded");
        } else {
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
        }
        out
    }
}
