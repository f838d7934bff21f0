//! One tree for every BigWorld data section, whichever encoding it came from
//! (text XML or packed binary XML), so format readers are written once.
//!
//! BigWorld's own `DataSection` is the model: an element has a tag, a value
//! (its own text, trimmed, mixed content allowed) and ordered children with
//! repeatable tags.

use crate::error::{FormatError, Location};
use glam::{DMat4, DVec3, DVec4};
use std::ops::Range;

#[derive(Debug, Clone, PartialEq, Default)]
pub struct Section {
    pub name: String,
    /// The element's own text with surrounding white space removed. For mixed
    /// content (`<primitiveGroup>\t0\n<material>…`) this is the text before,
    /// between and after the children, joined.
    pub value: String,
    pub children: Vec<Section>,
    /// Slash-separated tag path from the root, for error messages.
    pub path: String,
    /// Byte range of the whole element (`<tag` … `</tag>`) in a text XML
    /// source; for packed XML the range of the element's data.
    pub span: Range<usize>,
}

impl Section {
    pub fn child(&self, name: &str) -> Option<&Section> {
        self.children.iter().find(|c| c.name == name)
    }

    pub fn children_named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Section> + 'a {
        self.children.iter().filter(move |c| c.name == name)
    }

    /// Where this element is, for an error.
    pub fn location(&self) -> Location {
        Location::Element {
            path: self.path.clone(),
            offset: self.span.start as u64,
        }
    }

    pub fn error(&self, message: impl Into<String>) -> FormatError {
        FormatError::new(self.location(), message)
    }

    pub fn text(&self) -> &str {
        &self.value
    }

    /// The named child's trimmed text, if the child exists.
    pub fn child_text(&self, name: &str) -> Option<&str> {
        self.child(name).map(|c| c.value.as_str())
    }

    /// The named child, or an error naming this element and the missing tag.
    pub fn required(&self, name: &str) -> Result<&Section, FormatError> {
        self.child(name)
            .ok_or_else(|| self.error(format!("missing required element <{name}>")))
    }

    pub fn as_bool(&self) -> Result<bool, FormatError> {
        bool_of(&self.value).ok_or_else(|| {
            let other = self.value.to_ascii_lowercase();
            self.error(format!("expected true or false, found `{other}`"))
        })
    }

    pub fn as_i64(&self) -> Result<i64, FormatError> {
        let text = self.value.as_str();
        i64_of(text).ok_or_else(|| self.error(format!("expected an integer, found `{text}`")))
    }

    pub fn as_f64(&self) -> Result<f64, FormatError> {
        let text = self.value.as_str();
        text.parse::<f64>()
            .map_err(|_| self.error(format!("expected a number, found `{text}`")))
    }

    /// Every white-space separated number of the value.
    pub fn as_f64s(&self) -> Result<Vec<f64>, FormatError> {
        self.value
            .split_ascii_whitespace()
            .map(|word| {
                word.parse::<f64>()
                    .map_err(|_| self.error(format!("expected numbers, found `{word}`")))
            })
            .collect()
    }

    pub fn as_vec3(&self) -> Result<DVec3, FormatError> {
        let values = self.as_f64s()?;
        match values.as_slice() {
            [x, y, z] => Ok(DVec3::new(*x, *y, *z)),
            _ => Err(self.error(format!("expected 3 numbers, found {}", values.len()))),
        }
    }

    /// A BigWorld matrix: `<row0>`..`<row3>` children (text XML) or twelve
    /// numbers in the value (packed XML stores it so). Rows are row-vector
    /// (D3D) convention: rows 0–2 the basis, row 3 the translation.
    /// Missing rows default to identity rows, as the engine's `readMatrix34`.
    pub fn as_matrix(&self) -> Result<DMat4, FormatError> {
        let rows = ROW_TAGS.map(|tag| self.child(tag).map(|row| row.value.as_str()));
        matrix_of(rows, &self.value).map_err(|bad| match bad.row {
            Some(i) => self
                .children_named(ROW_TAGS[i])
                .next()
                .unwrap_or(self)
                .error(bad.message),
            None => self.error(bad.message),
        })
    }
}

/// The tags of a matrix's rows.
pub const ROW_TAGS: [&str; 4] = ["row0", "row1", "row2", "row3"];

/// A value that is not what was asked: the row it is in (`None`: the
/// element's own value) and what is wrong.
pub struct BadValue {
    pub row: Option<usize>,
    pub message: String,
}

/// A value as a boolean, BigWorld's way (`true`/`false`/`1`/`0`, any case).
pub fn bool_of(value: &str) -> Option<bool> {
    match value.to_ascii_lowercase().as_str() {
        "true" | "1" => Some(true),
        "false" | "0" => Some(false),
        _ => None,
    }
}

/// A value as an integer; the engine's asInt tolerates a float spelling
/// such as `128.0`.
pub fn i64_of(text: &str) -> Option<i64> {
    text.parse::<i64>().ok().or_else(|| {
        text.parse::<f64>()
            .ok()
            .filter(|v| v.fract() == 0.0 && v.abs() < 9.0e15)
            .map(|v| v as i64)
    })
}

/// A BigWorld matrix from its rows' values (`rows[i]`: the first
/// `<row{i}>`, if any) or, without rows, twelve numbers in `value`. Rows
/// are row-vector (D3D) convention: rows 0–2 the basis, row 3 the
/// translation. Missing rows default to identity rows, as the engine's
/// `readMatrix34`.
pub fn matrix_of(rows: [Option<&str>; 4], value: &str) -> Result<DMat4, BadValue> {
    let numbers = |text: &str, row: Option<usize>| -> Result<Vec<f64>, BadValue> {
        text.split_ascii_whitespace()
            .map(|word| {
                word.parse::<f64>().map_err(|_| BadValue {
                    row,
                    message: format!("expected numbers, found `{word}`"),
                })
            })
            .collect()
    };
    let mut out = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ZERO];
    if rows.iter().any(Option::is_some) {
        for (i, (row, text)) in out.iter_mut().zip(rows).enumerate() {
            let Some(text) = text else { continue };
            match numbers(text, Some(i))?.as_slice() {
                [x, y, z] => *row = DVec3::new(*x, *y, *z),
                values => {
                    return Err(BadValue {
                        row: Some(i),
                        message: format!("expected 3 numbers, found {}", values.len()),
                    })
                }
            }
        }
    } else {
        let values = numbers(value, None)?;
        if values.len() != 12 {
            return Err(BadValue {
                row: None,
                message: format!(
                    "expected <row0>..<row3> or 12 numbers, found {} numbers",
                    values.len()
                ),
            });
        }
        for (i, row) in out.iter_mut().enumerate() {
            *row = DVec3::new(values[3 * i], values[3 * i + 1], values[3 * i + 2]);
        }
    }
    // glam is column-vector; a row-vector matrix M with p' = p·M is the
    // column-vector matrix Mᵀ, whose columns are M's rows.
    Ok(DMat4::from_cols(
        DVec4::from((out[0], 0.0)),
        DVec4::from((out[1], 0.0)),
        DVec4::from((out[2], 0.0)),
        DVec4::from((out[3], 1.0)),
    ))
}

/// Hand-built trees for unit tests of the format readers.
#[cfg(test)]
pub(crate) mod build {
    use super::Section;

    pub fn el(name: &str, value: &str, children: Vec<Section>) -> Section {
        Section {
            name: name.into(),
            value: value.into(),
            children,
            ..Default::default()
        }
    }

    /// Fills in every element's `path` as a parser would.
    pub fn with_paths(mut s: Section, parent: &str) -> Section {
        s.path = if parent.is_empty() {
            s.name.clone()
        } else {
            format!("{parent}/{}", s.name)
        };
        let path = s.path.clone();
        s.children = s
            .children
            .into_iter()
            .map(|c| with_paths(c, &path))
            .collect();
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf(name: &str, value: &str) -> Section {
        Section {
            name: name.into(),
            value: value.into(),
            path: name.into(),
            ..Default::default()
        }
    }

    #[test]
    fn matrix_from_rows_is_row_vector_convention() {
        let m = Section {
            name: "transform".into(),
            children: vec![
                leaf("row0", "0 0 -1"),
                leaf("row1", "0 1 0"),
                leaf("row2", "1 0 0"),
                leaf("row3", "10 20 30"),
            ],
            ..Default::default()
        }
        .as_matrix()
        .unwrap();
        // p·M: local +x maps to row0 = (0,0,-1), then translate.
        let p = m.transform_point3(DVec3::X);
        assert_eq!(p, DVec3::new(10.0, 20.0, 29.0));
    }

    #[test]
    fn matrix_from_twelve_numbers_matches_rows() {
        let packed = leaf("transform", "0 0 -1 0 1 0 1 0 0 10 20 30").as_matrix();
        let rows = Section {
            name: "transform".into(),
            children: vec![
                leaf("row0", "0 0 -1"),
                leaf("row1", "0 1 0"),
                leaf("row2", "1 0 0"),
                leaf("row3", "10 20 30"),
            ],
            ..Default::default()
        }
        .as_matrix();
        assert_eq!(packed.unwrap(), rows.unwrap());
    }

    #[test]
    fn bad_numbers_name_the_element() {
        let err = leaf("row3", "1 two 3").as_vec3().unwrap_err();
        assert!(err.to_string().contains("<row3>"), "{err}");
        assert!(err.to_string().contains("two"), "{err}");
    }

    #[test]
    fn bools_and_ints() {
        assert!(leaf("b", "TRUE").as_bool().unwrap());
        assert!(!leaf("b", "false").as_bool().unwrap());
        assert!(leaf("b", "maybe").as_bool().is_err());
        assert_eq!(leaf("i", "-48").as_i64().unwrap(), -48);
        assert_eq!(leaf("i", "128.0").as_i64().unwrap(), 128);
        assert!(leaf("i", "1.5").as_i64().is_err());
    }
}
