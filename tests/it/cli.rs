//! The `shadowcull` binary: exit codes, `inspect --json` fields, `gen`.

use crate::generated::{fixture_dir, FIXTURE_SEED};
use crate::support::realdata;
use shadowcull::gen::{generate, Preset};
use std::process::{Command, Output};

pub fn shadowcull(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn json(output: &Output) -> serde_json::Value {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("inspect --json prints one JSON object")
}

#[test]
fn inspect_json_counts_match_the_generator_on_both_fixtures() {
    for preset in [Preset::Small, Preset::Village] {
        let settings = fixture_dir(preset).join("bake.xml");
        let value = json(&shadowcull(&[
            "inspect",
            settings.to_str().unwrap(),
            "--json",
        ]));
        let expected = serde_json::to_value(generate(preset, FIXTURE_SEED).expected).unwrap();
        for field in [
            "chunks",
            "instances",
            "models",
            "groups",
            "triangles",
            "terrain_blocks",
            "alpha_tested_groups",
            "double_sided_groups",
            "receiver_only_instances",
        ] {
            assert!(value[field].is_u64(), "{field} is an integer");
            assert_eq!(value[field], expected[field], "{preset:?} {field}");
        }
        assert_eq!(value["problems"].as_array().map(Vec::len), Some(0));
    }
}

#[test]
fn inspect_text_summary_is_readable() {
    let settings = fixture_dir(Preset::Small).join("bake.xml");
    let output = shadowcull(&["inspect", settings.to_str().unwrap()]);
    assert!(output.status.success());
    let text = String::from_utf8(output.stdout).unwrap();
    assert!(
        text.contains("triangles") && text.contains("no problems"),
        "{text}"
    );
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn inspect_of_arctic_lists_every_missing_primitives_file() {
    let Some(root) = realdata("inspect_of_arctic_lists_every_missing_primitives_file") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let settings = dir.path().join("arctic.xml");
    std::fs::write(
        &settings,
        format!(
            "<shadowcull>\n\t<resPaths>\n\t\t<path>\t{}\t</path>\n\t</resPaths>\n\t<space>\tspaces/arctic\t</space>\n</shadowcull>\n",
            root.join("fantasydemo-arctic/res").display()
        ),
    )
    .unwrap();
    let output = shadowcull(&["inspect", settings.to_str().unwrap(), "--json"]);
    // It lists problems, so it exits 1 (a bake would fail without --keep-going).
    assert_eq!(output.status.code(), Some(1));
    let value: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(value["chunks"], 104);
    let problems = value["problems"].as_array().unwrap();
    let needed = std::fs::read_to_string(root.join("fantasydemo-arctic/PRIMITIVES_NEEDED.txt"))
        .unwrap_or_default();
    let mut listed = 0;
    for problem in problems {
        let why = problem["why"].as_str().unwrap();
        if let Some(start) = why.find("resource `") {
            let name = &why[start + 10..];
            let name = &name[..name.find('`').unwrap()];
            if name.ends_with(".primitives") {
                listed += 1;
                assert!(
                    needed.is_empty() || needed.contains(name),
                    "{name} not in PRIMITIVES_NEEDED.txt"
                );
            }
        }
    }
    // 18 placed models, each missing its .primitives (README).
    assert_eq!(listed, 18, "{problems:#?}");
}

#[test]
fn exit_codes() {
    assert_eq!(shadowcull(&[]).status.code(), Some(2));
    assert_eq!(shadowcull(&["inspect"]).status.code(), Some(2));
    assert_eq!(shadowcull(&["frobnicate"]).status.code(), Some(2));
    assert_eq!(
        shadowcull(&["gen", "x", "--preset", "huge"]).status.code(),
        Some(2)
    );
    let missing = shadowcull(&["inspect", "/nonexistent/bake.xml"]);
    assert_eq!(missing.status.code(), Some(1));
    let message = String::from_utf8_lossy(&missing.stderr);
    assert!(message.contains("/nonexistent/bake.xml"), "{message}");
    assert_eq!(shadowcull(&["--help"]).status.code(), Some(0));
}

#[test]
fn gen_writes_the_same_bytes_as_the_library_and_the_world_inspects_clean() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("world");
    let output = shadowcull(&[
        "gen",
        out.to_str().unwrap(),
        "--preset",
        "small",
        "--seed",
        "3",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    for (relative, bytes) in generate(Preset::Small, 3).files {
        assert_eq!(
            std::fs::read(out.join(&relative)).unwrap(),
            bytes,
            "{relative}"
        );
    }
    let value = json(&shadowcull(&[
        "inspect",
        out.join("bake.xml").to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(value["problems"].as_array().map(Vec::len), Some(0));
}

/// Without the `raster` feature, `xcheck` and `xcheck --savings` fail
/// (exit 1) and say how to get it.
#[cfg(not(feature = "raster"))]
#[test]
fn xcheck_without_the_raster_feature_says_how_to_build_it() {
    let settings = fixture_dir(Preset::Small).join("bake.xml");
    for savings in [false, true] {
        let mut args = vec!["xcheck", settings.to_str().unwrap()];
        if savings {
            args.push("--savings");
        }
        let out = shadowcull(&args);
        assert_eq!(out.status.code(), Some(1));
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains("--features raster"), "{stderr}");
        assert!(
            stderr.contains("built without the cargo feature `raster`"),
            "{stderr}"
        );
        assert_eq!(stderr.contains("--savings"), savings, "{stderr}");
    }
}

/// `gen` ends with a bake command that runs this very program: its name
/// when `PATH` finds it under that name, `cargo run` from a cargo target
/// folder, else its full path.
#[cfg(unix)]
#[test]
fn gen_suggests_a_bake_command_that_runs_this_program() {
    use std::os::unix::fs::PermissionsExt;
    use std::path::Path;
    let dir = tempfile::tempdir().unwrap();
    let world = dir.path().join("world");
    let bake_xml = world.join("bake.xml").display().to_string();
    let suggestion = |program: &Path, path_var: &Path| -> String {
        let run = || {
            Command::new(program)
                .args(["gen", world.to_str().unwrap(), "--preset", "small"])
                .env("PATH", path_var)
                .output()
        };
        // A copy just written may still be open in a child another test
        // forked before that child's exec closed it.
        let mut output = run();
        for _ in 0..50 {
            match &output {
                Err(e) if e.raw_os_error() == Some(26) => {
                    std::thread::sleep(std::time::Duration::from_millis(20));
                    output = run();
                }
                _ => break,
            }
        }
        let output = output.unwrap();
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let said = String::from_utf8(output.stdout).unwrap();
        let line = said.lines().last().unwrap_or_default();
        line.split("bake it with: ")
            .nth(1)
            .unwrap_or_else(|| panic!("{said}"))
            .to_string()
    };
    let built = Path::new(env!("CARGO_BIN_EXE_shadowcull"));
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    // Built by cargo, not on PATH.
    assert_eq!(
        suggestion(built, &empty),
        format!("cargo run --release -- bake {bake_xml}")
    );
    // On PATH under its name (a link to this program).
    let bin = dir.path().join("bin");
    std::fs::create_dir(&bin).unwrap();
    std::os::unix::fs::symlink(built, bin.join("shadowcull")).unwrap();
    assert_eq!(
        suggestion(built, &bin),
        format!("shadowcull bake {bake_xml}")
    );
    // Another program of that name on PATH is not this one.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("shadowcull"), "#!/bin/sh\nexit 0\n").unwrap();
    std::fs::set_permissions(
        other.join("shadowcull"),
        std::fs::Permissions::from_mode(0o755),
    )
    .unwrap();
    assert_eq!(
        suggestion(built, &other),
        format!("cargo run --release -- bake {bake_xml}")
    );
    // A copy outside any cargo target folder, not on PATH: its own path.
    let tools = dir.path().join("tools");
    std::fs::create_dir(&tools).unwrap();
    let copy = tools.join("shadowcull");
    std::fs::copy(built, &copy).unwrap();
    let copy = copy.canonicalize().unwrap();
    assert_eq!(
        suggestion(&copy, &other),
        format!("{} bake {bake_xml}", copy.display())
    );
}
