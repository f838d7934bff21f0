//! `.chunk` files (chunk/chunk.cpp, chunk_model.cpp): the instances a chunk
//! places, its terrain, and (indoor chunks) its own transform. Everything else
//! in a chunk is left alone; element spans let the bake rewrite `<shadow>`
//! without touching the rest.

use super::Section;
use crate::error::FormatError;
use glam::DMat4;
use std::ops::Range;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum InstanceKind {
    Model,
    Shell,
}

impl InstanceKind {
    pub fn tag(self) -> &'static str {
        match self {
            InstanceKind::Model => "model",
            InstanceKind::Shell => "shell",
        }
    }

    /// The kind of instance an element with this tag is, if it is one.
    pub fn from_tag(tag: &str) -> Option<InstanceKind> {
        match tag {
            "model" => Some(InstanceKind::Model),
            "shell" => Some(InstanceKind::Shell),
            _ => None,
        }
    }
}

/// The chunk's instance elements in document order: the direct children of
/// the root tagged `<model>` or `<shell>`. Their position in this sequence is
/// the instance `index` everywhere (report, write-back), so both the reader
/// and the shadow writer use this one definition.
pub fn instance_elements(root: &Section) -> impl Iterator<Item = (InstanceKind, &Section)> + '_ {
    root.children
        .iter()
        .filter_map(|e| InstanceKind::from_tag(&e.name).map(|kind| (kind, e)))
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
    /// The `<resource>` parts, in order (`.model` resource names).
    pub resources: Vec<String>,
    /// Local-to-chunk transform; identity when the element has none, as the
    /// engine reads it.
    pub transform: DMat4,
    /// `<castsShadow>` (14.x), else the legacy `<editorOnly><castsShadow>`,
    /// else true.
    pub casts_shadow: bool,
    /// Tag path and byte span, for messages and the write-back.
    pub path: String,
    pub span: Range<usize>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct TerrainElement {
    /// e.g. `0000fffdo.cdata/terrain2`, relative to the space folder.
    pub resource: String,
    pub path: String,
    pub span: Range<usize>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ChunkFile {
    pub root_name: String,
    /// An indoor chunk's own `<transform>` (outdoor chunks have none).
    pub transform: Option<DMat4>,
    pub instances: Vec<InstanceElement>,
    pub terrain: Option<TerrainElement>,
}

pub fn parse(root: &Section) -> Result<ChunkFile, FormatError> {
    let transform = root
        .child("transform")
        .map(Section::as_matrix)
        .transpose()?;
    let mut instances = Vec::new();
    for (kind, element) in instance_elements(root) {
        let resources = element
            .children_named("resource")
            .map(|r| r.value.clone())
            .collect();
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
            path: element.path.clone(),
            span: element.span.clone(),
        });
    }
    let terrain = match terrain_element(root) {
        Some(element) => Some(TerrainElement {
            resource: element.required("resource")?.value.clone(),
            path: element.path.clone(),
            span: element.span.clone(),
        }),
        None => None,
    };
    Ok(ChunkFile {
        root_name: root.name.clone(),
        transform,
        instances,
        terrain,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::xml;
    use glam::DVec3;

    const CHUNK: &str = "<root>\n\t<shell>\n\t\t<resource>\tsets/a/shell.model\t</resource>\n\t\t<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>\n\t\t</editorOnly>\n\t</shell>\n\t<entity>\n\t\t<type>\tInfo\t</type>\n\t</entity>\n\t<model>\n\t\t<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>\n\t\t</editorOnly>\n\t\t<resource>\tsets/b.model\t</resource>\n\t\t<resource>\tsets/c.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t-1 0 0\t</row0>\n\t\t\t<row1>\t0 1 0\t</row1>\n\t\t\t<row2>\t0 0 1\t</row2>\n\t\t\t<row3>\t5 6 7\t</row3>\n\t\t</transform>\n\t\t<castsShadow>\ttrue\t</castsShadow>\n\t</model>\n\t<terrain>\n\t\t<resource>\t00000000o.cdata/terrain2\t</resource>\n\t</terrain>\n</root>\n";

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
        assert_eq!(model.resources, ["sets/b.model", "sets/c.model"]);
        assert!(
            model.casts_shadow,
            "the 14.x direct child wins over editorOnly"
        );
        assert!(model.transform.determinant() < 0.0);
        assert_eq!(
            model.transform.transform_point3(DVec3::X),
            DVec3::new(4.0, 6.0, 7.0)
        );
        assert!(CHUNK[model.span.clone()].starts_with("<model>"));
        assert!(CHUNK[model.span.clone()].ends_with("</model>"));
        assert_eq!(chunk.terrain.unwrap().resource, "00000000o.cdata/terrain2");
        assert_eq!(chunk.transform, None);
    }

    #[test]
    fn bad_flag_names_the_element() {
        let text = "<root><model><resource>a.model</resource><castsShadow>perhaps</castsShadow></model></root>";
        let err = parse(&xml::parse(text.as_bytes()).unwrap()).unwrap_err();
        assert!(err.to_string().contains("root/model/castsShadow"), "{err}");
    }
}
