//! `.model` files (model/model.cpp, model_common.hpp, nodeless_model.cpp,
//! nodefull_model.cpp): which visual a model draws and its LOD chain. The
//! bake uses the model's own visual (LOD 0); `parent` and `extent` are kept
//! for reports and tools.

use super::Section;
use crate::error::FormatError;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VisualKind {
    /// `<nodelessVisual>`: static geometry.
    Nodeless,
    /// `<nodefullVisual>`: geometry with a node hierarchy (animated or
    /// skinned).
    Nodefull,
    /// `<billboardVisual>` (the 14.x engine's factory no longer creates
    /// these; tools still list them).
    Billboard,
}

impl VisualKind {
    pub fn tag(self) -> &'static str {
        match self {
            VisualKind::Nodeless => "nodelessVisual",
            VisualKind::Nodefull => "nodefullVisual",
            VisualKind::Billboard => "billboardVisual",
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct ModelFile {
    pub kind: VisualKind,
    /// The visual's resource name without extension, as written (e.g.
    /// `sets/items/upperskull.static`).
    pub visual: String,
    /// The next LOD model, without `.model` (absent or empty: none).
    pub parent: Option<String>,
    /// LOD switch distance in metres, if given.
    pub extent: Option<f64>,
}

/// Reads a model's tree. When several visual elements are present the
/// engine's factory order decides: nodefull, then nodeless (then billboard).
/// A model with none is an error naming the model's root element.
pub fn parse_model(root: &Section) -> Result<ModelFile, FormatError> {
    let (kind, section) = [
        VisualKind::Nodefull,
        VisualKind::Nodeless,
        VisualKind::Billboard,
    ]
    .into_iter()
    .find_map(|kind| root.child(kind.tag()).map(|s| (kind, s)))
    .ok_or_else(|| {
        root.error(
            "model has no <nodelessVisual>, <nodefullVisual> or <billboardVisual>; \
             it draws nothing (re-export it, or remove it from the chunk)",
        )
    })?;
    if section.value.is_empty() {
        return Err(section.error(format!(
            "empty <{}>; expected a visual resource name without extension",
            kind.tag()
        )));
    }
    let parent = root
        .child("parent")
        .map(|p| p.value.clone())
        .filter(|p| !p.is_empty());
    let extent = match root.child("extent") {
        Some(e) => {
            let v = e.as_f64()?;
            if !v.is_finite() {
                return Err(e.error(format!("<extent> must be finite, found {v}")));
            }
            Some(v)
        }
        None => None,
    };
    Ok(ModelFile {
        kind,
        visual: section.value.clone(),
        parent,
        extent,
    })
}

/// The visual resources to try, in order, as the engine does: nodeless
/// `V.static.visual` then `V.visual` (NodelessModel::loadVisual); nodefull
/// only `V.visual` (NodefullModel); billboard `V.visual` then
/// `V.static.visual` (the asset tools' order, the engine no longer loads it).
pub fn visual_candidates(model: &ModelFile) -> Vec<String> {
    let v = &model.visual;
    match model.kind {
        VisualKind::Nodeless => vec![format!("{v}.static.visual"), format!("{v}.visual")],
        VisualKind::Nodefull => vec![format!("{v}.visual")],
        VisualKind::Billboard => vec![format!("{v}.visual"), format!("{v}.static.visual")],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf(name: &str, value: &str, parent: &str) -> Section {
        Section {
            name: name.into(),
            value: value.into(),
            path: format!("{parent}/{name}"),
            ..Default::default()
        }
    }

    fn model(children: &[(&str, &str)]) -> Section {
        Section {
            name: "m.model".into(),
            path: "m.model".into(),
            children: children
                .iter()
                .map(|(n, v)| leaf(n, v, "m.model"))
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn nodeless_with_lod_parent() {
        let m = parse_model(&model(&[
            ("extent", "10.000000"),
            ("parent", "sets/town/props/t_table_lod01"),
            ("nodelessVisual", "sets/town/props/t_table"),
        ]))
        .unwrap();
        assert_eq!(m.kind, VisualKind::Nodeless);
        assert_eq!(m.visual, "sets/town/props/t_table");
        assert_eq!(m.parent.as_deref(), Some("sets/town/props/t_table_lod01"));
        assert_eq!(m.extent, Some(10.0));
        assert_eq!(
            visual_candidates(&m),
            [
                "sets/town/props/t_table.static.visual",
                "sets/town/props/t_table.visual"
            ]
        );
    }

    #[test]
    fn nodefull_wins_and_tries_only_visual() {
        let m = parse_model(&model(&[
            ("nodelessVisual", "a"),
            ("nodefullVisual", "b"),
            ("parent", ""),
        ]))
        .unwrap();
        assert_eq!((m.kind, m.visual.as_str()), (VisualKind::Nodefull, "b"));
        assert_eq!(m.parent, None);
        assert_eq!(m.extent, None);
        assert_eq!(visual_candidates(&m), ["b.visual"]);
        let b = parse_model(&model(&[("billboardVisual", "c")])).unwrap();
        assert_eq!(visual_candidates(&b), ["c.visual", "c.static.visual"]);
    }

    #[test]
    fn errors_name_the_model() {
        let e = parse_model(&model(&[("extent", "5")]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("<m.model>") && e.contains("nodelessVisual"),
            "{e}"
        );
        let e = parse_model(&model(&[("nodelessVisual", "")]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("<m.model/nodelessVisual>"), "{e}");
        let e = parse_model(&model(&[("nodelessVisual", "a"), ("extent", "far")]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("far"), "{e}");
        let e = parse_model(&model(&[("nodelessVisual", "a"), ("extent", "inf")]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("finite"), "{e}");
    }
}
