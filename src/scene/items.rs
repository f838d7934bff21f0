//! Every kind of chunk item and what the bake does with it
//! (docs/contract.md §2), so a world never loses something without a word:
//! [`ITEM_KINDS`] is the one table of the kinds shadowcull knows and why
//! each may be left out; a kind not in it is unknown and said to be. The
//! speedtrees without a proxy, the casters the bake cannot model, are
//! counted per `.spt`.

use super::{Instance, Scene};
use crate::formats::chunk::InstanceKind;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// What the bake does with an item kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Treatment {
    /// Casters the bake models (through a proxy for speedtrees).
    Modelled,
    /// Drawn, but into no shadow map: it receives shadows only.
    ReceivesOnly,
    /// Nothing to draw into a shadow map.
    NotGeometry,
    /// Part of the chunk's own description, not something placed in it.
    ChunkData,
    /// Not a kind shadowcull knows: whether it casts is not known.
    Unknown,
}

impl Treatment {
    /// Left out of the bake: every kind but the modelled ones.
    pub fn left_out(self) -> bool {
        self != Treatment::Modelled
    }

    /// In words, for the lines of `inspect`, `plan` and the bake.
    pub fn label(self) -> &'static str {
        match self {
            Treatment::Modelled => "modelled",
            Treatment::ReceivesOnly => "left out: receives shadows only",
            Treatment::NotGeometry => "left out: not geometry",
            Treatment::ChunkData => "chunk data",
            Treatment::Unknown => "left out: unknown kind",
        }
    }
}

/// Every chunk item kind shadowcull knows (a chunk root's child tag),
/// what the bake does with it and why.
pub const ITEM_KINDS: &[(&str, Treatment, &str)] = &[
    ("model", Treatment::Modelled, "placed models: casters"),
    ("shell", Treatment::Modelled, "indoor shells: casters"),
    (
        "speedtree",
        Treatment::Modelled,
        "SpeedTree placements: casters through their proxies (<speedtrees> in the settings file)",
    ),
    (
        "terrain",
        Treatment::Modelled,
        "the chunk's terrain block: a caster",
    ),
    (
        "vlo",
        Treatment::ReceivesOnly,
        "water and other very large objects: drawn into no shadow map",
    ),
    (
        "water",
        Treatment::ReceivesOnly,
        "water: drawn into no shadow map",
    ),
    (
        "flora",
        Treatment::ReceivesOnly,
        "ground cover: drawn without casting shadows",
    ),
    (
        "particles",
        Treatment::ReceivesOnly,
        "particle systems: effects drawn into no shadow map",
    ),
    (
        "entity",
        Treatment::NotGeometry,
        "game objects created at run time: their shadows are dynamic, not baked",
    ),
    (
        "UserDataObject",
        Treatment::NotGeometry,
        "game data (paths, triggers, markers)",
    ),
    ("audio", Treatment::NotGeometry, "sound emitters"),
    ("sound", Treatment::NotGeometry, "sound emitters"),
    (
        "omniLight",
        Treatment::NotGeometry,
        "a light: it shines, it draws nothing",
    ),
    (
        "spotLight",
        Treatment::NotGeometry,
        "a light: it shines, it draws nothing",
    ),
    (
        "directionalLight",
        Treatment::NotGeometry,
        "a light: it shines, it draws nothing",
    ),
    (
        "ambientLight",
        Treatment::NotGeometry,
        "a light: it shines, it draws nothing",
    ),
    (
        "pulseLight",
        Treatment::NotGeometry,
        "a light: it shines, it draws nothing",
    ),
    (
        "flare",
        Treatment::NotGeometry,
        "a lens flare: a screen effect",
    ),
    (
        "worldNavmesh",
        Treatment::NotGeometry,
        "navigation data for AI: not drawn",
    ),
    (
        "navmesh",
        Treatment::NotGeometry,
        "navigation data for AI: not drawn",
    ),
    (
        "station",
        Treatment::NotGeometry,
        "a waypoint graph node: not drawn",
    ),
    (
        "transform",
        Treatment::ChunkData,
        "the indoor chunk's own transform",
    ),
    ("boundingBox", Treatment::ChunkData, "the chunk's bounds"),
    (
        "boundary",
        Treatment::ChunkData,
        "the chunk's boundaries and portals",
    ),
    (
        "waypointGenerationTime",
        Treatment::ChunkData,
        "editor bookkeeping",
    ),
    ("metaData", Treatment::ChunkData, "editor bookkeeping"),
];

/// Why an unknown kind is listed.
pub const UNKNOWN_KIND: &str =
    "a kind shadowcull does not know, not read: if it draws into shadow maps, those shadows are missing";

/// What the bake does with items tagged `kind`, and why.
pub fn treatment(kind: &str) -> (Treatment, &'static str) {
    ITEM_KINDS
        .iter()
        .find(|(tag, _, _)| *tag == kind)
        .map_or((Treatment::Unknown, UNKNOWN_KIND), |&(_, t, why)| (t, why))
}

/// How many items of one kind the space's chunks hold.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ItemCount {
    /// The tag.
    pub kind: String,
    pub count: usize,
    /// How many chunks hold at least one.
    pub chunks: usize,
}

/// An item kind with what the bake does with it (`inspect --json`'s
/// `items`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ItemEntry {
    pub kind: String,
    pub count: usize,
    pub chunks: usize,
    pub treatment: Treatment,
    pub why: &'static str,
}

/// The speedtree placements of one `.spt` that have no proxy: kept for
/// every light, never occluding.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct UnproxiedTrees {
    pub spt: String,
    pub placements: usize,
    pub chunks: usize,
}

impl Scene {
    /// Every item kind of the space's chunks with its treatment, by kind.
    pub fn item_entries(&self) -> Vec<ItemEntry> {
        self.items
            .iter()
            .map(|item| {
                let (treatment, why) = treatment(&item.kind);
                ItemEntry {
                    kind: item.kind.clone(),
                    count: item.count,
                    chunks: item.chunks,
                    treatment,
                    why,
                }
            })
            .collect()
    }

    /// The speedtrees without a proxy, per `.spt` (sorted by name).
    pub fn unproxied_trees(&self) -> Vec<UnproxiedTrees> {
        let mut by_spt: BTreeMap<&str, (usize, BTreeSet<usize>)> = BTreeMap::new();
        // Found in parallel: a large world places millions of instances.
        let trees: Vec<&Instance> = self
            .instances
            .par_iter()
            .filter(|i| i.is_unmodelled())
            .collect();
        for tree in trees {
            let entry = by_spt.entry(spt_of(tree)).or_default();
            entry.0 += 1;
            entry.1.insert(tree.chunk);
        }
        by_spt
            .into_iter()
            .map(|(spt, (placements, chunks))| UnproxiedTrees {
                spt: spt.to_string(),
                placements,
                chunks: chunks.len(),
            })
            .collect()
    }

    /// How many casters the bake cannot model: speedtree placements
    /// without a proxy.
    pub fn unmodelled_casters(&self) -> usize {
        self.instances
            .par_iter()
            .filter(|i| i.is_unmodelled())
            .count()
    }

    /// The item kinds the bake leaves out (chunk data is not an item) and
    /// the unmodelled casters, one line each, for `plan`, the bake's
    /// summary and `inspect`.
    pub fn left_out_lines(&self) -> Vec<String> {
        let mut lines: Vec<String> = self
            .item_entries()
            .into_iter()
            .filter(|e| e.treatment.left_out() && e.treatment != Treatment::ChunkData)
            .map(|e| {
                format!(
                    "{}: {} <{}> in {}: {}",
                    e.treatment.label(),
                    e.count,
                    e.kind,
                    plural(e.chunks, "chunk", "chunks"),
                    e.why
                )
            })
            .collect();
        let unproxied = self.unproxied_trees();
        if !unproxied.is_empty() {
            lines.push(format!(
                "not modelled: {} <speedtree> placements without a proxy (none of <speedtrees> matches their .spt, docs/contract.md §3): kept for every light, they occlude nothing",
                self.unmodelled_casters()
            ));
            for trees in unproxied {
                lines.push(format!(
                    "  {}: {} in {}",
                    trees.spt,
                    plural(trees.placements, "placement", "placements"),
                    plural(trees.chunks, "chunk", "chunks")
                ));
            }
        }
        lines
    }

    /// Item kinds shadowcull does not know, which may cast.
    pub fn unknown_item_kinds(&self) -> usize {
        self.items
            .iter()
            .filter(|i| treatment(&i.kind).0 == Treatment::Unknown)
            .count()
    }
}

/// A speedtree instance's `.spt` (its one resource name).
pub fn spt_of(tree: &Instance) -> &str {
    debug_assert_eq!(tree.kind, InstanceKind::SpeedTree);
    tree.resources.first().map_or("", |s| s.trim())
}

/// "1 chunk", "2 chunks".
pub fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_names_each_kind_once_and_every_reason() {
        let mut seen = BTreeSet::new();
        for (kind, _, why) in ITEM_KINDS {
            assert!(seen.insert(*kind), "{kind} twice");
            assert!(!why.is_empty(), "{kind}");
        }
        for kind in ["model", "shell", "speedtree", "terrain"] {
            assert_eq!(treatment(kind).0, Treatment::Modelled, "{kind}");
        }
        assert_eq!(treatment("vlo").0, Treatment::ReceivesOnly);
        assert_eq!(treatment("UserDataObject").0, Treatment::NotGeometry);
        assert_eq!(
            treatment("ControlPoint"),
            (Treatment::Unknown, UNKNOWN_KIND)
        );
        assert!(!Treatment::Modelled.left_out() && Treatment::Unknown.left_out());
    }
}
