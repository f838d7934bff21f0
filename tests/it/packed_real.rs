//! Packed binary XML on real data: every real text file, packed the way
//! `res_packer` does, reads back as the same tree (a six-decimal float as
//! the same `f32`, a row matrix as its twelve numbers), so every reader
//! works unchanged on packed resources; and the packed file, decoded and
//! encoded again without edits, is the same bytes.

use crate::support::realdata;
use crate::xml_real::files_with_extensions;
use shadowcull::formats::packed_xml::{self, Document};
use shadowcull::formats::visual::parse_visual;
use shadowcull::formats::{parse_data_section, xml, Section};

/// A value's words as `f32` bits, if every word is a number.
fn f32_words(text: &str) -> Option<Vec<u32>> {
    text.split_ascii_whitespace()
        .map(|w| w.parse::<f32>().ok().map(f32::to_bits))
        .collect()
}

/// A row matrix (`row0`..`row3` as the only children) as its twelve numbers.
fn matrix_words(section: &Section) -> Option<Vec<u32>> {
    let rows = ["row0", "row1", "row2", "row3"];
    if section.children.len() != 4 || rows.iter().any(|r| section.child(r).is_none()) {
        return None;
    }
    let words = section
        .children
        .iter()
        .map(|c| f32_words(&c.value).filter(|w| w.len() == 3))
        .collect::<Option<Vec<_>>>()?;
    Some(words.concat())
}

/// What a reader sees of `packed` is what it sees of `text`: the same tags
/// and values, numbers the engine stores as floats equal as `f32`.
fn same_as_read(text: &Section, packed: &Section) -> bool {
    if let Some(matrix) = matrix_words(text) {
        return packed.children.is_empty() && f32_words(&packed.value) == Some(matrix);
    }
    let value_read = text.value == packed.value
        || (packed_xml::guess_value(&text.value).kind == packed_xml::ValueType::Float
            && f32_words(&text.value) == f32_words(&packed.value));
    value_read
        && text.children.len() == packed.children.len()
        && text
            .children
            .iter()
            .zip(&packed.children)
            .all(|(x, y)| x.name == y.name && same_as_read(x, y))
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn every_real_text_file_survives_packing() {
    let Some(root) = realdata("every_real_text_file_survives_packing") else {
        return;
    };
    let files = files_with_extensions(&root, &[".chunk", ".visual", ".model", "space.settings"]);
    assert!(files.len() > 100);
    for path in &files {
        let text = xml::parse(&std::fs::read(path).unwrap()).unwrap();
        let packed = packed_xml::write(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(packed.starts_with(&packed_xml::MAGIC));
        let back =
            parse_data_section(&packed).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(same_as_read(&text, &back), "{}", path.display());
        let document = Document::parse(&packed).unwrap();
        assert_eq!(
            document.to_bytes().unwrap(),
            packed,
            "{}: decoded and encoded again",
            path.display()
        );
        assert_eq!(back.name, packed_xml::ROOT_NAME);
        if path.extension().is_some_and(|e| e == "visual") {
            let a = parse_visual(&text).unwrap();
            let b = parse_visual(&back).unwrap();
            // The engine stores transforms as f32: equal at that precision.
            let nodes = |v: &shadowcull::formats::visual::Visual| {
                v.nodes
                    .iter()
                    .map(|n| (n.identifier.clone(), n.parent, n.transform.as_mat4()))
                    .collect::<Vec<_>>()
            };
            assert_eq!(nodes(&a), nodes(&b), "{}", path.display());
            assert_eq!(a.render_sets.len(), b.render_sets.len());
            for (x, y) in a.render_sets.iter().zip(&b.render_sets) {
                assert_eq!(x.nodes, y.nodes);
                for (g, h) in x.geometries.iter().zip(&y.geometries) {
                    let flags = |g: &shadowcull::formats::visual::Geometry| {
                        g.groups
                            .iter()
                            .map(|p| (p.index, p.flags))
                            .collect::<Vec<_>>()
                    };
                    assert_eq!(flags(g), flags(h), "{}", path.display());
                }
            }
        }
    }
}
