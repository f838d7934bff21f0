//! Shadow write-back (docs/contract.md §5) on every real arctic chunk and on generated
//! chunks: the bytes outside `<shadow>` are kept, a second write changes
//! nothing, and the masks read back as written — in text and packed XML.

use crate::packed_world::differences_outside_shadows;
use crate::support::realdata;
use crate::xml_real::files_with_extensions;
use shadowcull::formats::chunk::{self, instance_elements, speedtree_elements, terrain_element};
use shadowcull::formats::shadow_write::{
    read_chunk_shadows, write_shadows, ChunkShadows, InstanceShadow,
};
use shadowcull::formats::{packed_xml, xml, Section};
use shadowcull::gen::{generate, Preset};
use shadowcull::rng::Rng;
use std::ops::Range;

/// Masks for a chunk: every fifth instance left alone, every seventh
/// receiver-only (all zeros), the rest random shapes and bits.
fn masks_for(root: &Section, seed: u64) -> ChunkShadows {
    let mut rng = Rng::new(seed);
    let instances = instance_elements(root)
        .enumerate()
        .map(|(i, _)| {
            if i % 5 == 4 {
                return None;
            }
            let zero = i % 7 == 6;
            let sets = (0..1 + rng.below(3))
                .map(|_| {
                    (0..1 + rng.below(2))
                        .map(|_| {
                            (0..1 + rng.below(4))
                                .map(|_| if zero { 0 } else { rng.next_u64() as u32 })
                                .collect()
                        })
                        .collect()
                })
                .collect();
            Some(InstanceShadow::from_groups(sets))
        })
        .collect();
    let terrain = terrain_element(root).map(|_| rng.next_u64() as u32);
    let speedtrees = vec![None; speedtree_elements(root).count()];
    ChunkShadows {
        instances,
        speedtrees,
        terrain,
    }
}

/// Where a direct `<shadow>` of an instance or the terrain is, widened to
/// its whole line when it stands alone on one (written independently of the
/// writer, as the oracle).
fn shadow_cuts(text: &[u8]) -> Vec<Range<usize>> {
    let root = xml::parse(text).unwrap();
    let mut cuts: Vec<Range<usize>> = instance_elements(&root)
        .map(|(_, e)| e)
        .chain(terrain_element(&root))
        .flat_map(|e| e.children_named("shadow"))
        .map(|s| {
            let line_start = text[..s.span.start]
                .iter()
                .rposition(|&b| b == b'\n')
                .map_or(0, |i| i + 1);
            let line_end = text[s.span.end..]
                .iter()
                .position(|&b| b == b'\n')
                .map(|i| s.span.end + i + 1);
            let blank = |bytes: &[u8]| bytes.iter().all(|b| matches!(b, b' ' | b'\t' | b'\r'));
            match line_end {
                Some(end)
                    if blank(&text[line_start..s.span.start])
                        && blank(&text[s.span.end..end - 1]) =>
                {
                    line_start..end
                }
                _ => s.span.clone(),
            }
        })
        .collect();
    cuts.sort_by_key(|r| r.start);
    cuts
}

fn without_shadows(text: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut pos = 0;
    for cut in shadow_cuts(text) {
        out.extend_from_slice(&text[pos..cut.start]);
        pos = cut.end;
    }
    out.extend_from_slice(&text[pos..]);
    out
}

/// Names, values and children, ignoring direct `<shadow>` children of
/// instances and terrain.
fn same_tree_but_shadows(a: &Section, b: &Section, depth: usize) -> bool {
    let keep = |s: &&Section| !(depth == 1 && s.name == "shadow");
    let ac: Vec<&Section> = a.children.iter().filter(keep).collect();
    let bc: Vec<&Section> = b.children.iter().filter(keep).collect();
    a.name == b.name
        && a.value == b.value
        && ac.len() == bc.len()
        && ac
            .iter()
            .zip(&bc)
            .all(|(x, y)| same_tree_but_shadows(x, y, depth + 1))
}

/// Every check on one text chunk; returns how many `<shadow>`s were written.
fn check_chunk(name: &str, original: &[u8], seed: u64) -> usize {
    let root = xml::parse(original).unwrap_or_else(|e| panic!("{name}: {e}"));
    let shadows = masks_for(&root, seed);
    let out = write_shadows(original, &shadows).unwrap_or_else(|e| panic!("{name}: {e}"));

    // Preservation: outside the <shadow> lines, byte for byte.
    assert_eq!(without_shadows(&out), without_shadows(original), "{name}");
    // Idempotence.
    assert_eq!(
        write_shadows(&out, &shadows).unwrap(),
        out,
        "{name}: not idempotent"
    );
    // Parse-back: the masks, and everything the bake reads, unchanged.
    let back_root = xml::parse(&out).unwrap();
    let back = read_chunk_shadows(&back_root).unwrap();
    let before = read_chunk_shadows(&root).unwrap();
    for (i, want) in shadows.instances.iter().enumerate() {
        let expected = if want.is_some() {
            want
        } else {
            &before.instances[i]
        };
        assert_eq!(&back.instances[i], expected, "{name}: instance {i}");
    }
    assert_eq!(back.terrain, shadows.terrain, "{name}");
    let (a, b) = (
        chunk::parse(&root).unwrap(),
        chunk::parse(&back_root).unwrap(),
    );
    assert_eq!(a.instances.len(), b.instances.len());
    for (x, y) in a.instances.iter().zip(&b.instances) {
        assert_eq!(
            (x.kind, x.index, &x.resources, x.transform, x.casts_shadow),
            (y.kind, y.index, &y.resources, y.transform, y.casts_shadow),
            "{name}"
        );
    }
    assert_eq!(a.terrain.map(|t| t.resource), b.terrain.map(|t| t.resource));
    assert!(same_tree_but_shadows(&root, &back_root, 0), "{name}");

    // The same chunk packed: same masks read back, same tree otherwise.
    let packed = packed_xml::write(&root).unwrap();
    let packed_out = write_shadows(&packed, &shadows).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(write_shadows(&packed_out, &shadows).unwrap(), packed_out);
    let differences = differences_outside_shadows(&packed, &packed_out);
    assert!(differences.is_empty(), "{name}: {differences:#?}");
    let packed_root = packed_xml::parse(&packed_out).unwrap();
    assert_eq!(
        read_chunk_shadows(&packed_root).unwrap(),
        back,
        "{name}: packed"
    );
    let mut packed_orig = packed_xml::parse(&packed).unwrap();
    packed_orig.name = root.name.clone();
    let mut packed_new = packed_root;
    packed_new.name = root.name.clone();
    assert!(
        same_tree_but_shadows(&packed_orig, &packed_new, 0),
        "{name}"
    );

    shadows.instances.iter().flatten().count() + usize::from(shadows.terrain.is_some())
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn every_real_arctic_chunk_round_trips() {
    let Some(data) = realdata("every_real_arctic_chunk_round_trips") else {
        return;
    };
    let space = data.join("fantasydemo-arctic/res/spaces/arctic");
    let files = files_with_extensions(&space, &[".chunk"]);
    assert_eq!(files.len(), 104, "README: 104 chunks");
    let mut written = 0;
    for (seed, path) in files.iter().enumerate() {
        let original = std::fs::read(path).unwrap();
        assert!(
            !original.windows(8).any(|w| w == b"<shadow>"),
            "real chunks are unbaked"
        );
        let count = check_chunk(&path.display().to_string(), &original, seed as u64);
        let out = write_shadows(
            &original,
            &masks_for(&xml::parse(&original).unwrap(), seed as u64),
        )
        .unwrap();
        assert_eq!(
            out.windows(8).filter(|w| w == b"<shadow>").count(),
            count,
            "{}: one <shadow> per element written",
            path.display()
        );
        written += count;
    }
    // README: 100 terrain blocks, 254 instance elements (250 models + 4
    // shells); masks_for skips every fifth instance of each chunk.
    assert!(written > 100 + 254 / 2, "{written}");
}

#[test]
fn generated_village_chunks_round_trip() {
    let world = generate(Preset::Village, 1);
    let chunks: Vec<_> = world
        .files
        .iter()
        .filter(|(p, _)| p.starts_with("spaces/village/") && p.ends_with(".chunk"))
        .collect();
    assert_eq!(chunks.len(), 9, "village is 3×3 chunks");
    for (seed, (path, bytes)) in chunks.iter().enumerate() {
        let written = check_chunk(path, bytes, seed as u64);
        assert!(written > 1, "{path}: terrain and instances");
    }
}
