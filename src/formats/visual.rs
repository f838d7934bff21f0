//! `.visual` files (moo/visual.cpp, effect_material.cpp): the node hierarchy,
//! the renderSets with their geometries, and for every primitive group the
//! two material flags the bake needs (alpha-tested, double-sided). The
//! geometry itself lives in the `.primitives` file; this module only says
//! which sections of which file to read and how to place them.
//!
//! Engine behaviour reproduced here:
//! - the hierarchy is the root's *first* `<node>`; without one the visual has
//!   a single identity node called `root`;
//! - a renderSet without `<node>` names is placed by the root node; a
//!   non-skinned renderSet's vertices are in its first node's space, placed
//!   by that node's transform chain up to and including the root;
//! - a `<vertices>`/`<primitive>` name without `/` is a section of the
//!   visual's own `.primitives`; one with `/` is a resource path split by the
//!   engine's `splitOldPrimitiveName` rule (see [`split_section_resource`]);
//! - a material's `<mfm>` names a material file loaded first; the material's
//!   own properties then override it, and among repeated properties of one
//!   material the first wins (the engine walks them back to front).

use super::Section;
use crate::error::FormatError;
use glam::DMat4;

/// Deepest `<mfm>` inheritance chain followed; real chains are 1–2 long.
pub const MAX_MFM_DEPTH: usize = 16;

#[derive(Debug, Clone, PartialEq)]
pub struct Visual {
    /// Depth-first order: index 0 is the root, and every node's parent has
    /// a smaller index.
    pub nodes: Vec<Node>,
    pub render_sets: Vec<RenderSet>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Node {
    pub identifier: String,
    /// Local transform, relative to the parent (column-vector glam form of
    /// the file's row-vector matrix).
    pub transform: DMat4,
    pub parent: Option<usize>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct RenderSet {
    /// True for skinned geometry (vertices already in model space, moved by
    /// bone weights).
    pub treat_as_world_space_object: bool,
    /// The `<node>` names, in file order.
    pub nodes: Vec<String>,
    /// Index into [`Visual::nodes`] of the first named node (the root when
    /// none is named): the space of non-skinned vertices.
    pub first_node: usize,
    pub geometries: Vec<Geometry>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Geometry {
    /// `<vertices>` as written: a section name, or a resource path with `/`.
    pub vertices: String,
    /// `<primitive>` as written (the index section).
    pub primitive: String,
    pub groups: Vec<PrimitiveGroup>,
    /// Element path, for errors found later (e.g. in the `.primitives`).
    pub path: String,
}

#[derive(Debug, Clone, PartialEq)]
pub struct PrimitiveGroup {
    /// Index into the index section's PrimitiveGroup table.
    pub index: u32,
    /// The material's `<identifier>` (empty when absent).
    pub material_identifier: String,
    /// `<mfm>` of the material, if any: a material file to inherit from.
    pub mfm: Option<String>,
    /// The flags of the material's own properties. With an `mfm` they are
    /// only final after [`Visual::resolve_materials`].
    pub flags: MaterialFlags,
    /// The `<material>` element, for [`resolve_material_flags`].
    pub material: Option<Section>,
    pub path: String,
}

/// The material properties that matter to the bake; `None` = not set (the
/// `.fx` default applies, taken as false: the effect files are not read).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MaterialFlags {
    pub alpha_test_enable: Option<bool>,
    pub double_sided: Option<bool>,
}

impl MaterialFlags {
    pub fn alpha_tested(&self) -> bool {
        self.alpha_test_enable.unwrap_or(false)
    }

    pub fn double_sided(&self) -> bool {
        self.double_sided.unwrap_or(false)
    }

    /// `self` over `base`: a property set here wins.
    fn over(self, base: MaterialFlags) -> MaterialFlags {
        MaterialFlags {
            alpha_test_enable: self.alpha_test_enable.or(base.alpha_test_enable),
            double_sided: self.double_sided.or(base.double_sided),
        }
    }
}

impl PrimitiveGroup {
    pub fn alpha_tested(&self) -> bool {
        self.flags.alpha_tested()
    }

    pub fn double_sided(&self) -> bool {
        self.flags.double_sided()
    }
}

impl Visual {
    /// Index of the first node (depth-first) with this identifier.
    pub fn node_index(&self, identifier: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.identifier == identifier)
    }

    /// Node `index`'s transform chained up to the root (row-vector
    /// `node · parent · … · root`, i.e. `root * … * parent * node` in glam).
    pub fn node_to_root_index(&self, index: usize) -> Option<DMat4> {
        let mut node = self.nodes.get(index)?;
        let mut m = node.transform;
        // Parents have smaller indices, so this ends; the bound is a guard
        // for hand-built values.
        for _ in 0..self.nodes.len() {
            let Some(parent) = node.parent else {
                return Some(m);
            };
            node = self.nodes.get(parent)?;
            m = node.transform * m;
        }
        None
    }

    /// Every `<mfm>` named directly by a material of this visual, sorted and
    /// without repeats (files they inherit from are found while resolving).
    pub fn mfm_names(&self) -> Vec<String> {
        let mut names: Vec<String> = self
            .render_sets
            .iter()
            .flat_map(|r| &r.geometries)
            .flat_map(|g| &g.groups)
            .filter_map(|p| p.mfm.clone())
            .collect();
        names.sort();
        names.dedup();
        names
    }

    /// Replaces every group's flags by the ones inherited through `<mfm>`
    /// files, loaded by `load_mfm` (`None`: not found, ignored as the engine
    /// does).
    pub fn resolve_materials(
        &mut self,
        load_mfm: &mut dyn FnMut(&str) -> Option<Section>,
    ) -> Result<(), FormatError> {
        for group in self
            .render_sets
            .iter_mut()
            .flat_map(|r| &mut r.geometries)
            .flat_map(|g| &mut g.groups)
        {
            if group.mfm.is_some() {
                if let Some(material) = &group.material {
                    group.flags = resolve_material_flags(material, load_mfm)?;
                }
            }
        }
        Ok(())
    }
}

/// `node_name`'s transform chain up to the root; see
/// [`Visual::node_to_root_index`].
pub fn node_to_root(visual: &Visual, node_name: &str) -> Option<DMat4> {
    visual.node_to_root_index(visual.node_index(node_name)?)
}

/// The `.primitives` resource of a visual: `x.static.visual` →
/// `x.static.primitives`, `x.visual` → `x.primitives` (the engine cuts at the
/// last `.`).
pub fn primitives_name(visual_resource: &str) -> String {
    let file_start = visual_resource.rfind('/').map_or(0, |i| i + 1);
    let base = match visual_resource[file_start..].rfind('.') {
        Some(dot) => &visual_resource[..file_start + dot],
        None => visual_resource,
    };
    format!("{base}.primitives")
}

/// Where a geometry's `<vertices>` or `<primitive>` section lives:
/// `(primitives file resource, section name)`.
///
/// - no `/`: a section of the visual's own `primitives_file`;
/// - `….primitives/section`: that file and section;
/// - otherwise the engine's old-style name (`splitOldPrimitiveName`): in the
///   last path component the first `.` starts the section name, except that
///   a leading `.static` stays with the file:
///   `sets/items/upperskull.static.vertices` →
///   (`sets/items/upperskull.static.primitives`, `vertices`),
///   `sets/town/props/t_candle.candle_wax.vertices` →
///   (`sets/town/props/t_candle.primitives`, `candle_wax.vertices`).
///
/// `None` when a path has no `.` in its last component (nothing names a
/// section).
pub fn split_section_resource(primitives_file: &str, name: &str) -> Option<(String, String)> {
    if !name.contains('/') {
        return Some((primitives_file.to_string(), name.to_string()));
    }
    const MARK: &str = ".primitives/";
    if let Some(at) = name.find(MARK) {
        let file_end = at + MARK.len() - 1;
        let section = &name[file_end + 1..];
        return (!section.is_empty()).then(|| (name[..file_end].to_string(), section.to_string()));
    }
    let file_start = name.rfind(['/', '\\']).map_or(0, |i| i + 1);
    let last = &name[file_start..];
    let mut dots = last.match_indices('.').map(|(i, _)| file_start + i);
    let mut dot = dots.next()?;
    if let Some(second) = dots.next() {
        if &name[dot..second] == ".static" {
            dot = second;
        }
    }
    let section = &name[dot + 1..];
    if section.is_empty() {
        return None;
    }
    Some((format!("{}.primitives", &name[..dot]), section.to_string()))
}

/// Reads a visual's tree (text or packed XML).
pub fn parse_visual(root: &Section) -> Result<Visual, FormatError> {
    let nodes = match root.child("node") {
        Some(node) => read_nodes(node)?,
        None => vec![Node {
            identifier: "root".to_string(),
            transform: DMat4::IDENTITY,
            parent: None,
        }],
    };
    let mut visual = Visual {
        nodes,
        render_sets: Vec::new(),
    };
    for set in root.children_named("renderSet") {
        let treat_as_world_space_object = match set.child("treatAsWorldSpaceObject") {
            Some(flag) => flag.as_bool()?,
            None => false,
        };
        let mut names = Vec::new();
        let mut first_node = None;
        for node in set.children_named("node") {
            let index = visual.node_index(&node.value).ok_or_else(|| {
                node.error(format!(
                    "renderSet names node `{}`, which is not in the visual's node hierarchy",
                    node.value
                ))
            })?;
            first_node.get_or_insert(index);
            names.push(node.value.clone());
        }
        let mut geometries = Vec::new();
        for geometry in set.children_named("geometry") {
            geometries.push(read_geometry(geometry)?);
        }
        visual.render_sets.push(RenderSet {
            treat_as_world_space_object,
            nodes: names,
            first_node: first_node.unwrap_or(0),
            geometries,
        });
    }
    Ok(visual)
}

/// Flattens the node tree depth-first without recursion.
fn read_nodes(top: &Section) -> Result<Vec<Node>, FormatError> {
    let mut nodes = Vec::new();
    let mut pending: Vec<(&Section, Option<usize>)> = vec![(top, None)];
    while let Some((section, parent)) = pending.pop() {
        let index = nodes.len();
        nodes.push(Node {
            identifier: section.child_text("identifier").unwrap_or("").to_string(),
            transform: read_transform(section)?,
            parent,
        });
        // Reversed so children come out in file order.
        let children: Vec<&Section> = section.children_named("node").collect();
        pending.extend(children.into_iter().rev().map(|c| (c, Some(index))));
    }
    Ok(nodes)
}

/// `<transform>` of a node; absent or empty means identity, as the engine's
/// `readMatrix34` with an identity default.
fn read_transform(node: &Section) -> Result<DMat4, FormatError> {
    let Some(t) = node.child("transform") else {
        return Ok(DMat4::IDENTITY);
    };
    if t.children.is_empty() && t.value.is_empty() {
        return Ok(DMat4::IDENTITY);
    }
    let m = t.as_matrix()?;
    if !m.is_finite() {
        return Err(t.error("node transform holds NaN or infinite numbers"));
    }
    Ok(m)
}

fn read_geometry(geometry: &Section) -> Result<Geometry, FormatError> {
    let name_of = |tag: &str| -> Result<String, FormatError> {
        let s = geometry.required(tag)?;
        if s.value.is_empty() {
            return Err(s.error(format!(
                "empty <{tag}>; expected a .primitives section name"
            )));
        }
        Ok(s.value.clone())
    };
    let vertices = name_of("vertices")?;
    let primitive = name_of("primitive")?;
    let mut groups = Vec::new();
    for group in geometry.children_named("primitiveGroup") {
        // The engine's asInt: an empty value reads as 0.
        let index = if group.value.is_empty() {
            0
        } else {
            let v = group.as_i64()?;
            u32::try_from(v).map_err(|_| {
                group.error(format!(
                    "primitive group index {v} is negative or too large"
                ))
            })?
        };
        let material = group.child("material");
        let (flags, mfm, material_identifier) = match material {
            Some(m) => (
                own_flags(m)?,
                mfm_of(m),
                m.child_text("identifier").unwrap_or("").to_string(),
            ),
            None => (MaterialFlags::default(), None, String::new()),
        };
        groups.push(PrimitiveGroup {
            index,
            material_identifier,
            mfm,
            flags,
            material: material.cloned(),
            path: group.path.clone(),
        });
    }
    Ok(Geometry {
        vertices,
        primitive,
        groups,
        path: geometry.path.clone(),
    })
}

fn mfm_of(material: &Section) -> Option<String> {
    material
        .child("mfm")
        .map(|m| m.value.clone())
        .filter(|v| !v.is_empty())
}

/// The flags set by a material's own `<property>` elements. A property's
/// name is its own text and its value its first child (`<Bool>`, or `<Int>`
/// read as non-zero); other value types leave the flag unset.
fn own_flags(material: &Section) -> Result<MaterialFlags, FormatError> {
    let mut flags = MaterialFlags::default();
    for property in material.children_named("property") {
        let slot = match property.value.as_str() {
            "alphaTestEnable" => &mut flags.alpha_test_enable,
            "doubleSided" => &mut flags.double_sided,
            _ => continue,
        };
        if slot.is_some() {
            continue; // the first occurrence wins
        }
        let Some(value) = property.children.first() else {
            continue;
        };
        *slot = match value.name.as_str() {
            "Bool" => Some(value.as_bool()?),
            "Int" => Some(value.as_i64()? != 0),
            _ => None,
        };
    }
    Ok(flags)
}

/// A material's flags including everything inherited through `<mfm>` files
/// (`load_mfm` returns the file's root, or `None` when it does not exist,
/// which the engine ignores). An inheritance cycle or a chain longer than
/// [`MAX_MFM_DEPTH`] is an error naming the `<mfm>` element.
pub fn resolve_material_flags(
    material: &Section,
    load_mfm: &mut dyn FnMut(&str) -> Option<Section>,
) -> Result<MaterialFlags, FormatError> {
    let mut chain = Vec::new();
    resolve_chain(material, load_mfm, &mut chain)
}

fn resolve_chain(
    material: &Section,
    load_mfm: &mut dyn FnMut(&str) -> Option<Section>,
    chain: &mut Vec<String>,
) -> Result<MaterialFlags, FormatError> {
    let own = own_flags(material)?;
    let Some(mfm_section) = material.child("mfm") else {
        return Ok(own);
    };
    let name = mfm_section.value.as_str();
    if name.is_empty() {
        return Ok(own);
    }
    if chain.iter().any(|n| n == name) {
        return Err(mfm_section.error(format!(
            "material inheritance cycle: {} -> {name}",
            chain.join(" -> ")
        )));
    }
    if chain.len() >= MAX_MFM_DEPTH {
        return Err(mfm_section.error(format!(
            "material inheritance deeper than {MAX_MFM_DEPTH} <mfm> files"
        )));
    }
    let Some(base) = load_mfm(name) else {
        return Ok(own);
    };
    chain.push(name.to_string());
    let inherited = resolve_chain(&base, load_mfm, chain)?;
    chain.pop();
    Ok(own.over(inherited))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::section::build::{el, with_paths};
    use glam::DVec3;

    fn leaf(name: &str, value: &str) -> Section {
        el(name, value, vec![])
    }

    fn transform(rows: [&str; 4]) -> Section {
        el(
            "transform",
            "",
            rows.iter()
                .enumerate()
                .map(|(i, r)| leaf(&format!("row{i}"), r))
                .collect(),
        )
    }

    fn node(id: &str, t: Option<Section>, children: Vec<Section>) -> Section {
        let mut c = vec![leaf("identifier", id)];
        c.extend(t);
        c.extend(children);
        el("node", "", c)
    }

    fn property(name: &str, kind: &str, value: &str) -> Section {
        el("property", name, vec![leaf(kind, value)])
    }

    fn group(index: &str, material: Vec<Section>) -> Section {
        el("primitiveGroup", index, vec![el("material", "", material)])
    }

    fn geometry(vertices: &str, groups: Vec<Section>) -> Section {
        let mut c = vec![leaf("vertices", vertices), leaf("primitive", "indices")];
        c.extend(groups);
        el("geometry", "", c)
    }

    /// Root (translate 0 10 0) → arm (rotate +x to -z, translate 1 0 0) →
    /// hand (translate 0 0 2); a renderSet on `hand` with two groups.
    fn sample() -> Section {
        let hierarchy = node(
            "Scene Root",
            Some(transform(["1 0 0", "0 1 0", "0 0 1", "0 10 0"])),
            vec![
                node(
                    "arm",
                    Some(transform(["0 0 -1", "0 1 0", "1 0 0", "1 0 0"])),
                    vec![node(
                        "hand",
                        Some(transform(["1 0 0", "0 1 0", "0 0 1", "0 0 2"])),
                        vec![],
                    )],
                ),
                node("empty", Some(el("transform", "", vec![])), vec![]),
            ],
        );
        let set = el(
            "renderSet",
            "",
            vec![
                leaf("treatAsWorldSpaceObject", "false"),
                leaf("node", "hand"),
                leaf("node", "arm"),
                geometry(
                    "Plane02.vertices",
                    vec![
                        group(
                            "0",
                            vec![
                                leaf("identifier", "leaves"),
                                property("alphaReference", "Int", "10"),
                                property("alphaTestEnable", "Bool", "true"),
                                property("doubleSided", "Bool", "true"),
                                el("property", "diffuseMap", vec![]),
                            ],
                        ),
                        group(
                            "1",
                            vec![
                                property("alphaTestEnable", "Bool", "false"),
                                property("alphaTestEnable", "Bool", "true"),
                                property("doubleSided", "Int", "0"),
                            ],
                        ),
                    ],
                ),
            ],
        );
        with_paths(el("x.visual", "", vec![hierarchy, set]), "")
    }

    #[test]
    fn hierarchy_render_sets_and_flags() {
        let v = parse_visual(&sample()).unwrap();
        let ids: Vec<_> = v.nodes.iter().map(|n| n.identifier.as_str()).collect();
        assert_eq!(ids, ["Scene Root", "arm", "hand", "empty"]);
        let parents: Vec<_> = v.nodes.iter().map(|n| n.parent).collect();
        assert_eq!(parents, [None, Some(0), Some(1), Some(0)]);
        assert_eq!(v.nodes[3].transform, DMat4::IDENTITY);
        let set = &v.render_sets[0];
        assert!(!set.treat_as_world_space_object);
        assert_eq!(set.nodes, ["hand", "arm"]);
        assert_eq!(set.first_node, 2);
        let g = &set.geometries[0];
        assert_eq!(
            (g.vertices.as_str(), g.primitive.as_str()),
            ("Plane02.vertices", "indices")
        );
        assert_eq!(g.groups.len(), 2);
        assert_eq!(g.groups[0].index, 0);
        assert_eq!(g.groups[0].material_identifier, "leaves");
        assert!(g.groups[0].alpha_tested() && g.groups[0].double_sided());
        // First of repeated properties wins; Int 0 is false.
        assert_eq!(g.groups[1].index, 1);
        assert_eq!(
            g.groups[1].flags,
            MaterialFlags {
                alpha_test_enable: Some(false),
                double_sided: Some(false)
            }
        );
        assert_eq!(g.path, "x.visual/renderSet/geometry");
    }

    #[test]
    fn node_chain_moves_points_as_the_engine() {
        let v = parse_visual(&sample()).unwrap();
        // Row-vector: p · hand · arm · root. Origin: hand → (0,0,2);
        // arm: x→-z, z→x, then +(1,0,0) → (3,0,0); root: +(0,10,0).
        let m = node_to_root(&v, "hand").unwrap();
        assert_eq!(m.transform_point3(DVec3::ZERO), DVec3::new(3.0, 10.0, 0.0));
        // Local +x: hand → (1,0,2); arm → (0,0,-1)+(2,0,0)+(1,0,0) = (3,0,-1).
        assert_eq!(m.transform_point3(DVec3::X), DVec3::new(3.0, 10.0, -1.0));
        assert_eq!(
            node_to_root(&v, "Scene Root")
                .unwrap()
                .transform_point3(DVec3::ZERO),
            DVec3::new(0.0, 10.0, 0.0)
        );
        assert!(node_to_root(&v, "nope").is_none());
    }

    #[test]
    fn no_node_means_one_identity_root() {
        let root = with_paths(
            el(
                "v",
                "",
                vec![el(
                    "renderSet",
                    "",
                    vec![geometry("vertices", vec![group("", vec![])])],
                )],
            ),
            "",
        );
        let v = parse_visual(&root).unwrap();
        assert_eq!(v.nodes.len(), 1);
        assert_eq!(v.nodes[0].identifier, "root");
        assert_eq!(v.render_sets[0].first_node, 0);
        assert_eq!(v.render_sets[0].geometries[0].groups[0].index, 0);
        assert!(!v.render_sets[0].geometries[0].groups[0].alpha_tested());
    }

    #[test]
    fn errors_name_the_element() {
        let mut bad_node = sample();
        bad_node.children[1].children[1].value = "ghost".into();
        let e = parse_visual(&bad_node).unwrap_err().to_string();
        assert!(
            e.contains("ghost") && e.contains("<x.visual/renderSet/node>"),
            "{e}"
        );

        let mut bad_index = sample();
        bad_index.children[1].children[3].children[2].value = "-1".into();
        let e = parse_visual(&bad_index).unwrap_err().to_string();
        assert!(
            e.contains("negative") && e.contains("primitiveGroup"),
            "{e}"
        );

        let mut no_vertices = sample();
        no_vertices.children[1].children[3].children.remove(0);
        let e = parse_visual(&no_vertices).unwrap_err().to_string();
        assert!(e.contains("<vertices>"), "{e}");

        let mut nan = sample();
        nan.children[0].children[1].children[3].value = "NaN 0 0".into();
        let e = parse_visual(&nan).unwrap_err().to_string();
        assert!(e.contains("NaN") && e.contains("transform"), "{e}");

        let mut bad_bool = sample();
        bad_bool.children[1].children[3].children[2].children[0].children[2].children[0].value =
            "yes".into();
        let e = parse_visual(&bad_bool).unwrap_err().to_string();
        assert!(e.contains("yes") && e.contains("Bool"), "{e}");
    }

    fn mfm_file(parent: Option<&str>, properties: Vec<Section>) -> Section {
        let mut c: Vec<Section> = parent.map(|p| leaf("mfm", p)).into_iter().collect();
        c.extend(properties);
        with_paths(el("root", "", c), "")
    }

    #[test]
    fn mfm_inheritance_and_override() {
        let material = with_paths(
            el(
                "material",
                "",
                vec![
                    leaf("mfm", "a.mfm"),
                    property("doubleSided", "Bool", "false"),
                ],
            ),
            "",
        );
        let mut load = |name: &str| match name {
            "a.mfm" => Some(mfm_file(
                Some("b.mfm"),
                vec![property("doubleSided", "Bool", "true")],
            )),
            "b.mfm" => Some(mfm_file(
                None,
                vec![property("alphaTestEnable", "Bool", "true")],
            )),
            _ => None,
        };
        let flags = resolve_material_flags(&material, &mut load).unwrap();
        assert_eq!(
            flags,
            MaterialFlags {
                alpha_test_enable: Some(true),
                double_sided: Some(false)
            }
        );
        // A missing file is ignored.
        let lonely = with_paths(el("material", "", vec![leaf("mfm", "missing.mfm")]), "");
        assert_eq!(
            resolve_material_flags(&lonely, &mut load).unwrap(),
            MaterialFlags::default()
        );
    }

    #[test]
    fn mfm_cycles_are_errors_not_loops() {
        let material = with_paths(el("material", "", vec![leaf("mfm", "a.mfm")]), "");
        let mut calls = 0;
        let mut load = |name: &str| {
            calls += 1;
            Some(mfm_file(
                Some(if name == "a.mfm" { "b.mfm" } else { "a.mfm" }),
                vec![],
            ))
        };
        let e = resolve_material_flags(&material, &mut load)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cycle") && e.contains("a.mfm -> b.mfm -> a.mfm"),
            "{e}"
        );
        assert_eq!(calls, 2);
        // An endless chain of distinct names stops at the depth bound.
        let mut n = 0;
        let mut endless = |_: &str| {
            n += 1;
            Some(mfm_file(Some(&format!("m{n}.mfm")), vec![]))
        };
        let e = resolve_material_flags(&material, &mut endless)
            .unwrap_err()
            .to_string();
        assert!(e.contains("deeper than"), "{e}");
    }

    #[test]
    fn visual_resolves_its_groups_through_mfm() {
        let mut root = sample();
        // Group 1 loses its own doubleSided and inherits one instead.
        let material = &mut root.children[1].children[3].children[3].children[0];
        material.children.remove(2);
        material.children.push(leaf("mfm", "base.mfm"));
        let mut v = parse_visual(&root).unwrap();
        assert_eq!(v.mfm_names(), ["base.mfm"]);
        assert!(!v.render_sets[0].geometries[0].groups[1].double_sided());
        let mut asked = Vec::new();
        v.resolve_materials(&mut |name: &str| {
            asked.push(name.to_string());
            Some(mfm_file(
                None,
                vec![
                    property("doubleSided", "Bool", "true"),
                    property("alphaTestEnable", "Bool", "true"),
                ],
            ))
        })
        .unwrap();
        assert_eq!(asked, ["base.mfm"]);
        let g = &v.render_sets[0].geometries[0].groups[1];
        assert!(g.double_sided(), "inherited");
        assert!(!g.alpha_tested(), "own property overrides the mfm");
    }

    #[test]
    fn primitives_names() {
        assert_eq!(
            primitives_name("sets/a/x.static.visual"),
            "sets/a/x.static.primitives"
        );
        assert_eq!(primitives_name("sets/a/x.visual"), "sets/a/x.primitives");
        assert_eq!(primitives_name("sets/a.b/x"), "sets/a.b/x.primitives");
    }

    #[test]
    fn section_resources_split_as_the_engine() {
        let own = "sets/t/x.primitives";
        let split = |n: &str| split_section_resource(own, n);
        assert_eq!(split("vertices"), Some((own.into(), "vertices".into())));
        assert_eq!(
            split("Plane02.vertices"),
            Some((own.into(), "Plane02.vertices".into()))
        );
        assert_eq!(
            split("sets/items/upperskull.static.vertices"),
            Some((
                "sets/items/upperskull.static.primitives".into(),
                "vertices".into()
            ))
        );
        assert_eq!(
            split("sets/town/props/t_candle.candle_wax.vertices"),
            Some((
                "sets/town/props/t_candle.primitives".into(),
                "candle_wax.vertices".into()
            ))
        );
        assert_eq!(
            split("sets/a/y.primitives/trunk.indices"),
            Some(("sets/a/y.primitives".into(), "trunk.indices".into()))
        );
        assert_eq!(split("sets/a/noext"), None);
        assert_eq!(split("sets/a/trailing."), None);
    }
}
