//! A text chunk file read straight from its XML events: what
//! [`chunk::parse`](super::chunk::parse) reads of it and where its
//! `<shadow>`s go ([`ShadowSites`]), without building the element tree,
//! whose allocations (a name, a value and a path per element) are most of
//! a large world's load. It reads the shape chunk files have; anything
//! else (an entity or CDATA in a value it reads, a value that does not
//! read, a file that does not parse) it leaves to the tree reader by
//! answering `None`, so every answer and every error is the tree
//! reader's. Tests compare both on generated and real chunks.

use super::chunk::{
    ChunkFile, InstanceElement, InstanceKind, SpeedTreeElement, TerrainElement, SPEEDTREE_TAG,
};
use super::section::{bool_of, i64_of, matrix_of, ROW_TAGS};
use super::shadow_write::{self, Place, ShadowSites, Site, SHADOW_TAG};
use glam::DMat4;
use quick_xml::events::Event;
use std::collections::BTreeMap;
use std::ops::Range;

/// Nesting the scan follows; deeper files go to the tree reader (which
/// has its own limit and error).
const MAX_DEPTH: usize = 64;

/// The chunk's items and `<shadow>` places, or `None` where the tree
/// reader must answer.
pub fn scan(bytes: &[u8]) -> Option<(ChunkFile, ShadowSites)> {
    let (mut reader, bom) = super::xml::reader(bytes);
    let mut scan = Scan::default();
    loop {
        let start = bom + reader.buffer_position() as usize;
        let event = reader.read_event().ok()?;
        let end = bom + reader.buffer_position() as usize;
        match event {
            Event::Start(tag) => {
                scan.open(std::str::from_utf8(tag.name().as_ref()).ok()?, start)?
            }
            Event::Empty(tag) => {
                scan.open(std::str::from_utf8(tag.name().as_ref()).ok()?, start)?;
                scan.close(start, end)?;
            }
            Event::End(_) => scan.close(start, end)?,
            Event::Text(text) => scan.text(text.as_ref())?,
            Event::CData(_) | Event::GeneralRef(_) => scan.unread()?,
            Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_) => {}
            Event::Eof => return None,
        }
        // The engine reads only the first top-level element.
        if scan.done {
            return scan.finish(bytes);
        }
    }
}

/// What an open element is to the scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Root,
    /// A direct child of the root the scan reads: an instance or the
    /// first `<terrain>` (the root's first `<transform>` is a `Transform`).
    Target,
    /// A value of the innermost target the scan reads.
    Value(Field),
    /// The target's first `<transform>` (or the root's), whose own value
    /// and rows are read.
    Transform,
    /// The target's first `<editorOnly>`, whose first `castsShadow` is.
    EditorOnly,
    /// The target's first direct `<shadow>`: its mask and render sets.
    Shadow,
    RenderSet,
    Geometry,
    /// A further direct `<shadow>`, removed when the target is written.
    ExtraShadow,
    /// Read by nothing: only its nesting is followed.
    Skipped,
}

/// Values the chunk reader and the shadow writer read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Field {
    Resource,
    Row(usize),
    CastsShadow,
    EditorCastsShadow,
    Spt,
    Seed,
    VisibilityMask,
    GroupMask,
}

/// Whether an element of this role has its text read.
fn reads_value(role: Role) -> bool {
    matches!(role, Role::Value(_) | Role::Shadow | Role::Transform)
}

/// What a direct child of the root the scan reads is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum TargetKind {
    Instance(InstanceKind),
    Terrain,
    /// The root's own transform (an indoor chunk's).
    Transform,
}

/// An open element: its role and its text as the tree reader joins it
/// (runs trimmed, joined by a space around children).
struct Open {
    role: Role,
    run: String,
    value: String,
}

/// One target element as read so far.
struct Target {
    kind: TargetKind,
    start: usize,
    resources: Vec<String>,
    transform: Option<Matrix>,
    casts_shadow: Option<String>,
    editor_only_seen: bool,
    editor_casts_shadow: Option<String>,
    spt: Option<String>,
    seed: Option<String>,
    visibility_mask: Option<String>,
    shadow: Option<Shadow>,
    extras: Vec<Range<usize>>,
    /// The element's span and where its end tag starts.
    span: Range<usize>,
    close: usize,
}

/// A `<transform>`: its own value and its first row of each number.
#[derive(Default)]
struct Matrix {
    value: String,
    rows: [Option<String>; 4],
}

impl Matrix {
    fn read(&self) -> Option<DMat4> {
        matrix_of(self.rows.each_ref().map(Option::as_deref), &self.value).ok()
    }
}

/// The first direct `<shadow>` of a target, as the writer reads it back.
#[derive(Default)]
struct Shadow {
    span: Range<usize>,
    mask: String,
    groups: Vec<String>,
}

#[derive(Default)]
struct Scan {
    open: Vec<Open>,
    root_name: Option<String>,
    items: BTreeMap<String, usize>,
    targets: Vec<Target>,
    done: bool,
}

impl Scan {
    /// A start tag at byte `start`: its role from its parent's.
    fn open(&mut self, name: &str, start: usize) -> Option<()> {
        if self.open.len() >= MAX_DEPTH {
            return None;
        }
        self.flush();
        let role = match self.open.last().map(|o| o.role) {
            None if self.root_name.is_some() => return None,
            None => {
                self.root_name = Some(name.to_string());
                Role::Root
            }
            Some(Role::Root) => self.root_child(name, start),
            Some(parent) => self.child(parent, name, start)?,
        };
        self.open.push(Open {
            role,
            run: String::new(),
            value: String::new(),
        });
        Some(())
    }

    fn root_child(&mut self, name: &str, start: usize) -> Role {
        let count = match self.items.get_mut(name) {
            Some(count) => {
                *count += 1;
                *count
            }
            None => {
                self.items.insert(name.to_string(), 1);
                1
            }
        };
        let (kind, role) = match (InstanceKind::from_tag(name), name, count) {
            (Some(kind), _, _) => (TargetKind::Instance(kind), Role::Target),
            (None, "terrain", 1) => (TargetKind::Terrain, Role::Target),
            (None, "transform", 1) => (TargetKind::Transform, Role::Transform),
            _ => return Role::Skipped,
        };
        self.targets.push(Target::new(kind, start));
        role
    }

    /// The role of a child of `parent` (below the root's children).
    fn child(&mut self, parent: Role, name: &str, start: usize) -> Option<Role> {
        let Some(target) = self.targets.last_mut() else {
            return Some(Role::Skipped);
        };
        let row = |matrix: &Option<Matrix>| {
            let i = ROW_TAGS.iter().position(|r| *r == name)?;
            matrix.as_ref()?.rows[i]
                .is_none()
                .then_some(Role::Value(Field::Row(i)))
        };
        Some(match parent {
            // Mixed content inside a value the tree reader joins; left to it.
            Role::Value(_) => return None,
            Role::Target => target.child(name, start),
            Role::Transform => row(&target.transform).unwrap_or(Role::Skipped),
            Role::EditorOnly if name == "castsShadow" && target.editor_casts_shadow.is_none() => {
                Role::Value(Field::EditorCastsShadow)
            }
            Role::Shadow if name == "RenderSet" => Role::RenderSet,
            Role::RenderSet if name == "Geometry" => Role::Geometry,
            Role::Geometry if name == "PrimitiveGroup" => Role::Value(Field::GroupMask),
            _ => Role::Skipped,
        })
    }

    /// Text inside the innermost open element; outside the root, only
    /// white space.
    fn text(&mut self, text: &[u8]) -> Option<()> {
        match self.open.last_mut() {
            Some(open) if reads_value(open.role) => {
                open.run.push_str(std::str::from_utf8(text).ok()?)
            }
            Some(_) => {}
            None if !text.iter().all(u8::is_ascii_whitespace) => return None,
            None => {}
        }
        Some(())
    }

    /// An entity or CDATA: fine where no value is read.
    fn unread(&mut self) -> Option<()> {
        match self.open.last() {
            Some(open) if reads_value(open.role) => None,
            _ => Some(()),
        }
    }

    /// The innermost open element's run joined to its value, as the tree
    /// reader does at each child and end tag.
    fn flush(&mut self) {
        if let Some(open) = self.open.last_mut() {
            let piece = open.run.trim();
            if !piece.is_empty() {
                if !open.value.is_empty() {
                    open.value.push(' ');
                }
                open.value.push_str(piece);
            }
            open.run.clear();
        }
    }

    /// An end tag starting at `close`, or an empty element's tag; the
    /// element ends at `end`.
    fn close(&mut self, close: usize, end: usize) -> Option<()> {
        self.flush();
        let open = self.open.pop()?;
        let Some(target) = self.targets.last_mut() else {
            self.done = open.role == Role::Root;
            return Some(());
        };
        match open.role {
            Role::Root => self.done = true,
            Role::Target => {
                target.span = target.start..end;
                target.close = close;
            }
            Role::Transform => target.transform.as_mut()?.value = open.value,
            Role::Shadow => {
                let shadow = target.shadow.as_mut()?;
                shadow.mask = open.value;
                shadow.span.end = end;
            }
            Role::ExtraShadow => target.extras.last_mut()?.end = end,
            Role::Value(field) => target.set(field, open.value),
            Role::RenderSet | Role::Geometry | Role::EditorOnly | Role::Skipped => {}
        }
        Some(())
    }

    fn finish(self, bytes: &[u8]) -> Option<(ChunkFile, ShadowSites)> {
        let root_name = self.root_name?;
        let depth = u8::try_from(1 + root_name.matches('/').count()).ok()?;
        let path = |tag: &str| format!("{root_name}/{tag}");
        let mut shared = super::chunk::SharedValues::default();
        let count =
            |of: fn(TargetKind) -> bool| self.targets.iter().filter(|t| of(t.kind)).count() as u32;
        let models = count(|k| matches!(k, TargetKind::Instance(i) if i.names_models()));
        let trees = count(|k| k == TargetKind::Instance(InstanceKind::SpeedTree));
        let mut chunk = ChunkFile {
            root_name: root_name.clone(),
            transform: None,
            instances: Vec::new(),
            speedtrees: Vec::new(),
            terrain: None,
            items: self.items,
        };
        let mut sites = ShadowSites {
            depth,
            ..ShadowSites::default()
        };
        for target in self.targets {
            // Its place in the writer's order: instances, speedtrees, terrain.
            let writer_index = match target.kind {
                TargetKind::Transform => {
                    chunk.transform = Some(target.transform?.read()?);
                    continue;
                }
                TargetKind::Instance(InstanceKind::SpeedTree) => {
                    models + chunk.speedtrees.len() as u32
                }
                TargetKind::Instance(_) => chunk.instances.len() as u32,
                TargetKind::Terrain => models + trees,
            };
            for extra in &target.extras {
                let line = shadow_write::whole_line(bytes, extra.clone());
                let range =
                    shadow_write::offset(line.start).ok()?..shadow_write::offset(line.end).ok()?;
                sites.extras.push((writer_index, range));
            }
            let site = target.site(bytes)?;
            let transform = || match &target.transform {
                Some(matrix) => matrix.read(),
                None => Some(DMat4::IDENTITY),
            };
            match target.kind {
                TargetKind::Instance(InstanceKind::SpeedTree) => {
                    let integer = |value: &Option<String>| match value {
                        Some(text) => i64_of(text).map(Some),
                        None => Some(None),
                    };
                    chunk.speedtrees.push(SpeedTreeElement {
                        index: chunk.speedtrees.len(),
                        spt: target.spt.clone().unwrap_or_default(),
                        seed: integer(&target.seed)?,
                        visibility_mask: integer(&target.visibility_mask)?,
                        transform: transform()?,
                        path: path(SPEEDTREE_TAG),
                    });
                    sites.speedtrees.push(site);
                }
                TargetKind::Instance(kind) => {
                    let casts_shadow = match (&target.casts_shadow, &target.editor_casts_shadow) {
                        (Some(flag), _) | (None, Some(flag)) => bool_of(flag)?,
                        (None, None) => true,
                    };
                    chunk.instances.push(InstanceElement {
                        kind,
                        index: chunk.instances.len(),
                        transform: transform()?,
                        casts_shadow,
                        path: shared.path(&path(kind.tag())),
                        resources: shared.list(target.resources),
                    });
                    sites.instances.push(site);
                }
                TargetKind::Terrain | TargetKind::Transform => {
                    chunk.terrain = Some(TerrainElement {
                        resource: target.resources.into_iter().next()?,
                        path: path("terrain"),
                    });
                    sites.terrain = Some(site);
                }
            }
        }
        // Extras were met in file order; the writer looks them up by target.
        sites.extras.sort_by_key(|(target, _)| *target);
        Some((chunk, sites))
    }
}

impl Target {
    fn new(kind: TargetKind, start: usize) -> Target {
        Target {
            kind,
            start,
            resources: Vec::new(),
            // The root's transform is read as an instance's is.
            transform: (kind == TargetKind::Transform).then(Matrix::default),
            casts_shadow: None,
            editor_only_seen: false,
            editor_casts_shadow: None,
            spt: None,
            seed: None,
            visibility_mask: None,
            shadow: None,
            extras: Vec::new(),
            span: start..start,
            close: start,
        }
    }

    /// The role of a direct child named `name` starting at `start`.
    fn child(&mut self, name: &str, start: usize) -> Role {
        match name {
            "resource" => Role::Value(Field::Resource),
            "transform" if self.transform.is_none() => {
                self.transform = Some(Matrix::default());
                Role::Transform
            }
            "castsShadow" if self.casts_shadow.is_none() => Role::Value(Field::CastsShadow),
            "editorOnly" if !self.editor_only_seen => {
                self.editor_only_seen = true;
                Role::EditorOnly
            }
            "spt" if self.spt.is_none() => Role::Value(Field::Spt),
            "seed" if self.seed.is_none() => Role::Value(Field::Seed),
            "visibilityMask" if self.visibility_mask.is_none() => {
                Role::Value(Field::VisibilityMask)
            }
            SHADOW_TAG if self.shadow.is_none() => {
                self.shadow = Some(Shadow {
                    span: start..start,
                    ..Shadow::default()
                });
                Role::Shadow
            }
            SHADOW_TAG => {
                self.extras.push(start..start);
                Role::ExtraShadow
            }
            _ => Role::Skipped,
        }
    }

    fn set(&mut self, field: Field, value: String) {
        let slot = match field {
            Field::Resource => {
                self.resources.push(value);
                return;
            }
            Field::GroupMask => {
                if let Some(shadow) = &mut self.shadow {
                    shadow.groups.push(value);
                }
                return;
            }
            Field::Row(i) => match &mut self.transform {
                Some(matrix) => &mut matrix.rows[i],
                None => return,
            },
            Field::CastsShadow => &mut self.casts_shadow,
            Field::EditorCastsShadow => &mut self.editor_casts_shadow,
            Field::Spt => &mut self.spt,
            Field::Seed => &mut self.seed,
            Field::VisibilityMask => &mut self.visibility_mask,
        };
        slot.get_or_insert(value);
    }

    /// Where its `<shadow>` goes, and the bits the one it has holds.
    fn site(&self, bytes: &[u8]) -> Option<Site> {
        let (place, span) = match &self.shadow {
            Some(shadow) => (Place::Replace, shadow.span.clone()),
            None => shadow_write::place_without_shadow(bytes, self.span.clone(), self.close),
        };
        let held = match &self.shadow {
            None => Some(0),
            Some(shadow) => {
                let mask = shadow_write::mask_of(&shadow.mask);
                let groups = shadow.groups.iter().map(|g| shadow_write::mask_of(g));
                groups.fold(mask, |all, group| Some(all? | group?))
            }
        };
        Some(Site {
            place,
            start: shadow_write::offset(span.start).ok()?,
            end: shadow_write::offset(span.end).ok()?,
            held,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::shadow_write::{write_shadows, ChunkShadows, InstanceShadow};
    use crate::formats::{chunk, xml};
    use crate::rng::Rng;

    /// What the tree reader reads of `bytes`: the oracle.
    fn tree(bytes: &[u8]) -> Option<(ChunkFile, ShadowSites)> {
        let root = xml::parse(bytes).ok()?;
        let chunk = chunk::parse(&root).ok()?;
        let sites = ShadowSites::find(bytes, &root).ok()?;
        Some((chunk, sites))
    }

    /// The scan answers what the tree reader answers, or leaves it to it.
    fn agrees(bytes: &[u8], what: &str) -> bool {
        match scan(bytes) {
            Some(scanned) => {
                let read = tree(bytes);
                assert!(
                    read.as_ref() == Some(&scanned),
                    "{what}: scan {scanned:?}\ntree {read:?}\n{}",
                    String::from_utf8_lossy(bytes)
                );
                true
            }
            None => false,
        }
    }

    fn pick<'a>(rng: &mut Rng, options: &[&'a str]) -> &'a str {
        options[rng.below(options.len())]
    }

    fn number(rng: &mut Rng) -> String {
        format!("{:.6}", rng.range(-100.0, 100.0))
    }

    fn rows(rng: &mut Rng, eol: &str, indent: &str) -> String {
        let mut out = String::new();
        for i in 0..4 {
            if rng.chance(0.9) {
                let n = if rng.chance(0.95) { 3 } else { 2 };
                let values: Vec<String> = (0..n).map(|_| number(rng)).collect();
                out.push_str(&format!(
                    "{indent}<row{i}>\t{}\t</row{i}>{eol}",
                    values.join(" ")
                ));
            }
        }
        out
    }

    fn transform(rng: &mut Rng, eol: &str, depth: usize) -> String {
        let tabs = "\t".repeat(depth);
        if rng.chance(0.3) {
            let values: Vec<String> = (0..12).map(|_| number(rng)).collect();
            return format!("{tabs}<transform>\t{}\t</transform>{eol}", values.join(" "));
        }
        let inner = rows(rng, eol, &"\t".repeat(depth + 1));
        format!("{tabs}<transform>{eol}{inner}{tabs}</transform>{eol}")
    }

    fn shadow(rng: &mut Rng, eol: &str) -> String {
        let mask = pick(rng, &["3", "0", "4294967295", "x", " 7 "]);
        if rng.chance(0.4) {
            return format!("\t\t<shadow>\t{mask}\t</shadow>{eol}");
        }
        let group = pick(rng, &["1", "2", "-1", "6"]);
        format!(
            "\t\t<shadow>\t{mask}{eol}\t\t\t<RenderSet>{eol}\t\t\t\t<Geometry>{eol}\t\t\t\t\t<PrimitiveGroup>\t{group}\t</PrimitiveGroup>{eol}\t\t\t\t\t<PrimitiveGroup>\t1\t</PrimitiveGroup>{eol}\t\t\t\t</Geometry>{eol}\t\t\t\t<Geometry />{eol}\t\t\t</RenderSet>{eol}\t\t</shadow>{eol}"
        )
    }

    /// A chunk of every shape the scan reads, and some it leaves.
    fn random_chunk(rng: &mut Rng) -> String {
        let eol = if rng.chance(0.3) { "\r\n" } else { "\n" };
        let root = pick(rng, &["root", "0000fffdo.chunk", "a/b"]);
        let mut text = format!("<{root}>{eol}");
        if rng.chance(0.3) {
            text.push_str(&transform(rng, eol, 1));
        }
        for _ in 0..rng.below(8) {
            let tag = pick(
                rng,
                &[
                    "model",
                    "shell",
                    "speedtree",
                    "terrain",
                    "entity",
                    "transform",
                    "light",
                ],
            );
            if rng.chance(0.1) {
                text.push_str(&format!("\t<{tag} />{eol}"));
                continue;
            }
            text.push_str(&format!("\t<{tag}>{eol}"));
            for _ in 0..rng.below(7) {
                let child = match rng.below(12) {
                    0 | 1 => format!("\t\t<resource>\t{}\t</resource>{eol}", pick(rng, &["sets/a.model", "t.cdata/terrain2", "", "a&amp;b"])),
                    2 => transform(rng, eol, 2),
                    3 => format!("\t\t<castsShadow>\t{}\t</castsShadow>{eol}", pick(rng, &["true", "FALSE", "0", "maybe"])),
                    4 => format!("\t\t<editorOnly>{eol}\t\t\t<castsShadow>\t{}\t</castsShadow>{eol}\t\t</editorOnly>{eol}", pick(rng, &["false", "1", "x"])),
                    5 => format!("\t\t<spt>\t{}\t</spt>{eol}", pick(rng, &["oak.spt", "<![CDATA[x]]>"])),
                    6 => format!("\t\t<seed>\t{}\t</seed>{eol}", pick(rng, &["4711", "-3", "1.0", "1.5"])),
                    7 => format!("\t\t<visibilityMask>\t{}\t</visibilityMask>{eol}", pick(rng, &["255", "x"])),
                    8 | 9 => shadow(rng, eol),
                    10 => format!("\t\t<!-- <shadow> -->{eol}"),
                    _ => format!("\t\t<reflectionVisible>\tfalse\t</reflectionVisible>{eol}"),
                };
                text.push_str(&child);
            }
            if rng.chance(0.2) {
                text.push_str(&format!("\t<{tag}>mixed{eol}\t\t<x/>\t</{tag}>{eol}"));
                continue;
            }
            text.push_str(&format!("\t</{tag}>{eol}"));
        }
        text.push_str(&format!("</{root}>{eol}"));
        text
    }

    #[test]
    fn the_scan_reads_what_the_tree_reads() {
        let mut rng = Rng::new(21);
        let (mut scanned, mut written) = (0, 0);
        for case in 0..3000 {
            let text = random_chunk(&mut rng);
            if agrees(text.as_bytes(), &format!("case {case}")) {
                scanned += 1;
            }
            // The same chunk once a bake wrote its masks.
            let Some((chunk, _)) = tree(text.as_bytes()) else {
                continue;
            };
            let shadows = ChunkShadows {
                instances: vec![
                    Some(InstanceShadow::from_groups(vec![vec![vec![5, 2]]]));
                    chunk.instances.len()
                ],
                speedtrees: vec![Some(InstanceShadow::default()); chunk.speedtrees.len()],
                terrain: chunk.terrain.as_ref().map(|_| 9),
            };
            if let Ok(out) = write_shadows(text.as_bytes(), &shadows) {
                if agrees(&out, &format!("case {case} written")) {
                    written += 1;
                }
            }
        }
        // Most chunks are of the shape the scan reads.
        assert!(
            scanned > 800 && written > 800,
            "{scanned} scanned, {written} written"
        );
    }

    #[test]
    fn a_damaged_chunk_is_left_to_the_tree_reader_or_read_as_it() {
        let mut rng = Rng::new(5);
        let mut scanned = 0;
        for case in 0..1500 {
            let mut bytes = random_chunk(&mut rng).into_bytes();
            match rng.below(4) {
                0 => bytes.truncate(rng.below(bytes.len() + 1)),
                1 => {
                    let at = rng.below(bytes.len());
                    bytes[at] = *b"<>/&\t x]".get(rng.below(8)).unwrap_or(&b'x');
                }
                2 => {
                    let at = rng.below(bytes.len());
                    let piece: &[u8] = pick(
                        &mut rng,
                        &[
                            "<!-- c -->",
                            "&amp;",
                            "<![CDATA[y]]>",
                            "<a>",
                            "</a>",
                            "\u{FEFF}",
                        ],
                    )
                    .as_bytes();
                    bytes.splice(at..at, piece.iter().copied());
                }
                _ => bytes
                    .splice(0..0, b"\xEF\xBB\xBF".iter().copied())
                    .for_each(drop),
            }
            if agrees(&bytes, &format!("case {case}")) {
                scanned += 1;
            }
        }
        assert!(scanned > 100, "{scanned}");
    }
}
