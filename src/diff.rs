//! What changed between two bakes (`shadowcull diff`): per light and chunk,
//! the casters whose bit flipped and those that appeared or disappeared,
//! read from two bake reports or from two folders of baked chunk files.
//! A tool above the bake: it reads what a bake wrote and traces nothing.
//!
//! A caster is a chunk, a kind (`model`, `speedtree`, `terrain`), the
//! instance's index and, when the instance has group masks, the group's
//! position among them (render set, geometry, group flattened, as the
//! report's `groups` lists them); an instance without groups and a terrain
//! block are one caster with their mask.

use crate::bake::output::REPORT_VERSION;
use crate::error::{Error, Result};
use crate::files;
use crate::formats::shadow_write::{read_chunk_shadows, ChunkShadows, InstanceShadow};
use crate::formats::{parse_data_section, Section};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The kinds of caster, in the report's order (`model`, `speedtree`,
/// `terrain`: its `casters[]` are sorted by these names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CasterKind {
    Model,
    #[serde(rename = "speedtree")]
    SpeedTree,
    Terrain,
}

impl CasterKind {
    pub fn name(self) -> &'static str {
        match self {
            CasterKind::Model => "model",
            CasterKind::SpeedTree => "speedtree",
            CasterKind::Terrain => "terrain",
        }
    }

    fn from_name(name: &str) -> Option<CasterKind> {
        match name {
            "model" => Some(CasterKind::Model),
            "speedtree" => Some(CasterKind::SpeedTree),
            "terrain" => Some(CasterKind::Terrain),
            _ => None,
        }
    }
}

/// A caster within its chunk: kind, instance index (none for terrain) and
/// group position (none for a caster without group masks).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct CasterKey {
    pub kind: CasterKind,
    pub index: Option<usize>,
    pub group: Option<usize>,
}

/// One chunk's casters and their masks.
pub type ChunkMasks = BTreeMap<CasterKey, u32>;

/// What one side of a diff is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum InputKind {
    /// A bake's `--report` JSON.
    Report,
    /// A folder of baked `.chunk` files, walked recursively.
    ChunkFolder,
}

impl InputKind {
    /// What `path` is: a folder is one of chunk files, anything else is
    /// read as a report (and named if it cannot be).
    pub fn of(path: &Path) -> InputKind {
        if files::is_folder(path) {
            InputKind::ChunkFolder
        } else {
            InputKind::Report
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            InputKind::Report => "a bake report",
            InputKind::ChunkFolder => "a folder of chunk files",
        }
    }
}

/// How a caster differs between the two bakes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Change {
    /// In both, some bit set in one and clear in the other.
    Flipped,
    /// Only in the new bake.
    Appeared,
    /// Only in the old bake.
    Disappeared,
}

/// One caster that differs.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CasterChange {
    pub chunk: String,
    pub kind: CasterKind,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub index: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub group: Option<usize>,
    pub change: Change,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub old_mask: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub new_mask: Option<u32>,
    /// Bits set in the old mask and clear in the new: useful → culled.
    pub to_culled: Vec<u32>,
    /// Bits clear in the old mask and set in the new: culled → useful.
    pub to_useful: Vec<u32>,
}

impl CasterChange {
    /// The caster in words: `model 3 group 1`, `speedtree 0`, `terrain`.
    pub fn caster(&self) -> String {
        let mut out = self.kind.name().to_string();
        if let Some(index) = self.index {
            out += &format!(" {index}");
        }
        if let Some(group) = self.group {
            out += &format!(" group {group}");
        }
        out
    }

    /// The mask the caster has on the side it is on (new, else old).
    pub fn mask(&self) -> u32 {
        self.new_mask.or(self.old_mask).unwrap_or(0)
    }
}

/// A light's share of the differences.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct LightChanges {
    pub bit: u32,
    /// Its name in the old and the new report (`None` for chunk folders,
    /// and on the side whose report does not bake it).
    pub old_name: Option<String>,
    pub new_name: Option<String>,
    /// Casters whose bit went from set to clear.
    pub to_culled: usize,
    /// Casters whose bit went from clear to set.
    pub to_useful: usize,
    /// Appeared casters with the bit set.
    pub appeared_useful: usize,
    /// Disappeared casters that had the bit set.
    pub disappeared_useful: usize,
}

impl LightChanges {
    fn named(bit: u32, old_name: Option<String>, new_name: Option<String>) -> LightChanges {
        LightChanges {
            bit,
            old_name,
            new_name,
            to_culled: 0,
            to_useful: 0,
            appeared_useful: 0,
            disappeared_useful: 0,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.to_culled + self.to_useful + self.appeared_useful + self.disappeared_useful == 0
    }

    /// The light in words: `sun`, `sun (old: sunset)`, `bit 3`.
    pub fn name(&self) -> String {
        match (&self.old_name, &self.new_name) {
            (Some(old), Some(new)) if old != new => format!("{new} (old: {old})"),
            (_, Some(name)) | (Some(name), None) => name.clone(),
            (None, None) => format!("bit {}", self.bit),
        }
    }
}

/// Totals over every light and chunk.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Totals {
    /// Casters in both bakes with some bit flipped.
    pub flipped: usize,
    /// Bit flips useful → culled, over every light.
    pub to_culled: usize,
    /// Bit flips culled → useful, over every light.
    pub to_useful: usize,
    pub appeared: usize,
    pub disappeared: usize,
    /// Chunks with any difference.
    pub chunks: usize,
}

/// How the chunk files of two folders compare (folders only).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ChunkFiles {
    /// Files in both folders (matched by relative path).
    pub matched: usize,
    /// Of those, files with identical bytes (not parsed).
    pub identical: usize,
    /// Files only in the new folder, only in the old.
    pub added: usize,
    pub removed: usize,
}

/// One side of a diff, as given.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Side {
    pub path: PathBuf,
    pub kind: InputKind,
}

/// Everything that differs between two bakes: per light totals and every
/// caster that differs, sorted by chunk, kind, index and group.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct BakeDiff {
    pub old: Side,
    pub new: Side,
    pub differs: bool,
    pub totals: Totals,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chunk_files: Option<ChunkFiles>,
    pub lights: Vec<LightChanges>,
    pub casters: Vec<CasterChange>,
}

/// The casters of one chunk that differ between `old` and `new`.
pub fn diff_chunk(chunk: &str, old: &ChunkMasks, new: &ChunkMasks) -> Vec<CasterChange> {
    let change = |key: &CasterKey, change, old_mask: Option<u32>, new_mask: Option<u32>| {
        let (before, after) = (old_mask.unwrap_or(0), new_mask.unwrap_or(0));
        let flipped = change == Change::Flipped;
        CasterChange {
            chunk: chunk.to_string(),
            kind: key.kind,
            index: key.index,
            group: key.group,
            change,
            old_mask,
            new_mask,
            to_culled: if flipped {
                bits(before & !after)
            } else {
                Vec::new()
            },
            to_useful: if flipped {
                bits(!before & after)
            } else {
                Vec::new()
            },
        }
    };
    let mut out = Vec::new();
    for (key, &mask) in old {
        match new.get(key) {
            Some(&now) if now != mask => {
                out.push(change(key, Change::Flipped, Some(mask), Some(now)))
            }
            Some(_) => {}
            None => out.push(change(key, Change::Disappeared, Some(mask), None)),
        }
    }
    for (key, &mask) in new {
        if !old.contains_key(key) {
            out.push(change(key, Change::Appeared, None, Some(mask)));
        }
    }
    out.sort_by_key(|c| (c.kind, c.index, c.group));
    out
}

/// The set bits of `mask`, lowest first.
fn bits(mask: u32) -> Vec<u32> {
    (0..32).filter(|b| mask & (1 << b) != 0).collect()
}

/// The casters of a chunk file's `<shadow>` elements: each instance's
/// groups (or its mask alone), each speedtree's, the terrain block's.
pub fn chunk_masks(shadows: &ChunkShadows) -> ChunkMasks {
    let mut out = ChunkMasks::new();
    let mut instance = |kind, index, shadow: &InstanceShadow| {
        let groups: Vec<u32> = shadow.groups().collect();
        insert_caster(&mut out, kind, Some(index), shadow.mask, &groups);
    };
    for (index, shadow) in shadows.instances.iter().enumerate() {
        if let Some(shadow) = shadow {
            instance(CasterKind::Model, index, shadow);
        }
    }
    for (index, shadow) in shadows.speedtrees.iter().enumerate() {
        if let Some(shadow) = shadow {
            instance(CasterKind::SpeedTree, index, shadow);
        }
    }
    if let Some(mask) = shadows.terrain {
        insert_caster(&mut out, CasterKind::Terrain, None, mask, &[]);
    }
    out
}

/// Adds a caster's group masks, or its mask when it has no groups; says
/// whether it was new.
fn insert_caster(
    out: &mut ChunkMasks,
    kind: CasterKind,
    index: Option<usize>,
    mask: u32,
    groups: &[u32],
) -> bool {
    let key = |group| CasterKey { kind, index, group };
    if groups.is_empty() {
        return out.insert(key(None), mask).is_none();
    }
    let mut new = true;
    for (group, &mask) in groups.iter().enumerate() {
        new &= out.insert(key(Some(group)), mask).is_none();
    }
    new
}

/// The parts of a `--report` a diff reads; other fields are ignored.
#[derive(Debug, Deserialize)]
struct ReportFile {
    report_version: u32,
    lights: Vec<ReportLight>,
    casters: Vec<ReportCaster>,
}

#[derive(Debug, Deserialize)]
struct ReportLight {
    bit: u32,
    name: String,
}

#[derive(Debug, Deserialize)]
struct ReportCaster {
    chunk: String,
    kind: String,
    index: Option<usize>,
    mask: u32,
    groups: Option<Vec<u32>>,
}

/// A report's lights (bit → name) and casters (chunk → masks).
#[derive(Debug, Default)]
pub struct ReportMasks {
    pub lights: BTreeMap<u32, String>,
    pub chunks: BTreeMap<String, ChunkMasks>,
}

/// Reads a report's lights and casters from its bytes; errors say what is
/// wrong (`path` names the file).
pub fn parse_report(path: &Path, bytes: &[u8]) -> Result<ReportMasks> {
    let garbled = |what: String| {
        Error::invalid(
            path,
            format!("not a bake report (the JSON `--report` writes): {what}"),
        )
    };
    let report: ReportFile = serde_json::from_slice(bytes).map_err(|e| garbled(e.to_string()))?;
    if report.report_version > REPORT_VERSION {
        return Err(garbled(format!(
            "report_version {} is newer than this shadowcull reads ({REPORT_VERSION}): diff it with the shadowcull that wrote it",
            report.report_version
        )));
    }
    let mut out = ReportMasks::default();
    for light in report.lights {
        if light.bit >= 32 {
            return Err(garbled(format!(
                "light `{}` has bit {}, outside the 32-bit mask",
                light.name, light.bit
            )));
        }
        out.lights.insert(light.bit, light.name);
    }
    for (at, caster) in report.casters.into_iter().enumerate() {
        let kind = CasterKind::from_name(&caster.kind).ok_or_else(|| {
            garbled(format!(
                "casters[{at}] has kind `{}`; expected model, speedtree or terrain",
                caster.kind
            ))
        })?;
        if (kind == CasterKind::Terrain) != caster.index.is_none() {
            return Err(garbled(format!(
                "casters[{at}] ({} in chunk {}): a terrain block has no index, a model or speedtree has one",
                caster.kind, caster.chunk
            )));
        }
        let groups = caster.groups.unwrap_or_default();
        let chunk = out.chunks.entry(caster.chunk.clone()).or_default();
        if !insert_caster(chunk, kind, caster.index, caster.mask, &groups) {
            return Err(garbled(format!(
                "casters[{at}] ({} {} in chunk {}) is listed twice",
                caster.kind,
                caster.index.map(|i| i.to_string()).unwrap_or_default(),
                caster.chunk
            )));
        }
    }
    Ok(out)
}

/// Diffs two bake reports.
pub fn diff_reports(old: &Path, new: &Path) -> Result<BakeDiff> {
    let read = |path: &Path| parse_report(path, &files::read_report_bytes(path)?);
    let (before, after) = (read(old)?, read(new)?);
    let empty = ChunkMasks::new();
    let mut casters = Vec::new();
    let mut names: Vec<&String> = before.chunks.keys().chain(after.chunks.keys()).collect();
    names.sort();
    names.dedup();
    for chunk in names {
        let old_masks = before.chunks.get(chunk).unwrap_or(&empty);
        let new_masks = after.chunks.get(chunk).unwrap_or(&empty);
        casters.extend(diff_chunk(chunk, old_masks, new_masks));
    }
    let mut lights: BTreeMap<u32, (Option<String>, Option<String>)> = BTreeMap::new();
    for (bit, name) in &before.lights {
        lights.entry(*bit).or_default().0 = Some(name.clone());
    }
    for (bit, name) in &after.lights {
        lights.entry(*bit).or_default().1 = Some(name.clone());
    }
    Ok(assemble(
        Side {
            path: old.to_path_buf(),
            kind: InputKind::Report,
        },
        Side {
            path: new.to_path_buf(),
            kind: InputKind::Report,
        },
        lights,
        casters,
        None,
    ))
}

/// The `.chunk` files under `dir`, by path relative to it; a folder
/// without one is an error.
fn chunk_files(dir: &Path) -> Result<BTreeMap<PathBuf, PathBuf>> {
    let walk = files::walk(dir, ".chunk", true)?;
    if let Some((_, err)) = walk.refused.into_iter().next() {
        return Err(err);
    }
    if walk.files.is_empty() {
        return Err(Error::invalid(
            dir,
            "holds no .chunk files: give two folders of baked chunk files (the space folders) or two bake reports",
        ));
    }
    Ok(walk
        .files
        .into_iter()
        .map(|path| {
            let relative = path.strip_prefix(dir).unwrap_or(&path).to_path_buf();
            (relative, path)
        })
        .collect())
}

/// A chunk's name in a folder diff: its path relative to the folder,
/// without `.chunk`, with `/` between folders (a space folder's chunk
/// files give the report's chunk names).
fn chunk_name(relative: &Path) -> String {
    let text = relative.to_string_lossy().replace('\\', "/");
    text.strip_suffix(".chunk").unwrap_or(&text).to_string()
}

/// The casters of the chunk file `path` whose bytes are `bytes`.
fn read_masks(path: &Path, bytes: &[u8]) -> Result<ChunkMasks> {
    let parse = |bytes: &[u8]| -> std::result::Result<ChunkShadows, crate::error::FormatError> {
        let root: Section = parse_data_section(bytes)?;
        read_chunk_shadows(&root)
    };
    let shadows = parse(bytes).map_err(|e| e.in_source(path, bytes))?;
    Ok(chunk_masks(&shadows))
}

/// What one relative chunk path contributes to a folder diff.
enum PairOutcome {
    Identical,
    Changed(Vec<CasterChange>),
}

/// Diffs two folders of baked chunk files of one space: files are matched
/// by relative path and only those whose bytes differ are parsed.
pub fn diff_chunk_folders(old: &Path, new: &Path) -> Result<BakeDiff> {
    let (before, after) = (chunk_files(old)?, chunk_files(new)?);
    let mut relatives: Vec<&PathBuf> = before.keys().chain(after.keys()).collect();
    relatives.sort();
    relatives.dedup();
    let empty = ChunkMasks::new();
    let outcomes = relatives
        .par_iter()
        .map(|relative| {
            let name = chunk_name(relative);
            let (old_path, new_path) = (before.get(*relative), after.get(*relative));
            let old_bytes = old_path.map(|p| files::read_file(p)).transpose()?;
            let new_bytes = new_path.map(|p| files::read_file(p)).transpose()?;
            if old_bytes.is_some() && old_bytes == new_bytes {
                return Ok(PairOutcome::Identical);
            }
            let masks = |path: Option<&PathBuf>, bytes: &Option<Vec<u8>>| match (path, bytes) {
                (Some(path), Some(bytes)) => read_masks(path, bytes),
                _ => Ok(empty.clone()),
            };
            let old_masks = masks(old_path, &old_bytes)?;
            let new_masks = masks(new_path, &new_bytes)?;
            Ok(PairOutcome::Changed(diff_chunk(
                &name, &old_masks, &new_masks,
            )))
        })
        .collect::<Result<Vec<PairOutcome>>>()?;
    let matched = before.keys().filter(|k| after.contains_key(*k)).count();
    let files = ChunkFiles {
        matched,
        identical: outcomes
            .iter()
            .filter(|o| matches!(o, PairOutcome::Identical))
            .count(),
        added: after.len() - matched,
        removed: before.len() - matched,
    };
    let mut casters: Vec<CasterChange> = outcomes
        .into_iter()
        .flat_map(|o| match o {
            PairOutcome::Identical => Vec::new(),
            PairOutcome::Changed(changes) => changes,
        })
        .collect();
    // Chunk names sort as strings, which relative paths need not.
    casters.sort_by(|a, b| {
        (&a.chunk, a.kind, a.index, a.group).cmp(&(&b.chunk, b.kind, b.index, b.group))
    });
    Ok(assemble(
        Side {
            path: old.to_path_buf(),
            kind: InputKind::ChunkFolder,
        },
        Side {
            path: new.to_path_buf(),
            kind: InputKind::ChunkFolder,
        },
        BTreeMap::new(),
        casters,
        Some(files),
    ))
}

/// Totals and per light counts of `casters`; `lights` names bits by the
/// old and the new report (every light listed, changed or not; other bits
/// only when something changed in them).
fn assemble(
    old: Side,
    new: Side,
    names: BTreeMap<u32, (Option<String>, Option<String>)>,
    casters: Vec<CasterChange>,
    chunk_files: Option<ChunkFiles>,
) -> BakeDiff {
    let mut lights: BTreeMap<u32, LightChanges> = names
        .into_iter()
        .map(|(bit, (old_name, new_name))| (bit, LightChanges::named(bit, old_name, new_name)))
        .collect();
    let mut light = |bit: u32, count: fn(&mut LightChanges)| {
        count(
            lights
                .entry(bit)
                .or_insert_with(|| LightChanges::named(bit, None, None)),
        )
    };
    let mut totals = Totals::default();
    let mut chunks: Vec<&str> = Vec::new();
    for caster in &casters {
        if chunks.last() != Some(&caster.chunk.as_str()) {
            chunks.push(&caster.chunk);
        }
        match caster.change {
            Change::Flipped => {
                totals.flipped += 1;
                totals.to_culled += caster.to_culled.len();
                totals.to_useful += caster.to_useful.len();
                caster
                    .to_culled
                    .iter()
                    .for_each(|&b| light(b, |l| l.to_culled += 1));
                caster
                    .to_useful
                    .iter()
                    .for_each(|&b| light(b, |l| l.to_useful += 1));
            }
            Change::Appeared => {
                totals.appeared += 1;
                bits(caster.mask())
                    .into_iter()
                    .for_each(|b| light(b, |l| l.appeared_useful += 1));
            }
            Change::Disappeared => {
                totals.disappeared += 1;
                bits(caster.mask())
                    .into_iter()
                    .for_each(|b| light(b, |l| l.disappeared_useful += 1));
            }
        }
    }
    totals.chunks = chunks.len();
    BakeDiff {
        old,
        new,
        differs: !casters.is_empty(),
        totals,
        chunk_files,
        lights: lights.into_values().collect(),
        casters,
    }
}

/// Instances listed per chunk and line in the text form before `… N more`.
pub const TEXT_LISTING_CAP: usize = 6;

impl BakeDiff {
    /// The readable form: a table per light, totals, then per light and
    /// chunk the casters that flipped, and those that appeared or
    /// disappeared (long listings capped; `--json` has every caster).
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        for (label, side) in [("old", &self.old), ("new", &self.new)] {
            let _ = writeln!(
                out,
                "{label}: {} ({})",
                side.path.display(),
                side.kind.describe()
            );
        }
        if !self.differs {
            let _ = writeln!(
                out,
                "no differences: every caster has the same mask in both"
            );
            if let Some(files) = &self.chunk_files {
                let _ = writeln!(out, "{}", files.summary());
            }
            return out;
        }
        let _ = writeln!(
            out,
            "{:<24} {:>3} {:>14} {:>14} {:>9} {:>12}",
            "light", "bit", "useful→culled", "culled→useful", "appeared", "disappeared"
        );
        for light in &self.lights {
            let _ = writeln!(
                out,
                "{:<24} {:>3} {:>14} {:>14} {:>9} {:>12}",
                light.name(),
                light.bit,
                light.to_culled,
                light.to_useful,
                light.appeared_useful,
                light.disappeared_useful
            );
        }
        let t = &self.totals;
        let _ = writeln!(
            out,
            "{} flipped ({} useful→culled, {} culled→useful), {} appeared, {} disappeared, in {}",
            plural(t.flipped, "caster", "casters"),
            t.to_culled,
            t.to_useful,
            t.appeared,
            t.disappeared,
            plural(t.chunks, "chunk", "chunks")
        );
        if let Some(files) = &self.chunk_files {
            let _ = writeln!(out, "{}", files.summary());
        }
        for light in self.lights.iter().filter(|l| l.to_culled + l.to_useful > 0) {
            let heading = match (&light.old_name, &light.new_name) {
                (None, None) => light.name(),
                _ => format!("{} (bit {})", light.name(), light.bit),
            };
            let _ = writeln!(out, "\n{heading}");
            let bit = light.bit;
            self.list(&mut out, "useful→culled", |c| c.to_culled.contains(&bit));
            self.list(&mut out, "culled→useful", |c| c.to_useful.contains(&bit));
        }
        for (change, title) in [
            (Change::Appeared, "appeared"),
            (Change::Disappeared, "disappeared"),
        ] {
            if self.casters.iter().any(|c| c.change == change) {
                let _ = writeln!(out, "\n{title}");
                self.list(&mut out, "", |c| c.change == change);
            }
        }
        out
    }

    /// One line per chunk: the casters `selected` picks, by instance.
    fn list(&self, out: &mut String, what: &str, selected: impl Fn(&CasterChange) -> bool) {
        let picked: Vec<&CasterChange> = self.casters.iter().filter(|c| selected(c)).collect();
        for chunk in picked.chunk_by(|a, b| a.chunk == b.chunk) {
            let instances: Vec<&[&CasterChange]> = chunk
                .chunk_by(|a, b| (a.kind, a.index) == (b.kind, b.index))
                .collect();
            let shown: Vec<String> = instances
                .iter()
                .take(TEXT_LISTING_CAP)
                .map(|casters| instance_label(casters))
                .collect();
            let mut line = shown.join(", ");
            let left: usize = instances
                .iter()
                .skip(TEXT_LISTING_CAP)
                .map(|c| c.len())
                .sum();
            if left > 0 {
                let _ = write!(line, ", … {left} more");
            }
            let what = if what.is_empty() {
                String::new()
            } else {
                format!("{what}  ")
            };
            let _ = writeln!(out, "  {:<12} {what}{line}", chunk[0].chunk);
        }
    }
}

/// `model 3`, `model 3 group 1`, `model 3 groups 0 1 2`, `terrain`: one
/// instance's casters.
fn instance_label(casters: &[&CasterChange]) -> String {
    let first = casters[0];
    let mut out = first.kind.name().to_string();
    if let Some(index) = first.index {
        let _ = write!(out, " {index}");
    }
    let groups: Vec<String> = casters
        .iter()
        .filter_map(|c| c.group.map(|g| g.to_string()))
        .collect();
    match groups.len() {
        0 => {}
        1 => {
            let _ = write!(out, " group {}", groups[0]);
        }
        _ => {
            let _ = write!(out, " groups {}", groups.join(" "));
        }
    }
    out
}

impl ChunkFiles {
    fn summary(&self) -> String {
        format!(
            "chunk files: {} in both ({} identical, not parsed), {} added, {} removed",
            self.matched, self.identical, self.added, self.removed
        )
    }
}

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(kind: CasterKind, index: Option<usize>, group: Option<usize>) -> CasterKey {
        CasterKey { kind, index, group }
    }

    #[test]
    fn flips_appearances_and_disappearances_are_told_apart() {
        let model = |i, g| key(CasterKind::Model, Some(i), Some(g));
        let terrain = key(CasterKind::Terrain, None, None);
        let old = ChunkMasks::from([
            (model(0, 0), 0b011),
            (model(0, 1), 0b1),
            (model(1, 0), 0b1),
            (terrain, 0b10),
        ]);
        let new = ChunkMasks::from([
            (model(0, 0), 0b110),
            (model(0, 1), 0b1),
            (model(2, 0), 0b100),
            (terrain, 0b10),
        ]);
        let changes = diff_chunk("c", &old, &new);
        type Summary = (Option<usize>, Change, Vec<u32>, Vec<u32>);
        let summary: Vec<Summary> = changes
            .iter()
            .map(|c| (c.index, c.change, c.to_culled.clone(), c.to_useful.clone()))
            .collect();
        assert_eq!(
            summary,
            vec![
                (Some(0), Change::Flipped, vec![0], vec![2]),
                (Some(1), Change::Disappeared, vec![], vec![]),
                (Some(2), Change::Appeared, vec![], vec![]),
            ]
        );
        assert!(diff_chunk("c", &old, &old).is_empty());
        let diff = assemble(
            Side {
                path: "a".into(),
                kind: InputKind::Report,
            },
            Side {
                path: "b".into(),
                kind: InputKind::Report,
            },
            BTreeMap::from([(1, (Some("sun".into()), Some("sun".into())))]),
            changes,
            None,
        );
        assert_eq!(diff.totals.flipped, 1);
        assert_eq!(
            (
                diff.totals.appeared,
                diff.totals.disappeared,
                diff.totals.chunks
            ),
            (1, 1, 1)
        );
        let by_bit: Vec<(u32, usize, usize, usize, usize)> = diff
            .lights
            .iter()
            .map(|l| {
                (
                    l.bit,
                    l.to_culled,
                    l.to_useful,
                    l.appeared_useful,
                    l.disappeared_useful,
                )
            })
            .collect();
        // Bit 1 is listed although nothing changed in it: the report names it.
        assert_eq!(
            by_bit,
            vec![(0, 1, 0, 0, 1), (1, 0, 0, 0, 0), (2, 0, 1, 1, 0)]
        );
        let text = diff.to_text();
        assert!(
            text.contains("c            useful→culled  model 0 group 0"),
            "{text}"
        );
        assert!(
            text.contains("appeared\n  c            model 2 group 0"),
            "{text}"
        );
    }

    #[test]
    fn chunk_shadows_become_group_casters_or_one_mask() {
        let shadows = ChunkShadows {
            instances: vec![
                Some(InstanceShadow::from_groups(vec![
                    vec![vec![1, 2]],
                    vec![vec![4]],
                ])),
                None,
                Some(InstanceShadow {
                    mask: 8,
                    render_sets: Vec::new(),
                }),
            ],
            speedtrees: vec![Some(InstanceShadow {
                mask: 3,
                render_sets: Vec::new(),
            })],
            terrain: Some(5),
        };
        let masks: Vec<(CasterKey, u32)> = chunk_masks(&shadows).into_iter().collect();
        let model = |i, g| key(CasterKind::Model, Some(i), g);
        assert_eq!(
            masks,
            vec![
                (model(0, Some(0)), 1),
                (model(0, Some(1)), 2),
                (model(0, Some(2)), 4),
                (model(2, None), 8),
                (key(CasterKind::SpeedTree, Some(0), None), 3),
                (key(CasterKind::Terrain, None, None), 5),
            ]
        );
    }

    #[test]
    fn a_report_that_is_not_one_is_named_with_what_is_wrong() {
        let path = Path::new("r.json");
        let error = |bytes: &str| {
            parse_report(path, bytes.as_bytes())
                .unwrap_err()
                .to_string()
        };
        let message = error("{\"casters\": [");
        assert!(
            message.starts_with("r.json: not a bake report"),
            "{message}"
        );
        let message = error(r#"{"report_version": 3, "lights": []}"#);
        assert!(message.contains("missing field `casters`"), "{message}");
        let caster = r#"{"chunk": "c", "kind": "tree", "index": 0, "mask": 1}"#;
        let message = error(&format!(
            r#"{{"report_version": 3, "lights": [], "casters": [{caster}]}}"#
        ));
        assert!(message.contains("casters[0] has kind `tree`"), "{message}");
        let caster = r#"{"chunk": "c", "kind": "model", "index": 0, "mask": 1}"#;
        let message = error(&format!(
            r#"{{"report_version": 3, "lights": [], "casters": [{caster}, {caster}]}}"#
        ));
        assert!(
            message.contains("casters[1] (model 0 in chunk c) is listed twice"),
            "{message}"
        );
        let message = error(r#"{"report_version": 99, "lights": [], "casters": []}"#);
        assert!(message.contains("report_version 99 is newer"), "{message}");
        let good = format!(
            r#"{{"report_version": 3, "lights": [{{"bit": 2, "name": "sun", "kind": "spot"}}], "casters": [{caster}]}}"#
        );
        let masks = parse_report(path, good.as_bytes()).unwrap();
        assert_eq!(masks.lights, BTreeMap::from([(2, "sun".to_string())]));
        assert_eq!(masks.chunks["c"].len(), 1);
    }
}
