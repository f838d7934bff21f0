//! `shadowcull diff` through the binary: two bakes of the `small` world
//! around a moved model (and an added one) are diffed as reports and as
//! chunk folders, and the differing casters are checked against a
//! comparison of the two reports' masks made here, bit by bit.

use crate::support::{model_elements, moved};
use serde_json::Value;
use shadowcull::files::write_tree;
use shadowcull::gen::{generate, Preset};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SPACE: &str = "spaces/small";
const CHUNK: &str = "00000000o";

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// A baked copy of the `small` world: its folder, space folder and report.
struct Baked {
    root: PathBuf,
    report: PathBuf,
}

impl Baked {
    /// Writes the `small` world under `dir/name`, lets `edit` change its
    /// chunk CHUNK's text, and bakes it with a report.
    fn new(dir: &Path, name: &str, edit: impl FnOnce(&str) -> String) -> Baked {
        let root = dir.join(name);
        write_tree(&root, &generate(Preset::Small, 1).files).unwrap();
        let chunk = root.join(SPACE).join(format!("{CHUNK}.chunk"));
        let text = std::fs::read_to_string(&chunk).unwrap();
        std::fs::write(&chunk, edit(&text)).unwrap();
        let report = dir.join(format!("{name}.json"));
        let settings = root.join("bake.xml");
        let args = [
            "bake",
            s(&settings),
            "--no-cache",
            "--report",
            s(&report),
            "--quiet",
        ];
        let output = run(&args);
        assert!(output.status.success(), "bake {name}: {}", stderr(&output));
        Baked { root, report }
    }

    fn space(&self) -> PathBuf {
        self.root.join(SPACE)
    }

    fn report(&self) -> Value {
        serde_json::from_slice(&std::fs::read(&self.report).unwrap()).unwrap()
    }
}

/// The chunk text with model `index` moved by (6, 8) m.
fn with_model_moved(text: &str, index: usize) -> String {
    let element = model_elements(text)[index].clone();
    let replacement = moved(&text[element.clone()], 6.0, 8.0);
    format!(
        "{}{replacement}{}",
        &text[..element.start],
        &text[element.end..]
    )
}

/// The chunk text with a copy of its first model, moved, placed after its
/// last one (so no other instance's index changes).
fn with_model_added(text: &str) -> String {
    let models = model_elements(text);
    let copy = moved(&text[models[0].clone()], 3.0, -2.0);
    let end = models.last().unwrap().end;
    format!("{}{copy}{}", &text[..end], &text[end..])
}

/// A caster's identity in a diff: chunk, kind, index, group.
type Key = (String, String, Option<u64>, Option<u64>);

/// Every caster of a report with its mask: one per group for casters with
/// group masks, else one for the mask.
fn report_masks(report: &Value) -> BTreeMap<Key, u32> {
    let mut out = BTreeMap::new();
    for caster in report["casters"].as_array().unwrap() {
        let key = |group| {
            (
                caster["chunk"].as_str().unwrap().to_string(),
                caster["kind"].as_str().unwrap().to_string(),
                caster["index"].as_u64(),
                group,
            )
        };
        let groups = caster["groups"].as_array().filter(|g| !g.is_empty());
        match groups {
            Some(groups) => {
                for (g, mask) in groups.iter().enumerate() {
                    out.insert(key(Some(g as u64)), mask.as_u64().unwrap() as u32);
                }
            }
            None => {
                out.insert(key(None), caster["mask"].as_u64().unwrap() as u32);
            }
        }
    }
    out
}

/// What differs between two reports, computed bit by bit: per caster its
/// change and the bits that went useful → culled and culled → useful.
fn expected_changes(old: &Value, new: &Value) -> BTreeMap<Key, (String, Vec<u64>, Vec<u64>)> {
    let (old, new) = (report_masks(old), report_masks(new));
    let mut out = BTreeMap::new();
    for key in old.keys().chain(new.keys()) {
        let change = match (old.get(key), new.get(key)) {
            (Some(a), Some(b)) => {
                let culled = (0..32).filter(|&bit| a >> bit & 1 == 1 && b >> bit & 1 == 0);
                let useful = (0..32).filter(|&bit| a >> bit & 1 == 0 && b >> bit & 1 == 1);
                let (culled, useful): (Vec<u64>, Vec<u64>) = (culled.collect(), useful.collect());
                if culled.is_empty() && useful.is_empty() {
                    continue;
                }
                ("flipped".to_string(), culled, useful)
            }
            (Some(_), None) => ("disappeared".to_string(), vec![], vec![]),
            _ => ("appeared".to_string(), vec![], vec![]),
        };
        out.insert(key.clone(), change);
    }
    out
}

/// `diff --json` of two paths (exit 0 expected).
fn diff_json(old: &Path, new: &Path) -> Value {
    let output = run(&["diff", s(old), s(new), "--json"]);
    assert!(output.status.success(), "diff: {}", stderr(&output));
    serde_json::from_slice(&output.stdout).unwrap()
}

/// The `casters` of a diff's JSON in the form of [`expected_changes`].
fn listed_changes(diff: &Value) -> BTreeMap<Key, (String, Vec<u64>, Vec<u64>)> {
    let bits = |v: &Value| -> Vec<u64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|b| b.as_u64().unwrap())
            .collect()
    };
    diff["casters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let key = (
                c["chunk"].as_str().unwrap().to_string(),
                c["kind"].as_str().unwrap().to_string(),
                c["index"].as_u64(),
                c["group"].as_u64(),
            );
            let change = c["change"].as_str().unwrap().to_string();
            (key, (change, bits(&c["to_culled"]), bits(&c["to_useful"])))
        })
        .collect()
}

#[test]
fn a_moved_model_is_diffed_alike_from_reports_and_chunk_folders() {
    let dir = tempfile::tempdir().unwrap();
    let before = Baked::new(dir.path(), "before", str::to_string);
    let after = Baked::new(dir.path(), "after", |text| with_model_moved(text, 2));
    let expected = expected_changes(&before.report(), &after.report());
    assert!(
        !expected.is_empty(),
        "the move changes no mask: the test would check nothing"
    );
    assert!(expected.values().all(|(change, ..)| change == "flipped"));

    let from_reports = diff_json(&before.report, &after.report);
    assert_eq!(listed_changes(&from_reports), expected);
    assert_eq!(from_reports["differs"], true);
    let keys: Vec<Key> = listed_changes(&from_reports).into_keys().collect();
    let mut sorted = keys.clone();
    sorted.sort();
    assert_eq!(keys, sorted, "casters sorted by chunk, kind, index, group");
    // Per light totals: the flips of each bit, named as the report names it.
    for light in after.report()["lights"].as_array().unwrap() {
        let bit = light["bit"].as_u64().unwrap();
        let count = |i: usize| {
            expected
                .values()
                .filter(|c| [&c.1, &c.2][i].contains(&bit))
                .count()
        };
        let listed = from_reports["lights"]
            .as_array()
            .unwrap()
            .iter()
            .find(|l| l["bit"] == bit)
            .unwrap();
        assert_eq!(listed["new_name"], light["name"]);
        assert_eq!(listed["to_culled"], count(0), "{listed}");
        assert_eq!(listed["to_useful"], count(1), "{listed}");
    }

    let from_folders = diff_json(&before.space(), &after.space());
    assert_eq!(from_folders["casters"], from_reports["casters"]);
    assert_eq!(from_folders["totals"], from_reports["totals"]);
    let files = &from_folders["chunk_files"];
    assert_eq!(files["matched"], 4, "{files}");
    assert_eq!(files["identical"], 3, "only the edited chunk is parsed");

    let text = run(&["diff", s(&before.report), s(&after.report)]);
    let text = String::from_utf8(text.stdout).unwrap();
    assert!(
        text.contains(&format!("{CHUNK}    useful→culled  model 2 group")),
        "{text}"
    );
}

#[test]
fn check_exits_1_only_when_something_differs() {
    let dir = tempfile::tempdir().unwrap();
    let before = Baked::new(dir.path(), "before", str::to_string);
    let after = Baked::new(dir.path(), "after", |text| with_model_moved(text, 2));
    for (old, new) in [
        (&before.report, &before.report),
        (&before.space(), &before.space()),
    ] {
        let same = run(&["diff", s(old), s(new), "--check"]);
        assert!(same.status.success(), "{}", stderr(&same));
        let json = diff_json(old, new);
        assert_eq!(json["differs"], false);
        assert_eq!(json["casters"], serde_json::json!([]));
        assert!(String::from_utf8(same.stdout)
            .unwrap()
            .contains("no differences"));
    }
    for (old, new) in [
        (&before.report, &after.report),
        (&before.space(), &after.space()),
    ] {
        let differs = run(&["diff", s(old), s(new), "--check"]);
        assert_eq!(differs.status.code(), Some(1), "{}", stderr(&differs));
        assert!(
            stderr(&differs).contains("--check:"),
            "{}",
            stderr(&differs)
        );
        let without_check = run(&["diff", s(old), s(new)]);
        assert!(without_check.status.success());
    }
}

#[test]
fn an_added_model_and_a_removed_chunk_file_appear_and_disappear() {
    let dir = tempfile::tempdir().unwrap();
    let before = Baked::new(dir.path(), "before", str::to_string);
    let added = Baked::new(dir.path(), "added", with_model_added);
    let chunk_text = std::fs::read_to_string(before.space().join(format!("{CHUNK}.chunk")));
    let new_index = model_elements(&chunk_text.unwrap()).len() as u64;
    let expected = expected_changes(&before.report(), &added.report());
    let appeared: Vec<&Key> = expected
        .iter()
        .filter(|(_, c)| c.0 == "appeared")
        .map(|(k, _)| k)
        .collect();
    assert!(!appeared.is_empty());
    assert!(
        appeared
            .iter()
            .all(|k| k.0 == CHUNK && k.1 == "model" && k.2 == Some(new_index)),
        "{appeared:?}"
    );
    for diff in [
        diff_json(&before.report, &added.report),
        diff_json(&before.space(), &added.space()),
    ] {
        assert_eq!(listed_changes(&diff), expected);
        assert_eq!(diff["totals"]["appeared"], appeared.len());
    }

    // A chunk file gone: every caster of that chunk disappeared.
    let pruned = dir.path().join("pruned");
    std::fs::create_dir(&pruned).unwrap();
    let mut kept = 0;
    for entry in std::fs::read_dir(before.space()).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        if name.ends_with(".chunk") && name != format!("{CHUNK}.chunk") {
            std::fs::copy(&path, pruned.join(&name)).unwrap();
            kept += 1;
        }
    }
    let diff = diff_json(&before.space(), &pruned);
    let of_chunk = report_masks(&before.report())
        .into_keys()
        .filter(|k| k.0 == CHUNK)
        .collect::<Vec<_>>();
    let listed = listed_changes(&diff);
    assert_eq!(listed.keys().cloned().collect::<Vec<_>>(), of_chunk);
    assert!(listed.values().all(|c| c.0 == "disappeared"));
    assert_eq!(diff["chunk_files"]["removed"], 1);
    assert_eq!(diff["chunk_files"]["matched"], kept);
}

#[test]
fn bad_inputs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let before = Baked::new(dir.path(), "before", str::to_string);
    let text = std::fs::read(&before.report).unwrap();
    let garbled = dir.path().join("garbled.json");
    std::fs::write(&garbled, &text[..text.len() / 2]).unwrap();
    let output = run(&["diff", s(&before.report), s(&garbled)]);
    assert_eq!(output.status.code(), Some(1));
    let message = stderr(&output);
    assert!(
        message.contains("garbled.json: not a bake report") && message.contains("line"),
        "{message}"
    );

    let output = run(&["diff", s(&before.report), s(&before.space())]);
    assert_eq!(output.status.code(), Some(2), "mixed kinds: a usage error");
    assert!(
        stderr(&output).contains("is a bake report but NEW"),
        "{}",
        stderr(&output)
    );

    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let output = run(&["diff", s(&empty), s(&before.space())]);
    assert_eq!(output.status.code(), Some(1));
    let message = stderr(&output);
    assert!(
        message.contains("empty: holds no .chunk files"),
        "{message}"
    );

    let broken = dir.path().join("broken");
    std::fs::create_dir(&broken).unwrap();
    std::fs::write(broken.join(format!("{CHUNK}.chunk")), "<root><model>").unwrap();
    let output = run(&["diff", s(&before.space()), s(&broken)]);
    assert_eq!(output.status.code(), Some(1));
    assert!(
        stderr(&output).contains(&format!("{CHUNK}.chunk")),
        "{}",
        stderr(&output)
    );

    let missing = dir.path().join("missing.json");
    let output = run(&["diff", s(&missing), s(&before.report)]);
    assert_eq!(output.status.code(), Some(1));
    assert!(stderr(&output).contains("missing.json: no such file"));
}
