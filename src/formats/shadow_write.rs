//! Writing baked shadow-caster masks back into `.chunk` files (docs/contract.md §5).
//!
//! The bake's only output the engine reads is a `<shadow>` element inside
//! each `<model>`/`<shell>`/`<speedtree>` and `<terrain>` of a chunk. Chunk files are
//! hand-edited, version-controlled and full of data this tool does not
//! understand (entities, lights, navmesh references), so a text chunk is
//! edited surgically: only the `<shadow>` elements change, every other byte
//! stays where it was, and re-running the bake on its own output changes
//! nothing (so "a file whose content would not change is not rewritten" works
//! on the bytes). Packed binary XML is edited the same way in its own
//! layout: only the `<shadow>` elements are encoded anew, every other value
//! keeps its binary type and bytes (see [`write_shadows`]).
//!
//! What is written (`→` stands for a tab; values are tab-padded and lines
//! indented one tab per level of depth, as BigWorld's own writer does):
//!
//! ```text
//! →<model>
//! →→...
//! →→<shadow>→3
//! →→→<RenderSet>
//! →→→→<Geometry>
//! →→→→→<PrimitiveGroup>→2→</PrimitiveGroup>
//! →→→→→<PrimitiveGroup>→3→</PrimitiveGroup>
//! →→→→</Geometry>
//! →→→</RenderSet>
//! →→</shadow>
//! →</model>
//! →<terrain>
//! →→...
//! →→<shadow>→2→</shadow>
//! →</terrain>
//! ```
//!
//! A `<speedtree>` gets its proxy's render sets exactly as a model does
//! (docs/contract.md §5). An empty render set or geometry is written
//! `<RenderSet />` / `<Geometry />`, as BigWorld writes empty sections; an
//! instance without render sets gets the mask alone (`<shadow>\t0\t</shadow>`;
//! a speedtree without a proxy, every baked bit).

use super::chunk::{
    instance_elements, speedtree_elements, terrain_element, InstanceKind, SPEEDTREE_TAG,
};
use super::{packed_xml, xml, Section};
use crate::digest::{Digest, Digester};
use crate::error::FormatError;
use std::ops::Range;

/// Tag of the element the bake owns inside instances and terrain.
pub const SHADOW_TAG: &str = "shadow";
const RENDER_SET_TAG: &str = "RenderSet";
const GEOMETRY_TAG: &str = "Geometry";
const GROUP_TAG: &str = "PrimitiveGroup";

/// Masks of one instance: `mask` = OR of all group masks; `render_sets[r][g]`
/// = the group masks of geometry g of render set r, render sets concatenated
/// over the instance's `<resource>` parts in order (a speedtree's: its
/// proxy's). Without render sets `mask` stands alone.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct InstanceShadow {
    pub mask: u32,
    pub render_sets: Vec<Vec<Vec<u32>>>,
}

impl InstanceShadow {
    /// Builds the masks of an instance from its group masks, with `mask` as
    /// their OR.
    pub fn from_groups(render_sets: Vec<Vec<Vec<u32>>>) -> Self {
        let mask = render_sets.iter().flatten().flatten().fold(0, |a, m| a | m);
        InstanceShadow { mask, render_sets }
    }

    /// Every bit it holds: its mask and its group masks ORed.
    pub fn bits(&self) -> u32 {
        self.groups().fold(self.mask, |a, m| a | m)
    }

    /// The group masks in output order (render set, geometry, group), as the
    /// report's `groups` lists them.
    pub fn groups(&self) -> impl Iterator<Item = u32> + '_ {
        self.render_sets.iter().flatten().flatten().copied()
    }
}

/// What to write into one chunk.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ChunkShadows {
    /// One entry per instance element (by its index among the chunk's
    /// `<model>`/`<shell>` elements): the masks to write, or `None` to leave
    /// that element exactly as it is (e.g. its model could not be loaded).
    pub instances: Vec<Option<InstanceShadow>>,
    /// The same for each `<speedtree>` element, by its index among the
    /// chunk's `<speedtree>` elements.
    pub speedtrees: Vec<Option<InstanceShadow>>,
    /// The terrain block's mask, if the chunk's terrain was baked; `None`
    /// leaves `<terrain>` exactly as it is.
    pub terrain: Option<u32>,
}

/// Returns the new content of a chunk file with `shadows` written in.
///
/// **Text XML.** Only `<shadow>` elements that are direct children of the
/// chunk's instance and speedtree elements and of its `<terrain>` are
/// touched:
/// - an existing `<shadow>` is replaced in place, wherever it is among the
///   element's children; further direct `<shadow>` children (an element has
///   one; a hand edit or a merge may leave more) are removed, together with
///   their line when they stand alone on it, so the engine cannot read a
///   stale one;
/// - otherwise the new `<shadow>` is inserted just before the element's
///   closing tag, on its own line, indented one tab deeper than the element's
///   depth; if the closing tag shares its line with other content
///   (`<model><resource>a</resource></model>`), a line break and the closing
///   tag's indentation are added around the new element;
/// - a self-closing element (`<model ... />`, `<terrain/>`) is expanded into
///   start tag, `<shadow>` and end tag.
///
/// Every other byte is kept as it was (comments, white space, entities,
/// a byte order mark, text after the root). New line breaks follow the
/// file's first line break (`\n` or `\r\n`). A `<shadow>` nested deeper (for
/// example inside `<editorOnly>`) is not the bake's and is left alone. The
/// output depends only on the bytes outside the direct `<shadow>` children
/// and on `shadows`, so writing the same masks into the output again gives
/// identical bytes.
///
/// **Packed binary XML** (magic `45 4E A1 62`): the file is read as a
/// [`packed_xml::Document`], which holds every value's type code and bytes
/// as stored. Each target element's direct `<shadow>` children are replaced
/// by the new one (at the position of the first, else appended last),
/// encoded as the engine's `res_packer` packs that text (masks as ints of
/// the fewest bytes); an element stored as a bare value becomes an element
/// keeping that value. Every other value keeps its type and bytes (a float
/// holding 250.0 stays a 4-byte float, an int its width, a blob or
/// encrypted blob its bytes, a matrix its 12 floats), children keep their
/// order, and the string table keeps its entries and order, tags it lacks
/// (`shadow`, `RenderSet`, `Geometry`, `PrimitiveGroup`) appended at its
/// end; only the headers of the edited elements and of the root change
/// with their lengths. Re-running with the same masks gives the same bytes.
///
/// Errors (with the element and byte offset): the file does not parse;
/// `shadows.instances` (`shadows.speedtrees`) does not have one entry per
/// instance (speedtree) element (the chunk changed since it was read); an
/// instance's `mask` is not the OR of its group masks while it has some; a
/// terrain mask for a chunk without `<terrain>`.
pub fn write_shadows(original: &[u8], shadows: &ChunkShadows) -> Result<Vec<u8>, FormatError> {
    if original.starts_with(&packed_xml::MAGIC) {
        write_packed(original, shadows)
    } else {
        write_text(original, shadows)
    }
}

/// [`write_shadows`] for a caller that has parsed `original` already
/// (`root`): text XML is not parsed again before its edits. With the
/// bytes, the places of the `<shadow>`s in them ([`ShadowSites`], text
/// XML only).
pub fn write_shadows_parsed(
    original: &[u8],
    root: &Section,
    shadows: &ChunkShadows,
) -> Result<(Vec<u8>, Option<ShadowSites>), FormatError> {
    if original.starts_with(&packed_xml::MAGIC) {
        return Ok((write_packed(original, shadows)?, None));
    }
    targets(root, shadows)?;
    let (out, sites) = ShadowSites::find(original, root)?.write(original, shadows)?;
    verify(&out, shadows)?;
    Ok((out, Some(sites)))
}

/// The chunk's bytes with every `<shadow>` the bake writes set to 0: what
/// a bake's answer depends on (it ignores old masks), so a fingerprint of
/// these bytes (`bake::shard`) stays the same when a bake or a merge
/// writes its masks into the chunk. `root` is `original` already parsed
/// (loading has it): text XML is edited from it without parsing again, and
/// the result is only hashed, never written, so it is not read back.
pub fn without_masks(
    original: &[u8],
    root: &Section,
    chunk: &super::chunk::ChunkFile,
) -> Result<Vec<u8>, FormatError> {
    let shadows = zero_masks(chunk);
    if original.starts_with(&packed_xml::MAGIC) {
        write_packed(original, &shadows)
    } else {
        edit_text(original, root, &shadows)
    }
}

/// The [`Digest`] of [`without_masks`] of a text chunk, from the places of
/// its `<shadow>`s (`sites`, found in `original`), without its tree and
/// without making the bytes.
pub fn digest_without_masks_at(
    original: &[u8],
    sites: &ShadowSites,
    chunk: &super::chunk::ChunkFile,
) -> Result<Digest, FormatError> {
    sites.digest(original, &zero_masks(chunk))
}

/// Every `<shadow>` the bake writes into `chunk`, with every mask 0.
fn zero_masks(chunk: &super::chunk::ChunkFile) -> ChunkShadows {
    ChunkShadows {
        instances: vec![Some(InstanceShadow::default()); chunk.instances.len()],
        speedtrees: vec![Some(InstanceShadow::default()); chunk.speedtrees.len()],
        terrain: chunk.terrain.as_ref().map(|_| 0),
    }
}

/// Reads back the direct `<shadow>` of an instance element: `None` when it
/// has none. Only the first direct `<shadow>` counts, as the engine reads it.
pub fn read_instance_shadow(element: &Section) -> Result<Option<InstanceShadow>, FormatError> {
    let Some(shadow) = element.child(SHADOW_TAG) else {
        return Ok(None);
    };
    let mask = mask_value(shadow)?;
    let mut render_sets = Vec::new();
    for render_set in shadow.children_named(RENDER_SET_TAG) {
        let mut geometries = Vec::new();
        for geometry in render_set.children_named(GEOMETRY_TAG) {
            let groups = geometry
                .children_named(GROUP_TAG)
                .map(mask_value)
                .collect::<Result<Vec<_>, _>>()?;
            geometries.push(groups);
        }
        render_sets.push(geometries);
    }
    Ok(Some(InstanceShadow { mask, render_sets }))
}

/// Reads back every `<shadow>` the bake writes into a chunk: what
/// [`write_shadows`] was given, for the elements it wrote.
pub fn read_chunk_shadows(root: &Section) -> Result<ChunkShadows, FormatError> {
    let instances = instance_elements(root)
        .map(|(_, element)| read_instance_shadow(element))
        .collect::<Result<Vec<_>, _>>()?;
    let speedtrees = speedtree_elements(root)
        .map(read_instance_shadow)
        .collect::<Result<Vec<_>, _>>()?;
    let terrain = match terrain_element(root).and_then(|t| t.child(SHADOW_TAG)) {
        Some(shadow) => Some(mask_value(shadow)?),
        None => None,
    };
    Ok(ChunkShadows {
        instances,
        speedtrees,
        terrain,
    })
}

fn mask_value(section: &Section) -> Result<u32, FormatError> {
    mask_of(&section.value).ok_or_else(|| {
        section.error(format!(
            "expected a 32-bit shadow mask (0..=4294967295), found `{}`",
            section.value
        ))
    })
}

/// A mask value's number.
pub(super) fn mask_of(value: &str) -> Option<u32> {
    value.trim().parse::<u32>().ok()
}

/// The elements to write into, as positions among the root's children,
/// each with its masks, after checking that `shadows` fits the chunk.
fn targets<'a>(
    root: &Section,
    shadows: &'a ChunkShadows,
) -> Result<Vec<(usize, Masks<'a>)>, FormatError> {
    let positions = |is_target: fn(&str) -> bool| -> Vec<usize> {
        (0..root.children.len())
            .filter(|&i| is_target(&root.children[i].name))
            .collect()
    };
    let models = |tag: &str| InstanceKind::from_tag(tag).is_some_and(InstanceKind::names_models);
    let mut out = Vec::new();
    for (positions, wanted, what) in [
        (positions(models), &shadows.instances, "<model>/<shell>"),
        (
            positions(|tag| tag == SPEEDTREE_TAG),
            &shadows.speedtrees,
            "<speedtree>",
        ),
    ] {
        if positions.len() != wanted.len() {
            return Err(root.error(format!(
                "masks were given for {} instances but the chunk has {} {what} elements; \
                 the file changed since it was read: bake again",
                wanted.len(),
                positions.len(),
            )));
        }
        for (position, shadow) in positions.into_iter().zip(wanted) {
            let Some(shadow) = shadow else { continue };
            let or = shadow.groups().fold(0, |a, m| a | m);
            if !shadow.render_sets.is_empty() && or != shadow.mask {
                return Err(root.children[position].error(format!(
                    "instance mask {} is not the OR of its group masks ({or}); \
                     this is a bug in the caller of the shadow writer",
                    shadow.mask
                )));
            }
            out.push((position, Masks::Instance(shadow)));
        }
    }
    if let Some(mask) = shadows.terrain {
        let terrain = root
            .children
            .iter()
            .position(|c| c.name == "terrain")
            .ok_or_else(|| {
                root.error("a terrain mask was given but the chunk has no <terrain> element")
            })?;
        out.push((terrain, Masks::Terrain(mask)));
    }
    Ok(out)
}

#[derive(Clone, Copy)]
enum Masks<'a> {
    Instance(&'a InstanceShadow),
    Terrain(u32),
}

impl Masks<'_> {
    fn bits(self) -> u32 {
        match self {
            Masks::Instance(shadow) => shadow.bits(),
            Masks::Terrain(mask) => mask,
        }
    }
}

fn write_text(original: &[u8], shadows: &ChunkShadows) -> Result<Vec<u8>, FormatError> {
    let (out, _) = write_shadows_parsed(original, &xml::parse(original)?, shadows)?;
    Ok(out)
}

/// `original` with `shadows` put in (see [`write_shadows`]); `root` is
/// `original` parsed.
fn edit_text(
    original: &[u8],
    root: &Section,
    shadows: &ChunkShadows,
) -> Result<Vec<u8>, FormatError> {
    // Checked on the tree first, so errors name the element.
    targets(root, shadows)?;
    let (out, _) = ShadowSites::find(original, root)?.write(original, shadows)?;
    Ok(out)
}

/// Where the `<shadow>`s of a text chunk go: for every element the bake
/// writes into, the place [`write_shadows`] puts its `<shadow>`. Found
/// once from the parsed file, they let the same bytes take their masks
/// later without being parsed again (a large world's chunks are most of
/// its output's time), and a write gives the places in its new bytes.
/// Offsets are bytes into the file the places were found in (a chunk
/// file is capped far below 4 GiB).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ShadowSites {
    /// Tabs before the target elements' tags: their depth in the tree.
    pub depth: u8,
    /// One per `<model>`/`<shell>` element, in file order.
    pub instances: Vec<Site>,
    /// One per `<speedtree>` element, in file order.
    pub speedtrees: Vec<Site>,
    /// The first `<terrain>` element's.
    pub terrain: Option<Site>,
    /// Further direct `<shadow>` children, removed when their element is
    /// written: (the element, by its place in the order instances,
    /// speedtrees, terrain; the bytes, with their line when alone on it).
    pub extras: Vec<(u32, Range<u32>)>,
}

/// Where one element's `<shadow>` goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Site {
    pub place: Place,
    pub start: u32,
    /// Equal to `start` for an insertion.
    pub end: u32,
    /// Every bit the element's `<shadow>` holds now (its mask and group
    /// masks ORed; 0 without one), `None` when a value there is not a
    /// mask: what a bake that keeps other lights' bits must know.
    pub held: Option<u32>,
}

/// How a `<shadow>` is put into its element (see [`write_shadows`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// Replaces the element's first direct `<shadow>` (`start..end`).
    Replace,
    /// Expands the self-closing element (`start..end`, its tag).
    Expand,
    /// On a line of its own inserted at `start`, the start of the line
    /// that holds only the closing tag's indentation and the tag.
    OwnLine,
    /// Inserted at `start`, the closing tag, which shares its line.
    BeforeClose,
}

impl Place {
    pub const ALL: [Place; 4] = [
        Place::Replace,
        Place::Expand,
        Place::OwnLine,
        Place::BeforeClose,
    ];
}

impl ShadowSites {
    /// The places in `original` (text XML), `root` being it parsed.
    pub fn find(original: &[u8], root: &Section) -> Result<ShadowSites, FormatError> {
        let models =
            |tag: &str| InstanceKind::from_tag(tag).is_some_and(InstanceKind::names_models);
        let of = |is_target: &dyn Fn(&str) -> bool| -> Vec<&Section> {
            root.children
                .iter()
                .filter(|c| is_target(&c.name))
                .collect()
        };
        let instances = of(&models);
        let speedtrees = of(&|tag| tag == SPEEDTREE_TAG);
        let terrain = root.children.iter().find(|c| c.name == "terrain");
        let mut extras = Vec::new();
        let mut target = 0u32;
        let mut site_of = |element: &Section| -> Result<Site, FormatError> {
            let (place, span) = element_site(original, element)?;
            let held = match read_instance_shadow(element) {
                Ok(shadow) => Some(shadow.as_ref().map_or(0, InstanceShadow::bits)),
                Err(_) => None,
            };
            if place == Place::Replace {
                for extra in element.children_named(SHADOW_TAG).skip(1) {
                    let line = whole_line(original, extra.span.clone());
                    extras.push((target, offset(line.start)?..offset(line.end)?));
                }
            }
            target += 1;
            Ok(Site {
                place,
                start: offset(span.start)?,
                end: offset(span.end)?,
                held,
            })
        };
        let instances = instances
            .into_iter()
            .map(&mut site_of)
            .collect::<Result<_, _>>()?;
        let speedtrees = speedtrees
            .into_iter()
            .map(&mut site_of)
            .collect::<Result<_, _>>()?;
        let terrain = terrain.map(&mut site_of).transpose()?;
        // Targets are the root's children: one depth for all.
        let depth = root.path.matches('/').count() + 1;
        Ok(ShadowSites {
            depth: u8::try_from(depth)
                .map_err(|_| root.error("chunk elements nested too deep for a <shadow>"))?,
            instances,
            speedtrees,
            terrain,
            extras,
        })
    }

    /// Every bit the targets' `<shadow>`s hold now, `None` when one holds
    /// a value that is not a mask.
    pub fn held(&self) -> Option<u32> {
        let sites = self
            .instances
            .iter()
            .chain(&self.speedtrees)
            .chain(&self.terrain);
        sites
            .map(|site| site.held)
            .try_fold(0, |all, held| Some(all | held?))
    }

    /// `original` (the bytes the places were found in) with `shadows`
    /// put in, and the places in the new bytes. Errors as
    /// [`write_shadows`]'s when `shadows` does not fit the chunk, and when
    /// a place does not hold what it held when found (the bytes are not
    /// the ones parsed): nothing is written then.
    pub fn write(
        &self,
        original: &[u8],
        shadows: &ChunkShadows,
    ) -> Result<(Vec<u8>, ShadowSites), FormatError> {
        let mut edits = self.edits(original, shadows)?;
        let out = splice(original, &mut edits)?;
        Ok((out, self.moved(&edits)))
    }

    /// The [`Digest`] of the bytes [`ShadowSites::write`] would make, made
    /// as they are spliced rather than after (loading hashes every chunk
    /// with its masks zeroed). Errors as `write`'s.
    pub fn digest(&self, original: &[u8], shadows: &ChunkShadows) -> Result<Digest, FormatError> {
        let mut digester = Digester::new();
        let mut pos = 0;
        for edit in &self.edits(original, shadows)? {
            digester.update(kept_before(original, pos, edit)?);
            digester.update(&edit.text);
            pos = edit.range.end;
        }
        digester.update(original.get(pos..).unwrap_or(&[]));
        Ok(digester.finish())
    }

    /// The edits that put `shadows` into `original`, in byte order.
    fn edits(&self, original: &[u8], shadows: &ChunkShadows) -> Result<Vec<Edit>, FormatError> {
        let eol = line_ending(original);
        let depth = usize::from(self.depth);
        let written = self.targets(shadows)?;
        let mut edits: Vec<Edit> = Vec::new();
        for (target, site, masks) in &written {
            let at = checked_span(original, site)?;
            let new = Written {
                target: *target,
                at: 0..0,
                held: masks.bits(),
            };
            edits.push(site_edit(
                original,
                at,
                site.place,
                (depth, eol),
                new,
                *masks,
            ));
            for (_, extra) in self.extras.iter().filter(|(t, _)| t == target) {
                let range = extra.start as usize..extra.end as usize;
                let holds_a_shadow = original
                    .get(range.clone())
                    .is_some_and(|b| find_last(b, b"<shadow").is_some());
                if !holds_a_shadow {
                    return Err(not_the_bytes(range.start));
                }
                edits.push(Edit {
                    range,
                    text: Vec::new(),
                    shadow: None,
                });
            }
        }
        edits.sort_by_key(|e| (e.range.start, e.range.end));
        Ok(edits)
    }

    /// Each target with masks to write: its place in the order instances,
    /// speedtrees, terrain, its site and its masks; an error when
    /// `shadows` does not fit the chunk.
    fn targets<'s>(
        &self,
        shadows: &'s ChunkShadows,
    ) -> Result<Vec<(u32, Site, Masks<'s>)>, FormatError> {
        let mut out = Vec::new();
        let mut target = 0u32;
        for (sites, wanted, what) in [
            (&self.instances, &shadows.instances, "<model>/<shell>"),
            (&self.speedtrees, &shadows.speedtrees, "<speedtree>"),
        ] {
            if sites.len() != wanted.len() {
                return Err(FormatError::whole_file(format!(
                    "masks were given for {} instances but the chunk has {} {what} elements; \
                     the file changed since it was read: bake again",
                    wanted.len(),
                    sites.len(),
                )));
            }
            for (site, shadow) in sites.iter().zip(wanted) {
                if let Some(shadow) = shadow {
                    let or = shadow.groups().fold(0, |a, m| a | m);
                    if !shadow.render_sets.is_empty() && or != shadow.mask {
                        return Err(FormatError::at_byte(
                            site.start as usize,
                            format!(
                                "instance mask {} is not the OR of its group masks ({or}); \
                                 this is a bug in the caller of the shadow writer",
                                shadow.mask
                            ),
                        ));
                    }
                    out.push((target, *site, Masks::Instance(shadow)));
                }
                target += 1;
            }
        }
        if let Some(mask) = shadows.terrain {
            let site = self.terrain.ok_or_else(|| {
                FormatError::whole_file(
                    "a terrain mask was given but the chunk has no <terrain> element",
                )
            })?;
            out.push((target, site, Masks::Terrain(mask)));
        }
        Ok(out)
    }

    /// The places in the bytes `edits` made: a written target's is its new
    /// `<shadow>`, every other place moves with the bytes before it.
    fn moved(&self, edits: &[Edit]) -> ShadowSites {
        // Bytes gained (or lost) by the edits that end at or before each
        // position.
        let mut gained = Vec::with_capacity(edits.len());
        let mut total = 0i64;
        for edit in edits {
            total += edit.text.len() as i64 - edit.range.len() as i64;
            gained.push((edit.range.end, total));
        }
        let shift = |at: u32| {
            let before = gained.partition_point(|(end, _)| *end <= at as usize);
            let by = before.checked_sub(1).map_or(0, |i| gained[i].1);
            (i64::from(at) + by) as u32
        };
        let mut shadows: Vec<&Written> = edits.iter().filter_map(|e| e.shadow.as_ref()).collect();
        shadows.sort_unstable_by_key(|w| w.target);
        let written = |target: u32| {
            let at = shadows.binary_search_by_key(&target, |w| w.target).ok()?;
            Some(shadows[at])
        };
        let mut target = 0u32;
        let mut place = |site: &Site| {
            let new = match written(target) {
                Some(w) => Site {
                    place: Place::Replace,
                    start: w.at.start as u32,
                    end: w.at.end as u32,
                    held: Some(w.held),
                },
                None => Site {
                    place: site.place,
                    start: shift(site.start),
                    end: shift(site.end),
                    held: site.held,
                },
            };
            target += 1;
            new
        };
        ShadowSites {
            depth: self.depth,
            instances: self.instances.iter().map(&mut place).collect(),
            speedtrees: self.speedtrees.iter().map(&mut place).collect(),
            terrain: self.terrain.as_ref().map(&mut place),
            extras: self
                .extras
                .iter()
                .filter(|(t, _)| written(*t).is_none())
                .map(|(t, r)| (*t, shift(r.start)..shift(r.end)))
                .collect(),
        }
    }
}

/// A byte offset into a chunk file as a place holds it.
pub(super) fn offset(at: usize) -> Result<u32, FormatError> {
    u32::try_from(at).map_err(|_| FormatError::at_byte(at, "chunk file larger than 4 GiB"))
}

/// One change to a chunk's bytes: `range` replaced by `text`, and the
/// `<shadow>` it writes, if any.
struct Edit {
    range: Range<usize>,
    text: Vec<u8>,
    shadow: Option<Written>,
}

/// A `<shadow>` an edit writes: its target (in the order instances,
/// speedtrees, terrain), where in the edit's text it lies (once spliced:
/// in the output), the bits it holds.
struct Written {
    target: u32,
    at: Range<usize>,
    held: u32,
}

/// Where an element's `<shadow>` goes in `original`, and the span its
/// [`Place`] names.
fn element_site(original: &[u8], element: &Section) -> Result<(Place, Range<usize>), FormatError> {
    if let Some(first) = element.children_named(SHADOW_TAG).next() {
        return Ok((Place::Replace, first.span.clone()));
    }
    let span = element.span.clone();
    let text = original
        .get(span.clone())
        .ok_or_else(|| element.error("internal error: element span outside the file"))?;
    let close = find_last(text, b"</").map(|i| span.start + i);
    if !text.ends_with(b"/>") && close.is_none() {
        return Err(element.error("internal error: element without an end tag"));
    }
    Ok(place_without_shadow(original, span, close.unwrap_or(0)))
}

/// Where the `<shadow>` of an element without one goes: the element spans
/// `span` of `original`, its end tag starts at `close` (unless it is
/// self-closing).
pub(super) fn place_without_shadow(
    original: &[u8],
    span: Range<usize>,
    close: usize,
) -> (Place, Range<usize>) {
    if original
        .get(span.clone())
        .is_some_and(|text| text.ends_with(b"/>"))
    {
        return (Place::Expand, span);
    }
    let line_start = original
        .get(..close)
        .and_then(|before| before.iter().rposition(|&b| b == b'\n'))
        .map_or(0, |i| i + 1);
    let alone = line_start > span.start
        && original
            .get(line_start..close)
            .is_some_and(|prefix| prefix.iter().all(|&b| b == b' ' || b == b'\t'));
    match alone {
        true => (Place::OwnLine, line_start..line_start),
        false => (Place::BeforeClose, close..close),
    }
}

/// The span `site` names in `original`, when the bytes there are what
/// its place was found at (a cheap check that these are the bytes the
/// places were found in).
fn checked_span(original: &[u8], site: &Site) -> Result<Range<usize>, FormatError> {
    let span = site.start as usize..site.end as usize;
    let blank = |b: &u8| *b == b' ' || *b == b'\t';
    let (Some(text), Some(after)) = (original.get(span.clone()), original.get(span.start..)) else {
        return Err(not_the_bytes(span.start));
    };
    let fits = match site.place {
        Place::Replace => text.starts_with(b"<shadow") && text.ends_with(b">"),
        Place::Expand => text.starts_with(b"<") && text.ends_with(b"/>"),
        Place::OwnLine => {
            let at_line_start = span.start == 0 || original[span.start - 1] == b'\n';
            let indent = after.iter().take_while(|b| blank(b)).count();
            at_line_start && after[indent..].starts_with(b"</")
        }
        Place::BeforeClose => after.starts_with(b"</"),
    };
    match fits {
        true => Ok(span),
        false => Err(not_the_bytes(span.start)),
    }
}

fn not_the_bytes(at: usize) -> FormatError {
    FormatError::at_byte(
        at,
        "internal error: the chunk's bytes are not those its <shadow> places were found in; \
         the file was not changed",
    )
}

/// The edit that puts the `<shadow>` of `masks` at `span` of `original`
/// as `place` says; elements sit `depth` tabs deep. Written straight into
/// the edit's bytes: a big world's output makes millions of them.
fn site_edit(
    original: &[u8],
    span: Range<usize>,
    place: Place,
    (depth, eol): (usize, &str),
    mut written: Written,
    masks: Masks,
) -> Edit {
    let mut text = Vec::with_capacity(64);
    let mut after: &[u8] = &[];
    let mut name: &[u8] = &[];
    match place {
        Place::Replace => {}
        Place::Expand => {
            // The start tag's bytes are kept as they are (attributes need
            // not be UTF-8); only `/>` becomes `>`.
            let tag = &original[span.clone()];
            let head = tag[..tag.len() - 2].trim_ascii_end();
            let name_end = head[1..]
                .iter()
                .position(|&b| b.is_ascii_whitespace() || b == b'>')
                .map_or(head.len(), |i| i + 1);
            text.extend_from_slice(head);
            text.push(b'>');
            text.extend_from_slice(eol.as_bytes());
            push_tabs(&mut text, depth + 1);
            name = &head[1..name_end];
        }
        Place::OwnLine => {
            push_tabs(&mut text, depth + 1);
            after = eol.as_bytes();
        }
        Place::BeforeClose => {
            text.extend_from_slice(eol.as_bytes());
            push_tabs(&mut text, depth + 1);
        }
    }
    let at = text.len();
    shadow_text(&mut text, masks, depth + 1, eol);
    written.at = at..text.len();
    match place {
        Place::Expand => {
            text.extend_from_slice(eol.as_bytes());
            push_tabs(&mut text, depth);
            text.extend_from_slice(b"</");
            text.extend_from_slice(name);
            text.push(b'>');
        }
        Place::BeforeClose => {
            text.extend_from_slice(eol.as_bytes());
            push_tabs(&mut text, depth);
        }
        Place::Replace | Place::OwnLine => text.extend_from_slice(after),
    }
    Edit {
        range: span,
        text,
        shadow: Some(written),
    }
}

/// `n` tabs.
fn push_tabs(out: &mut Vec<u8>, n: usize) {
    out.resize(out.len() + n, b'\t');
}

/// `v` in decimal, as `{v}` formats it.
fn push_decimal(out: &mut Vec<u8>, mut v: u32) {
    let mut digits = [0u8; 10];
    let mut at = digits.len();
    loop {
        at -= 1;
        digits[at] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    out.extend_from_slice(&digits[at..]);
}

/// `original` with `edits` (sorted, never overlapping) made; each edit's
/// `shadow` becomes where its `<shadow>` lies in the output.
fn splice(original: &[u8], edits: &mut [Edit]) -> Result<Vec<u8>, FormatError> {
    let grown: usize = edits.iter().map(|e| e.text.len()).sum();
    let mut out = Vec::with_capacity(original.len() + grown);
    let mut pos = 0;
    for edit in edits.iter_mut() {
        out.extend_from_slice(kept_before(original, pos, edit)?);
        let at = out.len();
        out.extend_from_slice(&edit.text);
        if let Some(shadow) = &mut edit.shadow {
            shadow.at = at + shadow.at.start..at + shadow.at.end;
        }
        pos = edit.range.end;
    }
    out.extend_from_slice(original.get(pos..).unwrap_or(&[]));
    Ok(out)
}

/// The bytes of `original` from `pos` to where `edit` begins.
fn kept_before<'o>(original: &'o [u8], pos: usize, edit: &Edit) -> Result<&'o [u8], FormatError> {
    // None only if two edits overlap, which the element tree rules out;
    // refuse rather than write a damaged file.
    original.get(pos..edit.range.start).ok_or_else(|| {
        FormatError::at_byte(
            edit.range.start,
            "internal error: overlapping <shadow> edits; the file was not changed",
        )
    })
}

/// Reads the output back before anyone writes it to disk: a file this module
/// produced must parse and hold exactly the masks it was given.
fn verify(out: &[u8], shadows: &ChunkShadows) -> Result<(), FormatError> {
    let internal = |what: String| {
        FormatError::whole_file(format!(
            "internal error: the rewritten chunk {what}; the file was not changed"
        ))
    };
    let root =
        super::parse_data_section(out).map_err(|e| internal(format!("does not parse ({e})")))?;
    let back =
        read_chunk_shadows(&root).map_err(|e| internal(format!("does not read back ({e})")))?;
    for (kind, wanted, read) in [
        ("instance", &shadows.instances, &back.instances),
        ("speedtree", &shadows.speedtrees, &back.speedtrees),
    ] {
        if read.len() != wanted.len() {
            return Err(internal(format!("has a different number of {kind}s")));
        }
        for (i, (want, got)) in wanted.iter().zip(read).enumerate() {
            if want.is_some() && want != got {
                return Err(internal(format!("reads back other masks for {kind} {i}")));
            }
        }
    }
    if shadows.terrain.is_some() && shadows.terrain != back.terrain {
        return Err(internal("reads back another terrain mask".into()));
    }
    Ok(())
}

/// `span` widened to its whole line, line break included, when nothing but
/// spaces and tabs share the line with it; else `span` itself.
pub(super) fn whole_line(text: &[u8], span: Range<usize>) -> Range<usize> {
    let blank = |b: &u8| *b == b' ' || *b == b'\t';
    let Some(before) = text.get(..span.start) else {
        return span;
    };
    let start = before
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(0, |i| i + 1);
    if !before.get(start..).is_some_and(|p| p.iter().all(blank)) {
        return span;
    }
    let Some(after) = text.get(span.end..) else {
        return span;
    };
    let spaces = after.iter().take_while(|b| blank(b)).count();
    let rest = after.get(spaces..).unwrap_or_default();
    let end = if rest.starts_with(b"\r\n") {
        span.end + spaces + 2
    } else if rest.starts_with(b"\n") {
        span.end + spaces + 1
    } else {
        return span;
    };
    start..end
}

fn find_last(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).rposition(|w| w == needle)
}

/// The file's own line break: that of its first line, `\n` if it has none.
fn line_ending(text: &[u8]) -> &'static str {
    match text.iter().position(|&b| b == b'\n') {
        Some(i) if i > 0 && text.get(i - 1) == Some(&b'\r') => "\r\n",
        _ => "\n",
    }
}

/// The `<shadow>` element's text, appended to `out`; `depth` is its own
/// depth (its tag is preceded by `depth` tabs, written by the caller),
/// inner lines go deeper.
fn shadow_text(out: &mut Vec<u8>, masks: Masks, depth: usize, eol: &str) {
    let shadow = match masks {
        Masks::Terrain(mask) => return value_element(out, SHADOW_TAG, mask),
        Masks::Instance(shadow) if shadow.render_sets.is_empty() => {
            return value_element(out, SHADOW_TAG, shadow.mask)
        }
        Masks::Instance(shadow) => shadow,
    };
    let eol = eol.as_bytes();
    let line = |out: &mut Vec<u8>, tabs: usize, tag: Tag| {
        push_tabs(out, tabs);
        tag.push(out);
        out.extend_from_slice(eol);
    };
    Tag::Open(SHADOW_TAG).push(out);
    out.push(b'\t');
    push_decimal(out, shadow.mask);
    out.extend_from_slice(eol);
    for render_set in &shadow.render_sets {
        if render_set.is_empty() {
            line(out, depth + 1, Tag::Empty(RENDER_SET_TAG));
            continue;
        }
        line(out, depth + 1, Tag::Open(RENDER_SET_TAG));
        for geometry in render_set {
            if geometry.is_empty() {
                line(out, depth + 2, Tag::Empty(GEOMETRY_TAG));
                continue;
            }
            line(out, depth + 2, Tag::Open(GEOMETRY_TAG));
            for &mask in geometry {
                push_tabs(out, depth + 3);
                value_element(out, GROUP_TAG, mask);
                out.extend_from_slice(eol);
            }
            line(out, depth + 2, Tag::Close(GEOMETRY_TAG));
        }
        line(out, depth + 1, Tag::Close(RENDER_SET_TAG));
    }
    push_tabs(out, depth);
    Tag::Close(SHADOW_TAG).push(out);
}

/// A start, end or empty-element tag.
#[derive(Clone, Copy)]
enum Tag<'a> {
    Open(&'a str),
    Close(&'a str),
    Empty(&'a str),
}

impl Tag<'_> {
    fn push(self, out: &mut Vec<u8>) {
        let (head, name, tail): (&[u8], &str, &[u8]) = match self {
            Tag::Open(name) => (b"<", name, b">"),
            Tag::Close(name) => (b"</", name, b">"),
            Tag::Empty(name) => (b"<", name, b" />"),
        };
        out.extend_from_slice(head);
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(tail);
    }
}

/// `<name>\tvalue\t</name>`.
fn value_element(out: &mut Vec<u8>, name: &str, value: u32) {
    Tag::Open(name).push(out);
    out.push(b'\t');
    push_decimal(out, value);
    out.push(b'\t');
    Tag::Close(name).push(out);
}

fn write_packed(original: &[u8], shadows: &ChunkShadows) -> Result<Vec<u8>, FormatError> {
    let mut document = packed_xml::Document::parse(original)?;
    let root = document.to_section()?;
    // Checked on the unedited tree, so errors point at the original elements.
    for (position, masks) in targets(&root, shadows)? {
        let element = &root.children[position];
        let shadow = shadow_section(masks, &element.path);
        document.set_child(&[position], &shadow, element)?;
    }
    let out = document.to_bytes()?;
    verify(&out, shadows)?;
    Ok(out)
}

fn shadow_section(masks: Masks, parent_path: &str) -> Section {
    fn node(name: &str, value: String, parent: &str, children: Vec<Section>) -> Section {
        Section {
            name: name.into(),
            value,
            path: format!("{parent}/{name}"),
            children,
            span: 0..0,
        }
    }
    let path = format!("{parent_path}/{SHADOW_TAG}");
    match masks {
        Masks::Terrain(mask) => node(SHADOW_TAG, mask.to_string(), parent_path, Vec::new()),
        Masks::Instance(shadow) => {
            let rs_path = format!("{path}/{RENDER_SET_TAG}");
            let g_path = format!("{rs_path}/{GEOMETRY_TAG}");
            let render_sets = shadow
                .render_sets
                .iter()
                .map(|render_set| {
                    let geometries = render_set
                        .iter()
                        .map(|groups| {
                            let groups = groups
                                .iter()
                                .map(|m| node(GROUP_TAG, m.to_string(), &g_path, Vec::new()))
                                .collect();
                            node(GEOMETRY_TAG, String::new(), &rs_path, groups)
                        })
                        .collect();
                    node(RENDER_SET_TAG, String::new(), &path, geometries)
                })
                .collect();
            node(
                SHADOW_TAG,
                shadow.mask.to_string(),
                parent_path,
                render_sets,
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn one(mask_groups: &[&[u32]]) -> InstanceShadow {
        InstanceShadow::from_groups(vec![mask_groups.iter().map(|g| g.to_vec()).collect()])
    }

    fn write_str(text: &str, shadows: &ChunkShadows) -> String {
        let out = write_shadows(text.as_bytes(), shadows).unwrap();
        String::from_utf8(out).unwrap()
    }

    /// The text with every direct `<shadow>` of instances and terrain cut
    /// out, with its line when it stands alone on one: what must be equal
    /// before and after a write.
    fn strip_shadows(text: &[u8]) -> Vec<u8> {
        let root = xml::parse(text).unwrap();
        let mut cuts: Vec<Range<usize>> = instance_elements(&root)
            .map(|(_, e)| e)
            .chain(speedtree_elements(&root))
            .chain(terrain_element(&root))
            .flat_map(|e| e.children_named(SHADOW_TAG))
            .map(|s| whole_line(text, s.span.clone()))
            .collect();
        cuts.sort_by_key(|r| r.start);
        let mut out = Vec::new();
        let mut pos = 0;
        for cut in cuts {
            assert!(cut.start >= pos, "overlapping cuts");
            out.extend_from_slice(&text[pos..cut.start]);
            pos = cut.end;
        }
        out.extend_from_slice(&text[pos..]);
        out
    }

    const BASIC: &str = "<root>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n\t<terrain>\n\t\t<resource>\tx.cdata/terrain2\t</resource>\n\t</terrain>\n</root>\n";

    #[test]
    fn decimals_are_what_display_writes() {
        let mut rng = crate::rng::Rng::new(5);
        let edges = [
            0,
            1,
            9,
            10,
            99,
            100,
            65_535,
            999_999_999,
            1_000_000_000,
            u32::MAX,
        ];
        let random = (0..2000).map(|_| rng.next_u64() as u32 >> (rng.next_u64() % 32));
        for v in edges.into_iter().chain(random) {
            let mut out = b"x".to_vec();
            push_decimal(&mut out, v);
            assert_eq!(out, format!("x{v}").into_bytes());
        }
    }

    #[test]
    fn writes_the_spec_layout() {
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[2, 3]]))],
            speedtrees: Vec::new(),
            terrain: Some(2),
        };
        assert_eq!(shadows.instances[0].as_ref().unwrap().mask, 3);
        let expected = "<root>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\
            \t\t<shadow>\t3\n\
            \t\t\t<RenderSet>\n\
            \t\t\t\t<Geometry>\n\
            \t\t\t\t\t<PrimitiveGroup>\t2\t</PrimitiveGroup>\n\
            \t\t\t\t\t<PrimitiveGroup>\t3\t</PrimitiveGroup>\n\
            \t\t\t\t</Geometry>\n\
            \t\t\t</RenderSet>\n\
            \t\t</shadow>\n\
            \t</model>\n\t<terrain>\n\t\t<resource>\tx.cdata/terrain2\t</resource>\n\
            \t\t<shadow>\t2\t</shadow>\n\
            \t</terrain>\n</root>\n";
        let out = write_str(BASIC, &shadows);
        assert_eq!(out, expected);
        assert_eq!(write_str(&out, &shadows), expected, "idempotent");
        assert_eq!(strip_shadows(out.as_bytes()), BASIC.as_bytes());
    }

    #[test]
    fn several_render_sets_and_geometries_in_order() {
        let shadow =
            InstanceShadow::from_groups(vec![vec![vec![1], vec![]], vec![], vec![vec![4, 0, 8]]]);
        assert_eq!(shadow.mask, 13);
        assert_eq!(shadow.groups().collect::<Vec<_>>(), [1, 4, 0, 8]);
        let shadows = ChunkShadows {
            instances: vec![Some(shadow.clone())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(BASIC, &shadows);
        assert!(out.contains(
            "\t\t<shadow>\t13\n\t\t\t<RenderSet>\n\t\t\t\t<Geometry>\n\
             \t\t\t\t\t<PrimitiveGroup>\t1\t</PrimitiveGroup>\n\t\t\t\t</Geometry>\n\
             \t\t\t\t<Geometry />\n\t\t\t</RenderSet>\n\t\t\t<RenderSet />\n"
        ));
        let root = xml::parse(out.as_bytes()).unwrap();
        let back = read_chunk_shadows(&root).unwrap();
        assert_eq!(back.instances, [Some(shadow)]);
        assert_eq!(back.terrain, None, "terrain untouched");
        assert!(out.ends_with(&BASIC[BASIC.find("\t<terrain>").unwrap()..]));
    }

    #[test]
    fn replaces_an_existing_last_child_in_place() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta\t</resource>\n\t\t<shadow>\t7\n\t\t\t<RenderSet>\n\t\t\t</RenderSet>\n\t\t</shadow>\n\t</model>\n</root>";
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[1]]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            "<root>\n\t<model>\n\t\t<resource>\ta\t</resource>\n\t\t<shadow>\t1\n\t\t\t<RenderSet>\n\t\t\t\t<Geometry>\n\t\t\t\t\t<PrimitiveGroup>\t1\t</PrimitiveGroup>\n\t\t\t\t</Geometry>\n\t\t\t</RenderSet>\n\t\t</shadow>\n\t</model>\n</root>"
        );
    }

    #[test]
    fn replaces_an_existing_middle_child_where_it_is() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta\t</resource>\n\t\t<shadow>\t7\t</shadow>\n\t\t<transform>\n\t\t</transform>\n\t</model>\n</root>";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert_eq!(out, text.replace("\t7\t", "\t0\t"));
    }

    #[test]
    fn extra_shadow_children_are_removed_with_their_lines() {
        let text = "<root>\n\t<model>\n\t\t<shadow>\t1\t</shadow>\n\t\t<resource>\ta\t</resource>\n\t\t<shadow>\t2\t</shadow>\n\t\t<castsShadow>\ttrue\t</castsShadow><shadow>\t3\t</shadow>\n\t</model>\n</root>";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::from_groups(vec![]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            "<root>\n\t<model>\n\t\t<shadow>\t0\t</shadow>\n\t\t<resource>\ta\t</resource>\n\t\t<castsShadow>\ttrue\t</castsShadow>\n\t</model>\n</root>"
        );
        assert_eq!(write_str(&out, &shadows), out);
        assert_eq!(
            strip_shadows(out.as_bytes()),
            strip_shadows(text.as_bytes())
        );
    }

    #[test]
    fn shadow_inside_editor_only_is_not_ours() {
        let text = "<root>\n\t<model>\n\t\t<editorOnly>\n\t\t\t<shadow>\t5\t</shadow>\n\t\t</editorOnly>\n\t\t<resource>\ta\t</resource>\n\t</model>\n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            text.replace("\t</model>", "\t\t<shadow>\t0\t</shadow>\n\t</model>")
        );
        let root = xml::parse(out.as_bytes()).unwrap();
        let model = &root.children[0];
        assert_eq!(
            model.child("editorOnly").unwrap().child_text("shadow"),
            Some("5")
        );
    }

    #[test]
    fn comments_and_odd_white_space_survive() {
        let text = "<root> <!-- <model><shadow>9</shadow></model> -->\n  <model>   <!-- keep -->\n      <resource>a</resource>  \n  <!-- <shadow> -->\n  </model>  \n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::from_groups(vec![vec![vec![6]]]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        // The closing tag stands alone on its line: the shadow goes on the
        // line before it, indented by depth (not by the file's spaces).
        let at = out.find("\t\t<shadow>\t6\n").unwrap();
        assert_eq!(&out[..at], &text[..text.find("  </model>").unwrap()]);
        assert!(out.ends_with("\t\t</shadow>\n  </model>  \n</root>\n"));
        assert_eq!(strip_shadows(out.as_bytes()), text.as_bytes());
        assert_eq!(write_str(&out, &shadows), out);
    }

    #[test]
    fn cdata_comments_and_odd_white_space_inside_a_model_survive() {
        let text = "<root>\n<!-- header -->\n   <model>  <!-- a <shadow> in a comment -->\n\t  <resource>\t<![CDATA[sets/a<b>.model]]>  </resource>\n  \t\t<shadow>\t7\t</shadow>   <!-- after -->\n<metaData><![CDATA[ <shadow>1</shadow> ]]></metaData>\n\n\t\t<transform>\n  <row0> 1 0 0 </row0>\n\t\t</transform>\n   </model>\t\n  <terrain>\r\n<resource>t</resource>\t</terrain>\n</root>  \n<!-- trailer -->\n";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::from_groups(vec![vec![vec![6, 1]]]))],
            speedtrees: Vec::new(),
            terrain: Some(3),
        };
        let out = write_str(text, &shadows);
        // Only the <shadow> element changed in the model; the terrain's
        // closing tag shares its line, so the new element comes on its own.
        let model_end = text.find("<metaData>").unwrap();
        let old_shadow = text.find("<shadow>\t7").unwrap();
        assert_eq!(&out[..old_shadow], &text[..old_shadow]);
        let after_shadow = &text[text.find("   <!-- after -->").unwrap()..model_end];
        assert!(out.contains(after_shadow));
        assert!(out.contains("<metaData><![CDATA[ <shadow>1</shadow> ]]></metaData>\n\n\t\t<transform>\n  <row0> 1 0 0 </row0>\n\t\t</transform>\n   </model>\t\n"));
        assert!(out.ends_with("</root>  \n<!-- trailer -->\n"));
        let root = xml::parse(out.as_bytes()).unwrap();
        assert_eq!(
            root.children[0].child_text("resource"),
            Some("sets/a<b>.model")
        );
        let back = read_chunk_shadows(&root).unwrap();
        assert_eq!(back.instances, shadows.instances);
        assert_eq!(back.terrain, Some(3));
        assert_eq!(write_str(&out, &shadows), out, "idempotent");
        // The same masks once more from the original: the same bytes.
        assert_eq!(write_str(text, &shadows), out);
    }

    #[test]
    fn crlf_files_get_crlf() {
        let text = BASIC.replace('\n', "\r\n");
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[2, 3]]))],
            speedtrees: Vec::new(),
            terrain: Some(1),
        };
        let out = write_str(&text, &shadows);
        let lone_lf = out
            .bytes()
            .enumerate()
            .filter(|&(i, b)| b == b'\n' && (i == 0 || out.as_bytes()[i - 1] != b'\r'))
            .count();
        assert_eq!(lone_lf, 0, "{out:?}");
        assert_eq!(
            out.replace("\r\n", "\n"),
            write_str(BASIC, &shadows),
            "same as the LF file but for line breaks"
        );
        assert_eq!(strip_shadows(out.as_bytes()), text.as_bytes());
    }

    #[test]
    fn element_on_one_line() {
        let text = "<root>\n\t<model><resource>a</resource></model>\n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[1]]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            "<root>\n\t<model><resource>a</resource>\n\t\t<shadow>\t1\n\t\t\t<RenderSet>\n\t\t\t\t<Geometry>\n\t\t\t\t\t<PrimitiveGroup>\t1\t</PrimitiveGroup>\n\t\t\t\t</Geometry>\n\t\t\t</RenderSet>\n\t\t</shadow>\n\t</model>\n</root>\n"
        );
        assert_eq!(write_str(&out, &shadows), out);
    }

    #[test]
    fn whole_file_on_one_line() {
        let text = "<root><model><resource>a</resource></model><terrain><resource>t</resource></terrain></root>";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: Some(4),
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            "<root><model><resource>a</resource>\n\t\t<shadow>\t0\t</shadow>\n\t</model><terrain><resource>t</resource>\n\t\t<shadow>\t4\t</shadow>\n\t</terrain></root>"
        );
        assert_eq!(write_str(&out, &shadows), out);
    }

    #[test]
    fn self_closing_elements_are_expanded() {
        let text = "<root>\n\t<model />\n\t<shell resource=\"x\"/>\n\t<terrain/>\n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![
                Some(InstanceShadow::default()),
                Some(InstanceShadow::default()),
            ],
            speedtrees: Vec::new(),
            terrain: Some(3),
        };
        let out = write_str(text, &shadows);
        assert_eq!(
            out,
            "<root>\n\t<model>\n\t\t<shadow>\t0\t</shadow>\n\t</model>\n\t<shell resource=\"x\">\n\t\t<shadow>\t0\t</shadow>\n\t</shell>\n\t<terrain>\n\t\t<shadow>\t3\t</shadow>\n\t</terrain>\n</root>\n"
        );
        assert_eq!(write_str(&out, &shadows), out);
    }

    #[test]
    fn bytes_that_are_not_utf8_are_kept() {
        let text = b"<root>\n\t<model a=\"\xe9\" />\n\t<entity>\xff</entity>\n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_shadows(text, &shadows).unwrap();
        let expected = b"<root>\n\t<model a=\"\xe9\">\n\t\t<shadow>\t0\t</shadow>\n\t</model>\n\t<entity>\xff</entity>\n</root>\n";
        assert_eq!(out, expected.to_vec());
    }

    #[test]
    fn file_named_root_and_nested_depth() {
        let text = "<fffb0000o.chunk>\n\t<shell>\n\t\t<resource>\ts\t</resource>\n\t</shell>\n</fffb0000o.chunk>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[0]]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert!(out.starts_with("<fffb0000o.chunk>\n\t<shell>\n\t\t<resource>\ts\t</resource>\n\t\t<shadow>\t0\n\t\t\t<RenderSet>\n"));
        assert!(out.ends_with("\t\t</shadow>\n\t</shell>\n</fffb0000o.chunk>\n"));
    }

    #[test]
    fn entities_and_byte_order_mark_are_kept() {
        let text = "\u{feff}<root>\n\t<entity>\n\t\t<name>\ta &amp; b &lt;c&gt; &#233;\t</name>\n\t</entity>\n\t<model>\n\t\t<resource>\tsets/&amp;.model\t</resource>\n\t</model>\n</root>\n";
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[5]]))],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &shadows);
        assert!(out.starts_with(
            "\u{feff}<root>\n\t<entity>\n\t\t<name>\ta &amp; b &lt;c&gt; &#233;\t</name>"
        ));
        assert_eq!(strip_shadows(out.as_bytes()), text.as_bytes());
        let root = xml::parse(out.as_bytes()).unwrap();
        assert_eq!(
            root.children[1].child_text("resource"),
            Some("sets/&.model")
        );
    }

    #[test]
    fn none_leaves_elements_byte_for_byte() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta\t</resource>\n\t\t<shadow>\t9\t</shadow>\n\t\t<shadow>\t8\t</shadow>\n\t</model>\n\t<model>\n\t\t<resource>\tb\t</resource>\n\t</model>\n\t<terrain>\n\t\t<shadow>\t1\t</shadow>\n\t</terrain>\n</root>\n";
        let nothing = ChunkShadows {
            instances: vec![None, None],
            speedtrees: Vec::new(),
            terrain: None,
        };
        assert_eq!(write_str(text, &nothing), text);
        let second = ChunkShadows {
            instances: vec![None, Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let out = write_str(text, &second);
        let first_model = &text
            [text.find("\t<model>").unwrap()..text.find("\t<model>\n\t\t<resource>\tb").unwrap()];
        assert!(out.contains(first_model));
        assert!(out.contains("<terrain>\n\t\t<shadow>\t1\t</shadow>\n\t</terrain>"));
        let back = read_chunk_shadows(&xml::parse(out.as_bytes()).unwrap()).unwrap();
        assert_eq!(
            back.instances[0].as_ref().unwrap().mask,
            9,
            "first one counts"
        );
        assert_eq!(back.instances[1], Some(InstanceShadow::default()));
        assert_eq!(back.terrain, Some(1));
    }

    #[test]
    fn receiver_only_instance_gets_zeros() {
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[0, 0]]))],
            speedtrees: Vec::new(),
            terrain: Some(0),
        };
        let out = write_str(BASIC, &shadows);
        assert!(out.contains("<shadow>\t0\n"));
        assert_eq!(
            out.matches("<PrimitiveGroup>\t0\t</PrimitiveGroup>")
                .count(),
            2
        );
        assert!(out.contains("<shadow>\t0\t</shadow>\n\t</terrain>"));
    }

    #[test]
    fn mismatches_are_errors_naming_the_element() {
        let too_many = ChunkShadows {
            instances: vec![None, None],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let err = write_shadows(BASIC.as_bytes(), &too_many).unwrap_err();
        assert!(err.to_string().contains("for 2 instances"), "{err}");
        assert!(err.to_string().contains("has 1"), "{err}");
        assert!(err.to_string().contains("<root>"), "{err}");

        let wrong_or = ChunkShadows {
            instances: vec![Some(InstanceShadow {
                mask: 1,
                render_sets: vec![vec![vec![2]]],
            })],
            speedtrees: Vec::new(),
            terrain: None,
        };
        let err = write_shadows(BASIC.as_bytes(), &wrong_or).unwrap_err();
        assert!(err.to_string().contains("root/model"), "{err}");
        assert!(err.to_string().contains("(byte 8)"), "{err}");

        let text = "<root>\n\t<model>\t</model>\n</root>";
        let no_terrain = ChunkShadows {
            instances: vec![None],
            speedtrees: Vec::new(),
            terrain: Some(1),
        };
        let err = write_shadows(text.as_bytes(), &no_terrain).unwrap_err();
        assert!(err.to_string().contains("no <terrain>"), "{err}");

        let err =
            write_shadows(b"<root>\n\t<model>\n</root>", &ChunkShadows::default()).unwrap_err();
        assert!(matches!(err.at, crate::error::Location::Byte(_)), "{err}");
    }

    #[test]
    fn bad_existing_masks_do_not_stop_a_rewrite_but_fail_a_read() {
        let text = "<root>\n\t<model>\n\t\t<shadow>\tlots\t</shadow>\n\t</model>\n</root>";
        let root = xml::parse(text.as_bytes()).unwrap();
        let err = read_chunk_shadows(&root).unwrap_err();
        assert!(err.to_string().contains("root/model/shadow"), "{err}");
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: None,
        };
        assert_eq!(write_str(text, &shadows), text.replace("lots", "0"));
    }

    #[test]
    fn packed_chunks_are_edited_as_trees() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t\t<shadow>\t1\t</shadow>\n\t\t<castsShadow>\ttrue\t</castsShadow>\n\t\t<shadow>\t2\t</shadow>\n\t</model>\n\t<model>\n\t\t<resource>\tb.model\t</resource>\n\t</model>\n\t<terrain>\n\t\t<resource>\tt\t</resource>\n\t</terrain>\n</root>\n";
        let packed = packed_xml::write(&xml::parse(text.as_bytes()).unwrap()).unwrap();
        let shadows = ChunkShadows {
            instances: vec![
                Some(InstanceShadow::from_groups(vec![
                    vec![vec![3, 0]],
                    vec![vec![1 << 31]],
                ])),
                None,
            ],
            speedtrees: Vec::new(),
            terrain: Some(6),
        };
        let out = write_shadows(&packed, &shadows).unwrap();
        assert!(out.starts_with(&packed_xml::MAGIC));
        assert_eq!(write_shadows(&out, &shadows).unwrap(), out, "idempotent");
        let root = packed_xml::parse(&out).unwrap();
        let back = read_chunk_shadows(&root).unwrap();
        assert_eq!(back.instances[0], shadows.instances[0]);
        assert_eq!(back.instances[1], None);
        assert_eq!(back.terrain, Some(6));
        let names: Vec<&str> = root.children[0]
            .children
            .iter()
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(
            names,
            ["resource", "shadow", "castsShadow"],
            "first position, extras gone"
        );
        // Errors also hold for packed files.
        let err = write_shadows(&packed, &ChunkShadows::default()).unwrap_err();
        assert!(err.message.contains("for 0 instances"), "{err}");
    }

    /// A random chunk in the styles real and hand-edited files have, with
    /// a flag telling whether every element it writes into is laid out one
    /// child per line (then bytes outside `<shadow>` lines must be equal).
    fn random_chunk(rng: &mut Rng) -> (String, ChunkShadows, bool) {
        let eol = if rng.chance(0.3) { "\r\n" } else { "\n" };
        let root = if rng.chance(0.5) {
            "root"
        } else {
            "fffb0000o.chunk"
        };
        let mut text = format!("<{root}>{eol}");
        let mut shadows = ChunkShadows::default();
        let mut strict = true;
        let elements = rng.below(6);
        let terrain_at = if rng.chance(0.7) {
            Some(rng.below(elements + 1))
        } else {
            None
        };
        for i in 0..=elements {
            if terrain_at == Some(i) {
                let mask = rng.chance(0.8).then(|| rng.next_u64() as u32);
                let one_line = rng.chance(0.2);
                if mask.is_some() && one_line {
                    strict = false;
                }
                if one_line {
                    text.push_str(&format!("\t<terrain><resource>t</resource></terrain>{eol}"));
                } else {
                    text.push_str(&format!(
                        "\t<terrain>{eol}\t\t<resource>\tt\t</resource>{eol}"
                    ));
                    if rng.chance(0.4) {
                        text.push_str(&format!("\t\t<shadow>\t{}\t</shadow>{eol}", rng.below(99)));
                    }
                    text.push_str(&format!("\t</terrain>{eol}"));
                }
                shadows.terrain = mask;
            }
            if i == elements {
                break;
            }
            if rng.chance(0.2) {
                text.push_str(&format!("\t<entity>\t&amp;x{eol}\t</entity>{eol}"));
            }
            if rng.chance(0.15) {
                text.push_str(&format!("\t<!-- <model> -->{eol}"));
            }
            let tag = if rng.chance(0.8) { "model" } else { "shell" };
            let style = rng.below(10);
            let masks = if rng.chance(0.8) {
                let sets = (0..rng.below(3))
                    .map(|_| {
                        (0..rng.below(3))
                            .map(|_| {
                                (0..rng.below(4))
                                    .map(|_| {
                                        if rng.chance(0.3) {
                                            0
                                        } else {
                                            rng.next_u64() as u32
                                        }
                                    })
                                    .collect()
                            })
                            .collect()
                    })
                    .collect();
                Some(InstanceShadow::from_groups(sets))
            } else {
                None
            };
            if masks.is_some() && style < 2 {
                strict = false;
            }
            match style {
                0 => text.push_str(&format!("\t<{tag} />{eol}")),
                1 => text.push_str(&format!(
                    "\t<{tag}><resource>a</resource><shadow>1</shadow></{tag}>{eol}"
                )),
                _ => {
                    text.push_str(&format!("\t<{tag}>{eol}"));
                    for _ in 0..rng.below(6) {
                        let indent = if rng.chance(0.2) { "    " } else { "\t\t" };
                        let child = match rng.below(6) {
                            0 => format!("<shadow>\t{}\t</shadow>", rng.below(50)),
                            1 => format!("<editorOnly>{eol}\t\t\t<shadow>\t4\t</shadow>{eol}\t\t</editorOnly>"),
                            2 => "<!-- a comment -->".to_string(),
                            3 => "<castsShadow>\ttrue\t</castsShadow><shadow>\t2\t</shadow>  ".to_string(),
                            _ => "<resource>\tsets/a&amp;b.model\t</resource>".to_string(),
                        };
                        text.push_str(&format!("{indent}{child}{eol}"));
                    }
                    text.push_str(&format!("\t</{tag}>{eol}"));
                }
            }
            shadows.instances.push(masks);
        }
        text.push_str(&format!("</{root}>{eol}"));
        (text, shadows, strict)
    }

    /// The places a write gives for its output are the places parsing
    /// that output finds, so a chunk written with them can be written
    /// again without a parse; written with places, the bytes are those of
    /// a write that parses.
    #[test]
    fn places_from_a_write_are_those_its_output_parses_to() {
        let mut rng = Rng::new(11);
        let mut places = [0usize; 4];
        for case in 0..400 {
            let (text, shadows, _) = random_chunk(&mut rng);
            let root = xml::parse(text.as_bytes()).unwrap();
            let sites = ShadowSites::find(text.as_bytes(), &root).unwrap();
            for site in sites
                .instances
                .iter()
                .chain(&sites.speedtrees)
                .chain(&sites.terrain)
            {
                places[Place::ALL.iter().position(|p| *p == site.place).unwrap()] += 1;
            }
            let (out, moved) = sites.write(text.as_bytes(), &shadows).unwrap();
            assert_eq!(
                out,
                write_shadows(text.as_bytes(), &shadows).unwrap(),
                "case {case}"
            );
            let found = ShadowSites::find(&out, &xml::parse(&out).unwrap()).unwrap();
            assert_eq!(moved, found, "case {case}:\n{text}");
            // Other masks into the written bytes, through the places alone.
            let mut other = shadows.clone();
            if let Some(t) = &mut other.terrain {
                *t ^= 5;
            }
            let (twice, _) = moved.write(&out, &other).unwrap();
            assert_eq!(twice, write_shadows(&out, &other).unwrap(), "case {case}");
        }
        assert!(
            places.iter().all(|&n| n > 20),
            "every place met: {places:?}"
        );
    }

    #[test]
    fn a_place_is_the_twenty_bytes_the_memory_model_counts() {
        // bake::memory::PER_INSTANCE counts one per placed element.
        assert_eq!(std::mem::size_of::<Site>(), 20);
    }

    #[test]
    fn places_refuse_bytes_they_were_not_found_in() {
        let text = BASIC.as_bytes();
        let sites = ShadowSites::find(text, &xml::parse(text).unwrap()).unwrap();
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[1]]))],
            speedtrees: Vec::new(),
            terrain: Some(1),
        };
        let other = BASIC.replace("<root>", "<root> ");
        let err = sites.write(other.as_bytes(), &shadows).unwrap_err();
        assert!(
            err.to_string().contains("not those its <shadow> places"),
            "{err}"
        );
        let shorter = &text[..40];
        assert!(sites.write(shorter, &shadows).is_err());
        let mut fewer = shadows.clone();
        fewer.instances.clear();
        let err = sites.write(text, &fewer).unwrap_err();
        assert!(
            err.to_string().contains("the chunk has 1 <model>/<shell>"),
            "{err}"
        );
    }

    #[test]
    fn generated_chunks_idempotent_preserved_and_read_back() {
        let mut rng = Rng::new(7);
        let mut strict_cases = 0;
        for case in 0..400 {
            let (text, shadows, strict) = random_chunk(&mut rng);
            let out = write_shadows(text.as_bytes(), &shadows)
                .unwrap_or_else(|e| panic!("case {case}: {e}\n{text}"));
            let again = write_shadows(&out, &shadows).unwrap();
            assert_eq!(again, out, "case {case} not idempotent:\n{text}");
            let root = xml::parse(&out).unwrap();
            let before = read_chunk_shadows(&xml::parse(text.as_bytes()).unwrap()).unwrap();
            let back = read_chunk_shadows(&root).unwrap();
            assert_eq!(back.instances.len(), shadows.instances.len());
            for (i, want) in shadows.instances.iter().enumerate() {
                let expected = if want.is_some() {
                    want
                } else {
                    &before.instances[i]
                };
                assert_eq!(&back.instances[i], expected, "case {case} instance {i}");
            }
            for ((_, element), want) in instance_elements(&root).zip(&shadows.instances) {
                if want.is_some() {
                    let n = element.children_named(SHADOW_TAG).count();
                    assert_eq!(n, 1, "case {case}: one direct <shadow> per written element");
                }
            }
            let want_terrain = shadows.terrain.or(before.terrain);
            assert_eq!(back.terrain, want_terrain, "case {case}");
            if strict {
                strict_cases += 1;
                assert_eq!(
                    String::from_utf8(strip_shadows(&out)).unwrap(),
                    String::from_utf8(strip_shadows(text.as_bytes())).unwrap(),
                    "case {case}"
                );
            } else {
                // Only white space and expanded tags differ outside <shadow>.
                let squash = |b: Vec<u8>| -> String {
                    String::from_utf8(b)
                        .unwrap()
                        .split_whitespace()
                        .collect::<String>()
                };
                let expand = |s: String| {
                    s.replace("<model/>", "<model></model>")
                        .replace("<shell/>", "<shell></shell>")
                };
                assert_eq!(
                    expand(squash(strip_shadows(&out))),
                    expand(squash(strip_shadows(text.as_bytes()))),
                    "case {case}"
                );
            }
            let packed = packed_xml::write(&xml::parse(text.as_bytes()).unwrap()).unwrap();
            let packed_out = write_shadows(&packed, &shadows).unwrap();
            assert_eq!(write_shadows(&packed_out, &shadows).unwrap(), packed_out);
            let packed_back = read_chunk_shadows(&packed_xml::parse(&packed_out).unwrap()).unwrap();
            assert_eq!(packed_back, back, "case {case}: packed and text agree");
        }
        assert!(strict_cases > 100, "{strict_cases}");
    }

    #[test]
    fn every_prefix_and_garbage_is_an_error_not_a_panic() {
        let shadows = ChunkShadows {
            instances: vec![Some(InstanceShadow::default())],
            speedtrees: Vec::new(),
            terrain: Some(1),
        };
        for len in 0..BASIC.len() {
            let _ = write_shadows(&BASIC.as_bytes()[..len], &shadows);
        }
        let packed = packed_xml::write(&xml::parse(BASIC.as_bytes()).unwrap()).unwrap();
        for len in 0..packed.len() {
            let _ = write_shadows(&packed[..len], &shadows);
        }
        let mut rng = Rng::new(3);
        for _ in 0..200 {
            let mut bytes = packed.clone();
            let i = rng.below(bytes.len());
            bytes[i] ^= 1 << rng.below(8);
            let _ = write_shadows(&bytes, &shadows);
        }
    }

    #[test]
    fn without_masks_is_the_file_with_zero_masks_and_survives_a_write() {
        let chunk_of =
            |text: &[u8]| super::super::chunk::parse(&xml::parse(text).unwrap()).unwrap();
        let shadows = ChunkShadows {
            instances: vec![Some(one(&[&[5, 2]]))],
            speedtrees: Vec::new(),
            terrain: Some(3),
        };
        let written = write_str(BASIC, &shadows);
        for text in [BASIC.as_bytes(), written.as_bytes()] {
            let chunk = chunk_of(text);
            let root = xml::parse(text).unwrap();
            let zeroed = ChunkShadows {
                instances: vec![Some(InstanceShadow::default())],
                speedtrees: Vec::new(),
                terrain: Some(0),
            };
            let zeroed_bytes = write_shadows(text, &zeroed).unwrap();
            assert_eq!(without_masks(text, &root, &chunk).unwrap(), zeroed_bytes);
            // Hashed as it is spliced, the same digest as of the bytes.
            let sites = ShadowSites::find(text, &root).unwrap();
            assert_eq!(
                digest_without_masks_at(text, &sites, &chunk).unwrap(),
                Digest::of(&zeroed_bytes)
            );
        }
        let before = without_masks(
            BASIC.as_bytes(),
            &xml::parse(BASIC.as_bytes()).unwrap(),
            &chunk_of(BASIC.as_bytes()),
        );
        let after = without_masks(
            written.as_bytes(),
            &xml::parse(written.as_bytes()).unwrap(),
            &chunk_of(written.as_bytes()),
        );
        assert_eq!(
            before.unwrap(),
            after.unwrap(),
            "writing masks leaves the fingerprinted bytes alone"
        );
    }

    const TREES: &str = "<root>\n\t<speedtree>\n\t\t<spt>\ta.spt\t</spt>\n\t\t<transform>\t1 0 0 0 1 0 0 0 1 5 0 5\t</transform>\n\t</speedtree>\n\t<model>\n\t\t<resource>\tm.model\t</resource>\n\t</model>\n\t<speedtree>\n\t\t<spt>\tb.spt\t</spt>\n\t\t<shadow>\t9\t</shadow>\n\t</speedtree>\n\t<speedtree>\n\t\t<spt>\tc.spt\t</spt>\n\t</speedtree>\n</root>\n";

    fn tree_shadows() -> ChunkShadows {
        ChunkShadows {
            instances: vec![Some(one(&[&[1]]))],
            speedtrees: vec![
                // A parametric proxy: trunk and crown.
                Some(one(&[&[3, 2]])),
                // No proxy: the mask alone.
                Some(InstanceShadow {
                    mask: 7,
                    render_sets: Vec::new(),
                }),
                None,
            ],
            terrain: None,
        }
    }

    #[test]
    fn speedtrees_get_their_masks_inside_the_item_like_models() {
        let shadows = tree_shadows();
        let out = write_str(TREES, &shadows);
        assert!(out.contains("\t\t<shadow>\t3\n\t\t\t<RenderSet>\n\t\t\t\t<Geometry>\n\t\t\t\t\t<PrimitiveGroup>\t3\t</PrimitiveGroup>\n\t\t\t\t\t<PrimitiveGroup>\t2\t</PrimitiveGroup>"), "{out}");
        assert!(
            out.contains("<spt>\tb.spt\t</spt>\n\t\t<shadow>\t7\t</shadow>\n\t</speedtree>"),
            "the old mask replaced in place: {out}"
        );
        assert!(
            out.contains("<spt>\tc.spt\t</spt>\n\t</speedtree>"),
            "None leaves it: {out}"
        );
        assert_eq!(write_str(&out, &shadows), out, "idempotent");
        assert_eq!(
            String::from_utf8(strip_shadows(out.as_bytes())).unwrap(),
            String::from_utf8(strip_shadows(TREES.as_bytes())).unwrap(),
        );
        let back = read_chunk_shadows(&xml::parse(out.as_bytes()).unwrap()).unwrap();
        assert_eq!(back.instances, shadows.instances);
        assert_eq!(&back.speedtrees[..2], &shadows.speedtrees[..2]);
        assert_eq!(back.speedtrees[2], None);

        let packed = packed_xml::write(&xml::parse(TREES.as_bytes()).unwrap()).unwrap();
        let packed_out = write_shadows(&packed, &shadows).unwrap();
        assert_eq!(write_shadows(&packed_out, &shadows).unwrap(), packed_out);
        let packed_back = read_chunk_shadows(&packed_xml::parse(&packed_out).unwrap()).unwrap();
        assert_eq!(packed_back, back, "packed and text agree");

        let root = xml::parse(TREES.as_bytes()).unwrap();
        let chunk = super::super::chunk::parse(&root).unwrap();
        let zeroed = without_masks(TREES.as_bytes(), &root, &chunk).unwrap();
        let zeroed_back = read_chunk_shadows(&xml::parse(&zeroed).unwrap()).unwrap();
        assert!(zeroed_back
            .speedtrees
            .iter()
            .all(|s| s == &Some(InstanceShadow::default())));
    }

    #[test]
    fn speedtree_masks_that_do_not_fit_are_errors() {
        let mut too_few = tree_shadows();
        too_few.speedtrees.pop();
        let err = write_shadows(TREES.as_bytes(), &too_few).unwrap_err();
        assert!(
            err.to_string().contains("has 3 <speedtree> elements"),
            "{err}"
        );
        let mut wrong_or = tree_shadows();
        wrong_or.speedtrees[0] = Some(InstanceShadow {
            mask: 1,
            render_sets: vec![vec![vec![2]]],
        });
        let err = write_shadows(TREES.as_bytes(), &wrong_or).unwrap_err();
        assert!(err.to_string().contains("root/speedtree"), "{err}");
    }
}
