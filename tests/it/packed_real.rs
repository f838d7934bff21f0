//! Packed binary XML on real data: every real text file, packed the way
//! `res_packer` would and read back, gives the same tree, so every reader
//! works unchanged on packed resources.

use crate::support::realdata;
use crate::xml_real::files_with_extensions;
use shadowcull::formats::visual::parse_visual;
use shadowcull::formats::{packed_xml, parse_data_section, xml, Section};

fn same_tree(a: &Section, b: &Section) -> bool {
    a.value == b.value
        && a.children.len() == b.children.len()
        && a.children
            .iter()
            .zip(&b.children)
            .all(|(x, y)| x.name == y.name && same_tree(x, y))
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
        assert!(same_tree(&text, &back), "{}", path.display());
        assert_eq!(back.name, packed_xml::ROOT_NAME);
        if path.extension().is_some_and(|e| e == "visual") {
            let a = parse_visual(&text).unwrap();
            let b = parse_visual(&back).unwrap();
            assert_eq!(a.nodes, b.nodes, "{}", path.display());
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
