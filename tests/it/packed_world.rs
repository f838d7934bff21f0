//! Packed worlds rewritten byte-true (docs/contract.md §5): a bake of a
//! world packed as a shipped game holds it changes only the `<shadow>`
//! elements it owns, every other value keeping its type and bytes (a float
//! holding 250.0 stays a 4-byte float), and a re-bake with the same masks
//! changes no byte.

use crate::generated::load_world;
use shadowcull::files::write_tree;
use shadowcull::formats::packed_xml::{self, Document, Element, Node};
use shadowcull::formats::shadow_write::read_chunk_shadows;
use shadowcull::gen::{generate, generate_packed, typed_values, Preset, SETTINGS_FILE};
use std::path::{Path, PathBuf};
use std::process::Command;

const SHADOW: &[u8] = b"shadow";

/// Every difference between two packed files outside the `<shadow>`
/// children of the root's children (the elements a bake owns): the string
/// table other than names appended at its end, a tag, a value's type or
/// bytes, an element's own value or trailing bytes, the order of children.
pub fn differences_outside_shadows(before: &[u8], after: &[u8]) -> Vec<String> {
    let (a, b) = (
        Document::parse(before).unwrap(),
        Document::parse(after).unwrap(),
    );
    let mut out = Vec::new();
    let (names_a, names_b) = (a.names(), b.names());
    if !names_b.starts_with(&names_a) {
        out.push(format!("string table {names_a:?} became {names_b:?}"));
    }
    compare(&a, a.root(), &b, b.root(), "root", 0, &mut out);
    out
}

fn compare(
    a: &Document,
    ea: &Element,
    b: &Document,
    eb: &Element,
    path: &str,
    depth: usize,
    out: &mut Vec<String>,
) {
    if ea.own != eb.own {
        out.push(format!(
            "{path}: own value {:?} became {:?}",
            ea.own, eb.own
        ));
    }
    if ea.trailing != eb.trailing {
        out.push(format!("{path}: trailing bytes changed"));
    }
    // The bake owns the <shadow> children of the root's children.
    let kept = |d: &Document, e: &Element| -> Vec<(Vec<u8>, Node)> {
        e.children
            .iter()
            .map(|c| (d.name_of(c.key).unwrap().to_vec(), c.node.clone()))
            .filter(|(name, _)| !(depth == 1 && name == SHADOW))
            .collect()
    };
    let (ca, cb) = (kept(a, ea), kept(b, eb));
    let tags = |c: &[(Vec<u8>, Node)]| -> Vec<String> {
        c.iter()
            .map(|(n, _)| String::from_utf8_lossy(n).into_owned())
            .collect()
    };
    if tags(&ca) != tags(&cb) {
        out.push(format!(
            "{path}: children {:?} became {:?}",
            tags(&ca),
            tags(&cb)
        ));
        return;
    }
    for ((name, x), (_, y)) in ca.iter().zip(&cb) {
        let child_path = format!("{path}/{}", String::from_utf8_lossy(name));
        match (x, y) {
            (Node::Value(x), Node::Value(y)) if x != y => out.push(format!(
                "{child_path}: {:?} {:?} became {:?} {:?}",
                x.kind, x.data, y.kind, y.data
            )),
            (Node::Value(_), Node::Value(_)) => {}
            (Node::Element(x), Node::Element(y)) => {
                compare(a, x, b, y, &child_path, depth + 1, out)
            }
            // An item stored as a value gains a <shadow>: its value stays.
            (Node::Value(x), Node::Element(y)) if depth == 0 => {
                let only_shadows = y.children.iter().all(|c| b.name_of(c.key) == Some(SHADOW));
                if y.own != *x || !only_shadows || !y.trailing.is_empty() {
                    out.push(format!("{child_path}: value became an element"));
                }
            }
            _ => out.push(format!("{child_path}: element and value swapped")),
        }
    }
}

fn shadowcull(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn chunks(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    shadowcull::files::find_files(dir, ".chunk")
        .unwrap()
        .into_iter()
        .map(|p| {
            let bytes = std::fs::read(&p).unwrap();
            (p, bytes)
        })
        .collect()
}

fn bake(settings: &Path) -> String {
    let run = shadowcull(&["bake", settings.to_str().unwrap(), "--threads", "2"]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    String::from_utf8_lossy(&run.stdout).into_owned()
}

#[test]
fn a_bake_of_a_packed_world_rewrites_only_its_shadows_and_a_rebake_nothing() {
    let world = generate_packed(Preset::Village, 1).unwrap();
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &world.files).unwrap();
    let settings = dir.path().join(SETTINGS_FILE);
    let before = chunks(dir.path());
    assert_eq!(before.len(), 9, "village is 3×3 chunks");

    bake(&settings);
    let baked = chunks(dir.path());
    for ((path, original), (_, rewritten)) in before.iter().zip(&baked) {
        let name = path.display();
        assert_ne!(original, rewritten, "{name}: masks written");
        let differences = differences_outside_shadows(original, rewritten);
        assert!(differences.is_empty(), "{name}: {differences:#?}");
        let document = Document::parse(rewritten).unwrap();
        for (at, kind, data) in typed_values() {
            let value = document.value_at(at).unwrap();
            assert_eq!((value.kind, &value.data), (kind, &data), "{name}: {at}");
        }
        let masks = read_chunk_shadows(&document.to_section().unwrap()).unwrap();
        assert!(masks.terrain.is_some(), "{name}");
        assert!(masks.instances.iter().all(Option::is_some), "{name}");
    }

    // Unchanged masks: no file written, every byte the same.
    let again = bake(&settings);
    assert!(again.contains("wrote 0 of 9"), "{again}");
    assert_eq!(chunks(dir.path()), baked, "a re-bake changes no byte");
}

/// The check above can fail: decoding a packed chunk to text values and
/// packing it again, as a writer without the stored types does, turns the
/// float 250.0 into an int, and the comparison names it.
#[test]
fn re_encoding_from_text_values_is_caught() {
    let world = generate_packed(Preset::Small, 1).unwrap();
    let (path, original) = world
        .files
        .iter()
        .find(|(p, _)| p.ends_with(".chunk"))
        .unwrap();
    let re_encoded = packed_xml::write(&packed_xml::parse(original).unwrap()).unwrap();
    let differences = differences_outside_shadows(original, &re_encoded);
    assert!(
        differences
            .iter()
            .any(|d| d.starts_with("root/audio/maxDistance: Float") && d.contains("Int")),
        "{path}: {differences:#?}"
    );
    assert!(
        differences
            .iter()
            .any(|d| d.starts_with("root/UserDataObject/properties/secret: EncryptedBlob")),
        "{differences:#?}"
    );
    assert_eq!(
        differences_outside_shadows(original, original),
        Vec::<String>::new()
    );
}

#[test]
fn a_packed_world_loads_as_its_text_twin() {
    for preset in [Preset::Small, Preset::Village] {
        let (text, packed) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        write_tree(text.path(), &generate(preset, 3).files).unwrap();
        write_tree(packed.path(), &generate_packed(preset, 3).unwrap().files).unwrap();
        let a = load_world(&text.path().join(SETTINGS_FILE));
        let b = load_world(&packed.path().join(SETTINGS_FILE));
        assert!(b.problems.is_empty(), "{:#?}", b.problems);
        assert_eq!(a.stats(), b.stats(), "{preset:?}");
    }
}

#[test]
fn gen_writes_the_packed_variant() {
    let dir = tempfile::tempdir().unwrap();
    let run = shadowcull(&[
        "gen",
        dir.path().to_str().unwrap(),
        "--preset",
        "small",
        "--packed",
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let world = generate_packed(Preset::Small, 1).unwrap();
    for (path, bytes) in &world.files {
        assert_eq!(
            &std::fs::read(dir.path().join(path)).unwrap(),
            bytes,
            "{path}"
        );
    }
}
