//! `.chunk` files (chunk/chunk.cpp, chunk_model.cpp): the instances a chunk
//! places (`<model>`, `<shell>`, `<speedtree>`), its terrain, (indoor
//! chunks) its own transform, and how many items of every kind it holds,
//! so nothing the bake leaves out goes unmentioned. None of it depends on
//! the `<shadow>`s a bake writes (`formats::shadow_write` rewrites those
//! from the parsed tree), so a chunk reads the same before and after.

use super::Section;
use crate::error::FormatError;
use glam::DMat4;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// What a placed instance element is: a model, an indoor shell, or a
/// SpeedTree placement (docs/contract.md §2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum InstanceKind {
    Model,
    Shell,
    SpeedTree,
}

impl InstanceKind {
    pub fn tag(self) -> &'static str {
        match self {
            InstanceKind::Model => "model",
            InstanceKind::Shell => "shell",
            InstanceKind::SpeedTree => SPEEDTREE_TAG,
        }
    }

    /// The kind of instance an element with this tag is, if it is one.
    pub fn from_tag(tag: &str) -> Option<InstanceKind> {
        match tag {
            "model" => Some(InstanceKind::Model),
            "shell" => Some(InstanceKind::Shell),
            SPEEDTREE_TAG => Some(InstanceKind::SpeedTree),
            _ => None,
        }
    }

    /// A `<model>` or `<shell>`: the elements that name `.model`
    /// resources and are counted by [`instance_elements`].
    pub fn names_models(self) -> bool {
        matches!(self, InstanceKind::Model | InstanceKind::Shell)
    }
}

/// Tag of a SpeedTree placement.
pub const SPEEDTREE_TAG: &str = "speedtree";

/// The chunk's model instance elements in document order: the direct
/// children of the root tagged `<model>` or `<shell>`. Their position in
/// this sequence is the instance `index` everywhere (report, write-back),
/// so both the reader and the shadow writer use this one definition.
pub fn instance_elements(root: &Section) -> impl Iterator<Item = (InstanceKind, &Section)> + '_ {
    root.children.iter().filter_map(|e| {
        InstanceKind::from_tag(&e.name)
            .filter(|kind| kind.names_models())
            .map(|kind| (kind, e))
    })
}

/// The chunk's `<speedtree>` elements in document order: the direct
/// children of the root with that tag. A tree's position here is its
/// `index` (report, write-back), as [`instance_elements`] is a model's.
pub fn speedtree_elements(root: &Section) -> impl Iterator<Item = &Section> + '_ {
    root.children.iter().filter(|e| e.name == SPEEDTREE_TAG)
}

/// The chunk's terrain element: the first direct `<terrain>` child of the
/// root, as the engine reads it.
pub fn terrain_element(root: &Section) -> Option<&Section> {
    root.child("terrain")
}

/// One `<model>` or `<shell>` element.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceElement {
    pub kind: InstanceKind,
    /// 0-based position among the chunk's `<model>`/`<shell>` elements in
    /// document order (the report's `index`).
    pub index: usize,
    /// The `<resource>` parts, in order (`.model` resource names); one
    /// list shared by a chunk's elements that name the same models, and by
    /// the instances placed from them.
    pub resources: Arc<[String]>,
    /// Local-to-chunk transform; identity when the element has none, as the
    /// engine reads it.
    pub transform: DMat4,
    /// `<castsShadow>` (14.x), else the legacy `<editorOnly><castsShadow>`,
    /// else true.
    pub casts_shadow: bool,
    /// Tag path, for messages (the same for every element of a kind).
    pub path: Arc<str>,
}

/// One `<speedtree>` element: a SpeedTree placement. The `.spt` itself is
/// never read (a proprietary format, often not shipped): its geometry
/// comes from a proxy in the settings file (docs/contract.md §3).
#[derive(Debug, Clone, PartialEq)]
pub struct SpeedTreeElement {
    /// 0-based position among the chunk's `<speedtree>` elements in
    /// document order (the report's `index`).
    pub index: usize,
    /// `<spt>`: the tree's `.spt` resource name; empty when the element
    /// has none.
    pub spt: String,
    /// `<seed>` and `<visibilityMask>`: read and checked, not used by the
    /// bake (a proxy is the same for every seed).
    pub seed: Option<i64>,
    pub visibility_mask: Option<i64>,
    /// Local-to-chunk transform: twelve numbers in `<transform>` or
    /// `<row0>`..`<row3>`, as a model's; identity when absent.
    pub transform: DMat4,
    /// Tag path, for messages.
    pub path: String,
}

#[derive(Debug, Clone, PartialEq)]
pub struct TerrainElement {
    /// e.g. `0000fffdo.cdata/terrain2`, relative to the space folder.
    pub resource: String,
    pub path: String,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ChunkFile {
    pub root_name: String,
    /// An indoor chunk's own `<transform>` (outdoor chunks have none).
    pub transform: Option<DMat4>,
    pub instances: Vec<InstanceElement>,
    pub speedtrees: Vec<SpeedTreeElement>,
    pub terrain: Option<TerrainElement>,
    /// How many direct children of the root carry each tag: every item
    /// kind the chunk holds, whether the bake models it or not.
    pub items: BTreeMap<String, usize>,
}

pub fn parse(root: &Section) -> Result<ChunkFile, FormatError> {
    let transform = root
        .child("transform")
        .map(Section::as_matrix)
        .transpose()?;
    let mut instances = Vec::new();
    let mut shared = SharedValues::default();
    for (kind, element) in instance_elements(root) {
        let resources = shared.list(
            element
                .children_named("resource")
                .map(|r| r.value.clone())
                .collect(),
        );
        let transform = match element.child("transform") {
            Some(t) => t.as_matrix()?,
            None => DMat4::IDENTITY,
        };
        let casts_shadow = match element.child("castsShadow") {
            Some(flag) => flag.as_bool()?,
            None => match element
                .child("editorOnly")
                .and_then(|e| e.child("castsShadow"))
            {
                Some(flag) => flag.as_bool()?,
                None => true,
            },
        };
        instances.push(InstanceElement {
            kind,
            index: instances.len(),
            resources,
            transform,
            casts_shadow,
            path: shared.path(&element.path),
        });
    }
    let speedtrees = speedtree_elements(root)
        .enumerate()
        .map(|(index, element)| parse_speedtree(index, element))
        .collect::<Result<_, _>>()?;
    let terrain = match terrain_element(root) {
        Some(element) => Some(TerrainElement {
            resource: element.required("resource")?.value.clone(),
            path: element.path.clone(),
        }),
        None => None,
    };
    let mut items = BTreeMap::new();
    for child in &root.children {
        *items.entry(child.name.clone()).or_insert(0) += 1;
    }
    Ok(ChunkFile {
        root_name: root.name.clone(),
        transform,
        instances,
        speedtrees,
        terrain,
        items,
    })
}

/// The values a chunk's elements share, made once per chunk: a chunk
/// places many instances of a few models, and each instance's copy of
/// its resource list and tag path would be held by the scene for the
/// whole bake.
#[derive(Default)]
pub(crate) struct SharedValues {
    lists: HashMap<Vec<String>, Arc<[String]>>,
    paths: HashMap<String, Arc<str>>,
}

impl SharedValues {
    /// The chunk's one list equal to `resources`.
    pub(crate) fn list(&mut self, resources: Vec<String>) -> Arc<[String]> {
        self.lists
            .entry(resources)
            .or_insert_with_key(|list| Arc::from(list.as_slice()))
            .clone()
    }

    /// The chunk's one tag path equal to `path`.
    pub(crate) fn path(&mut self, path: &str) -> Arc<str> {
        if let Some(shared) = self.paths.get(path) {
            return shared.clone();
        }
        let shared: Arc<str> = Arc::from(path);
        self.paths.insert(path.to_string(), shared.clone());
        shared
    }
}

/// One `<speedtree>` element; a value that does not read (a transform
/// that is not 12 numbers, a seed that is no integer) is an error naming
/// it, as for a model.
fn parse_speedtree(index: usize, element: &Section) -> Result<SpeedTreeElement, FormatError> {
    let integer = |tag: &str| element.child(tag).map(Section::as_i64).transpose();
    Ok(SpeedTreeElement {
        index,
        spt: element.child_text("spt").unwrap_or_default().to_string(),
        seed: integer("seed")?,
        visibility_mask: integer("visibilityMask")?,
        transform: match element.child("transform") {
            Some(t) => t.as_matrix()?,
            None => DMat4::IDENTITY,
        },
        path: element.path.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::xml;
    use glam::DVec3;

    const CHUNK: &str = "<root>\n\t<shell>\n\t\t<resource>\tsets/a/shell.model\t</resource>\n\t\t<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>\n\t\t</editorOnly>\n\t</shell>\n\t<entity>\n\t\t<type>\tInfo\t</type>\n\t</entity>\n\t<model>\n\t\t<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>\n\t\t</editorOnly>\n\t\t<resource>\tsets/b.model\t</resource>\n\t\t<resource>\tsets/c.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t-1 0 0\t</row0>\n\t\t\t<row1>\t0 1 0\t</row1>\n\t\t\t<row2>\t0 0 1\t</row2>\n\t\t\t<row3>\t5 6 7\t</row3>\n\t\t</transform>\n\t\t<castsShadow>\ttrue\t</castsShadow>\n\t</model>\n\t<terrain>\n\t\t<resource>\t00000000o.cdata/terrain2\t</resource>\n\t</terrain>\n</root>\n";

    #[test]
    fn elements_naming_the_same_resources_share_them() {
        let text = "<root>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n\t<model>\n\t\t<resource>\tb.model\t</resource>\n\t</model>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n</root>\n";
        let chunk = parse(&xml::parse(text.as_bytes()).unwrap()).unwrap();
        let [a, b, again] = &chunk.instances[..] else {
            panic!("three elements");
        };
        assert!(Arc::ptr_eq(&a.resources, &again.resources));
        assert!(!Arc::ptr_eq(&a.resources, &b.resources));
        assert_eq!(*b.resources, ["b.model"]);
        assert!(Arc::ptr_eq(&a.path, &b.path));
    }

    #[test]
    fn instances_in_document_order_with_flags() {
        let chunk = parse(&xml::parse(CHUNK.as_bytes()).unwrap()).unwrap();
        assert_eq!(chunk.instances.len(), 2);
        let shell = &chunk.instances[0];
        assert_eq!((shell.kind, shell.index), (InstanceKind::Shell, 0));
        assert!(!shell.casts_shadow, "legacy editorOnly flag applies");
        assert_eq!(shell.transform, DMat4::IDENTITY);
        let model = &chunk.instances[1];
        assert_eq!((model.kind, model.index), (InstanceKind::Model, 1));
        assert_eq!(*model.resources, ["sets/b.model", "sets/c.model"]);
        assert!(
            model.casts_shadow,
            "the 14.x direct child wins over editorOnly"
        );
        assert!(model.transform.determinant() < 0.0);
        assert_eq!(
            model.transform.transform_point3(DVec3::X),
            DVec3::new(4.0, 6.0, 7.0)
        );
        assert_eq!(chunk.terrain.unwrap().resource, "00000000o.cdata/terrain2");
        assert_eq!(chunk.transform, None);
    }

    #[test]
    fn bad_flag_names_the_element() {
        let text = "<root><model><resource>a.model</resource><castsShadow>perhaps</castsShadow></model></root>";
        let err = parse(&xml::parse(text.as_bytes()).unwrap()).unwrap_err();
        assert!(err.to_string().contains("root/model/castsShadow"), "{err}");
    }

    const TREES: &str = "<root>\n\t<speedtree>\n\t\t<visibilityMask>\t255\t</visibilityMask>\n\t\t<spt>\tspeedtree/m/Bush2_1.spt\t</spt>\n\t\t<seed>\t4711\t</seed>\n\t\t<transform>\t1.3 0 0 0 1.69 0 0 0 -0.8 5 6 7\t</transform>\n\t\t<reflectionVisible>\ttrue\t</reflectionVisible>\n\t</speedtree>\n\t<model>\n\t\t<resource>\ta.model\t</resource>\n\t</model>\n\t<speedtree>\n\t\t<spt>\tspeedtree/m/Oak.spt\t</spt>\n\t\t<transform>\n\t\t\t<row0>\t1.3 0 0\t</row0>\n\t\t\t<row1>\t0 1.69 0\t</row1>\n\t\t\t<row2>\t0 0 -0.8\t</row2>\n\t\t\t<row3>\t5 6 7\t</row3>\n\t\t</transform>\n\t</speedtree>\n\t<vlo>\n\t\t<uid>\tA.B.C.D\t</uid>\n\t</vlo>\n\t<vlo />\n</root>\n";

    #[test]
    fn speedtrees_are_read_in_their_own_order_with_both_transform_forms() {
        let root = xml::parse(TREES.as_bytes()).unwrap();
        let packed = crate::formats::packed_xml::write(&root).unwrap();
        for (encoding, root) in [
            ("text", root),
            (
                "packed",
                crate::formats::packed_xml::parse(&packed).unwrap(),
            ),
        ] {
            let chunk = parse(&root).unwrap();
            assert_eq!(chunk.instances.len(), 1, "{encoding}: trees are no models");
            let [first, second] = &chunk.speedtrees[..] else {
                panic!("{encoding}: {:?}", chunk.speedtrees);
            };
            assert_eq!((first.index, second.index), (0, 1));
            assert_eq!(first.spt, "speedtree/m/Bush2_1.spt");
            assert_eq!((first.seed, first.visibility_mask), (Some(4711), Some(255)));
            assert_eq!((second.seed, second.visibility_mask), (None, None));
            assert_eq!(
                first.transform, second.transform,
                "{encoding}: twelve numbers and rows are one placement"
            );
            // Row-vector: local x scales by 1.3, y by 1.69, z mirrors.
            let p = first.transform.transform_point3(DVec3::new(1.0, 1.0, 1.0));
            assert!((p - DVec3::new(6.3, 7.69, 6.2)).length() < 1e-12, "{p}");
            assert!(first.transform.determinant() < 0.0);
            assert_eq!(first.path, "root/speedtree");
            assert_eq!(chunk.items["speedtree"], 2);
            assert_eq!(chunk.items["vlo"], 2);
            assert_eq!(chunk.items["model"], 1);
            assert_eq!(speedtree_elements(&root).count(), 2);
            assert_eq!(instance_elements(&root).count(), 1);
        }
    }

    #[test]
    fn a_speedtree_value_that_does_not_read_names_the_element() {
        for (bad, element) in [
            ("<seed>x</seed>", "root/speedtree/seed"),
            (
                "<visibilityMask>1.5</visibilityMask>",
                "root/speedtree/visibilityMask",
            ),
            ("<transform>1 2 3</transform>", "root/speedtree/transform"),
        ] {
            let text = format!("<root><speedtree><spt>a.spt</spt>{bad}</speedtree></root>");
            let err = parse(&xml::parse(text.as_bytes()).unwrap()).unwrap_err();
            assert!(err.to_string().contains(element), "{bad}: {err}");
        }
        let text = "<root><speedtree><seed>1</seed></speedtree></root>";
        let chunk = parse(&xml::parse(text.as_bytes()).unwrap()).unwrap();
        assert_eq!(
            chunk.speedtrees[0].spt, "",
            "no <spt>: the scene makes it a problem"
        );
        assert_eq!(chunk.speedtrees[0].transform, DMat4::IDENTITY);
    }
}
