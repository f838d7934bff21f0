//! Damaged worlds: each defect is either an error naming the file (and
//! element or byte offset) or a problem listed by the scene while the rest of
//! the world still loads. Nothing panics.

use shadowcull::files::read_bake_settings;
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig, Problem, Scene};
use shadowcull::Error;
use std::path::Path;
use tempfile::TempDir;

const CHUNK: &str = "spaces/small/00000000o.chunk";
const CRATE_PRIMITIVES: &str = "sets/gen/props/crate.primitives";

fn small_world() -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(Preset::Small, 1).files).unwrap();
    dir
}

fn load(dir: &Path) -> Result<Scene, Error> {
    let settings = read_bake_settings(&dir.join(SETTINGS_FILE))?;
    load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths),
        space: settings.space,
        speedtrees: settings.speedtrees,
    })
}

fn edit(dir: &Path, file: &str, change: impl FnOnce(&mut Vec<u8>)) {
    let path = dir.join(file);
    let mut bytes = std::fs::read(&path).unwrap();
    change(&mut bytes);
    std::fs::write(path, bytes).unwrap();
}

fn replace_text(dir: &Path, file: &str, from: &str, to: &str) {
    edit(dir, file, |bytes| {
        let text = String::from_utf8(bytes.clone()).unwrap();
        assert!(text.contains(from), "{file} holds no `{from}`");
        *bytes = text.replacen(from, to, 1).into_bytes();
    });
}

fn problem<'a>(scene: &'a Scene, what_contains: &str) -> &'a Problem {
    scene
        .problems
        .iter()
        .find(|p| p.what.contains(what_contains))
        .unwrap_or_else(|| panic!("no problem about {what_contains}: {:#?}", scene.problems))
}

/// The `line:column` a problem's `what` ends with (`path:line:column`).
fn line_and_column(what: &str) -> Option<(usize, usize)> {
    let mut fields = what.rsplitn(3, ':');
    let column = fields.next()?.parse().ok()?;
    let line = fields.next()?.parse().ok()?;
    Some((line, column))
}

#[test]
fn undamaged_small_world_has_no_problems() {
    let dir = small_world();
    let scene = load(dir.path()).unwrap();
    assert!(scene.problems.is_empty(), "{:#?}", scene.problems);
}

#[test]
fn xml_syntax_error_in_a_chunk_names_file_and_byte_and_keeps_the_others() {
    let dir = small_world();
    replace_text(dir.path(), CHUNK, "</transform>", "</transfrom>");
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "00000000o.chunk");
    assert!(
        problem.why.starts_with("at byte") && line_and_column(&problem.what).is_some(),
        "{problem:?}"
    );
    assert!(
        !problem.why.contains("00000000o.chunk"),
        "the path is said once, in `what`: {problem:?}"
    );
    assert_eq!(scene.chunks.len(), 3, "the other three chunks load");
}

#[test]
fn a_truncated_chunk_is_blamed_where_its_bytes_end_naming_the_path_once() {
    let dir = small_world();
    let mut cut = 0;
    edit(dir.path(), CHUNK, |bytes| {
        // Cut inside the second <model>, so two elements are still open.
        let text = String::from_utf8(bytes.clone()).unwrap();
        let second = text.match_indices("<model>").nth(1).unwrap().0;
        cut = second + "<model>".len() + 3;
        bytes.truncate(cut);
    });
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "00000000o.chunk");
    assert!(!problem.why.contains("00000000o.chunk"), "{problem:?}");
    assert!(
        problem.why.contains(&format!("(byte {cut})")),
        "blamed where the input ends, not at the root's start: {problem:?}"
    );
    assert!(problem.why.contains("<root/model>"), "{problem:?}");
    assert!(line_and_column(&problem.what).is_some(), "{problem:?}");
    assert!(problem.why.contains("truncated"), "{problem:?}");
}

#[test]
fn missing_model_is_listed_once_with_the_chunk_that_names_it() {
    let dir = small_world();
    std::fs::remove_file(dir.path().join("sets/gen/props/crate.model")).unwrap();
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "sets/gen/props/crate.model");
    assert!(
        problem.why.contains("not found in any res path"),
        "{problem:?}"
    );
    assert!(
        problem.why.contains(".chunk"),
        "names a chunk placing it: {problem:?}"
    );
    assert_eq!(scene.problems.len(), 1);
    // Instances placing the crate keep their place but lack that part.
    assert!(scene.instances.iter().any(|i| !i.is_complete()));
}

#[test]
fn truncated_primitives_name_the_file_and_offset() {
    let dir = small_world();
    edit(dir.path(), CRATE_PRIMITIVES, |bytes| {
        bytes.truncate(bytes.len() / 2)
    });
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "crate.model");
    assert!(problem.why.contains("crate.primitives"), "{problem:?}");
    assert!(problem.why.contains("byte"), "{problem:?}");
}

#[test]
fn index_beyond_the_vertices_names_group_and_index() {
    let dir = small_world();
    edit(dir.path(), CRATE_PRIMITIVES, |bytes| {
        let container = shadowcull::formats::binsection::parse(bytes).unwrap();
        let (_, offset) = container.get("indices").unwrap();
        // First index (u16 after the 72-byte header) → 65535.
        bytes[offset + 72] = 0xff;
        bytes[offset + 73] = 0xff;
    });
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "crate.model");
    assert!(problem.why.contains("crate.primitives"), "{problem:?}");
    assert!(problem.why.contains("65535"), "{problem:?}");
}

#[test]
fn group_range_outside_the_index_buffer_is_reported() {
    let dir = small_world();
    edit(dir.path(), CRATE_PRIMITIVES, |bytes| {
        let container = shadowcull::formats::binsection::parse(bytes).unwrap();
        let (data, offset) = container.get("indices").unwrap();
        let n_indices = i32::from_le_bytes(data[64..68].try_into().unwrap()) as usize;
        // The group table follows the u16 indices; its first nPrimitives → huge.
        let table = offset + 72 + 2 * n_indices;
        bytes[table + 4..table + 8].copy_from_slice(&1_000_000i32.to_le_bytes());
    });
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "crate.model");
    assert!(
        problem.why.contains("crate.primitives") && problem.why.contains("group"),
        "{problem:?}"
    );
}

#[test]
fn nan_and_singular_transforms_leave_the_instance_out() {
    let dir = small_world();
    let before = load(dir.path()).unwrap().instances.len();
    replace_text(
        dir.path(),
        CHUNK,
        "0.000000 -0.941000 0.000000",
        "0.000000 nan 0.000000",
    );
    replace_text(
        dir.path(),
        CHUNK,
        "-0.939693 0.000000 0.342020",
        "0.000000 0.000000 0.000000",
    );
    let scene = load(dir.path()).unwrap();
    assert_eq!(scene.instances.len(), before - 2);
    let nan = scene
        .problems
        .iter()
        .find(|p| p.why.contains("NaN"))
        .expect("NaN problem");
    assert!(
        nan.what.contains("00000000o.chunk") && nan.what.contains("root/model"),
        "{nan:?}"
    );
    let singular = scene
        .problems
        .iter()
        .find(|p| p.why.contains("singular"))
        .expect("singular problem");
    assert!(singular.what.contains("00000000o.chunk"), "{singular:?}");
}

#[test]
fn damaged_terrain_is_a_problem_not_a_failure() {
    let dir = small_world();
    edit(dir.path(), "spaces/small/00000000o.cdata", |bytes| {
        bytes.truncate(100)
    });
    let scene = load(dir.path()).unwrap();
    let problem = problem(&scene, "00000000o.chunk <terrain>");
    assert!(problem.why.contains("00000000o.cdata"), "{problem:?}");
    assert_eq!(scene.terrain.len(), 3);
}

#[test]
fn empty_space_and_missing_space_are_errors_that_say_what_to_do() {
    let dir = small_world();
    for chunk in shadowcull::files::find_files(&dir.path().join("spaces/small"), ".chunk").unwrap()
    {
        std::fs::remove_file(chunk).unwrap();
    }
    let err = load(dir.path()).unwrap_err().to_string();
    assert!(err.contains("no .chunk files"), "{err}");

    std::fs::remove_file(dir.path().join("spaces/small/space.settings")).unwrap();
    let err = load(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("space.settings") && err.contains("<resPaths>"),
        "{err}"
    );
}

#[test]
fn broken_settings_file_names_itself() {
    let dir = small_world();
    replace_text(dir.path(), SETTINGS_FILE, "</space>", "</spaec>");
    let err = load(dir.path()).unwrap_err().to_string();
    assert!(err.contains("bake.xml") && err.contains("byte"), "{err}");
}

#[test]
fn every_damaged_copy_of_a_generated_file_loads_or_reports() {
    // Truncations and seeded bit flips of a model's binaries, a chunk and a
    // terrain block, through the whole loader: a problem, never a panic.
    let dir = small_world();
    let targets = [
        CRATE_PRIMITIVES,
        CHUNK,
        "spaces/small/00000000o.cdata",
        "sets/gen/props/crate.visual",
    ];
    let mut rng = shadowcull::rng::Rng::new(11);
    let mut damaged = 0;
    for target in targets {
        let path = dir.path().join(target);
        let original = std::fs::read(&path).unwrap();
        for round in 0..24 {
            let mut bytes = original.clone();
            if round % 3 == 0 {
                bytes.truncate(rng.below(original.len()));
            } else {
                for _ in 0..1 + round % 4 {
                    let at = rng.below(bytes.len());
                    bytes[at] ^= 1 << rng.below(8);
                }
            }
            std::fs::write(&path, &bytes).unwrap();
            match load(dir.path()) {
                Ok(scene) => damaged += usize::from(!scene.problems.is_empty()),
                Err(err) => assert!(!err.to_string().is_empty()),
            }
        }
        std::fs::write(&path, &original).unwrap();
    }
    assert!(damaged > 20, "damage was noticed only {damaged} times");
}

#[test]
fn chunks_in_sep_sub_folders_load_unless_single_dir() {
    let dir = small_world();
    let before = load(dir.path()).unwrap().stats();
    let sep = dir.path().join("spaces/small/fffxfffx/sep");
    std::fs::create_dir_all(&sep).unwrap();
    std::fs::rename(
        dir.path().join("spaces/small/ffffffffo.chunk"),
        sep.join("ffffffffo.chunk"),
    )
    .unwrap();
    // The terrain resource is relative to the chunk's folder.
    std::fs::rename(
        dir.path().join("spaces/small/ffffffffo.cdata"),
        sep.join("ffffffffo.cdata"),
    )
    .unwrap();
    assert_eq!(load(dir.path()).unwrap().stats(), before);
    replace_text(
        dir.path(),
        "spaces/small/space.settings",
        "</bounds>",
        "</bounds>\n\t<singleDir>\ttrue\t</singleDir>",
    );
    assert_eq!(load(dir.path()).unwrap().chunks.len(), before.chunks - 1);
}

#[test]
fn a_world_saved_as_packed_binary_xml_loads_the_same() {
    let dir = small_world();
    let before = load(dir.path()).unwrap().stats();
    let mut converted = 0;
    for suffix in [".chunk", ".model", ".visual", "space.settings"] {
        for path in shadowcull::files::find_files(dir.path(), suffix).unwrap() {
            let text = std::fs::read(&path).unwrap();
            let tree = shadowcull::formats::xml::parse(&text).unwrap();
            let packed = shadowcull::formats::packed_xml::write(&tree).unwrap();
            assert!(packed.starts_with(&shadowcull::formats::packed_xml::MAGIC));
            std::fs::write(&path, packed).unwrap();
            converted += 1;
        }
    }
    assert!(converted > 10);
    assert_eq!(load(dir.path()).unwrap().stats(), before);
}
