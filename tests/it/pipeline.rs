//! The bake in a studio pipeline: broken input fails, every
//! light is checked before any is traced, `--light` and `<bit>` keep other
//! bits, `plan` and `--max-memory`, progress for machines, `--check`,
//! `--dry-run`, the report's files and versions, and small things.

use crate::cli::shadowcull;
use serde_json::Value;
use shadowcull::files::write_tree;
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;
use tempfile::TempDir;

const CHUNK: &str = "spaces/small/00000000o.chunk";

fn world(preset: Preset) -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(preset, 1).files).unwrap();
    dir
}

/// The small world with coarse lights (these tests are about the pipeline,
/// not rays).
fn small() -> TempDir {
    let dir = world(Preset::Small);
    edit(dir.path(), SETTINGS_FILE, "0.195312", "1.000000");
    edit(dir.path(), SETTINGS_FILE, "\t512\t", "\t64\t");
    edit(dir.path(), SETTINGS_FILE, "\t256\t", "\t32\t");
    dir
}

fn edit(dir: &Path, file: &str, from: &str, to: &str) {
    let path = dir.join(file);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains(from), "{file} holds no `{from}`");
    std::fs::write(path, text.replacen(from, to, 1)).unwrap();
}

fn settings(dir: &TempDir) -> String {
    dir.path().join(SETTINGS_FILE).display().to_string()
}

fn run(args: &[&str]) -> Output {
    shadowcull(args)
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Every file of the world under `dir` (not the bake cache beside its
/// settings file, which `--check` and `--dry-run` keep too).
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(dir) = pending.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.ends_with(".shadowcull-cache") {
                continue;
            }
            if path.is_dir() {
                pending.push(path);
            } else {
                out.insert(path.clone(), std::fs::read(&path).unwrap());
            }
        }
    }
    out
}

fn report_of(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// (chunk, kind, index) → mask, from a report.
fn masks(report: &Value) -> BTreeMap<(String, String, i64), (u64, Vec<u64>)> {
    report["casters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                (
                    c["chunk"].as_str().unwrap().to_string(),
                    c["kind"].as_str().unwrap().to_string(),
                    c["index"].as_i64().unwrap_or(-1),
                ),
                (
                    c["mask"].as_u64().unwrap(),
                    c["groups"]
                        .as_array()
                        .map(|g| g.iter().map(|m| m.as_u64().unwrap()).collect())
                        .unwrap_or_default(),
                ),
            )
        })
        .collect()
}

// ---------------------------------------------------------------------------
// 1. Broken input fails the bake.

#[test]
fn broken_input_fails_the_bake_writes_nothing_and_lists_every_problem() {
    let dir = small();
    // A truncated chunk and a missing .model.
    let chunk = dir.path().join("spaces/small/0000ffffo.chunk");
    let bytes = std::fs::read(&chunk).unwrap();
    std::fs::write(&chunk, &bytes[..bytes.len() / 2]).unwrap();
    let model = files(dir.path())
        .into_keys()
        .find(|p| p.extension().is_some_and(|e| e == "model"))
        .unwrap();
    std::fs::remove_file(&model).unwrap();
    let before = files(dir.path());
    let report = dir.path().join("report.json");
    let failed = run(&[
        "bake",
        &settings(&dir),
        "--report",
        report.to_str().unwrap(),
    ]);
    let stderr = text(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("0000ffffo.chunk"), "{stderr}");
    let model_name = model.file_name().unwrap().to_str().unwrap();
    assert!(stderr.contains(model_name), "{stderr}");
    assert!(
        stderr.contains("2 problems in the input") && stderr.contains("--keep-going"),
        "{stderr}"
    );
    assert_eq!(files(dir.path()), before, "nothing may be written");

    let kept = run(&[
        "bake",
        &settings(&dir),
        "--keep-going",
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(kept.status.success(), "{}", text(&kept.stderr));
    assert_ne!(files(dir.path()), before, "--keep-going bakes what loaded");
    let skipped = report_of(&report)["skipped"].as_array().unwrap().clone();
    let severity = |what: &str| -> Vec<String> {
        skipped
            .iter()
            .filter(|s| {
                s["what"].as_str().unwrap().contains(what)
                    || s["why"].as_str().unwrap().contains(what)
            })
            .map(|s| s["severity"].as_str().unwrap().to_string())
            .collect()
    };
    assert!(severity("0000ffffo.chunk").iter().all(|s| s == "error"));
    assert!(!severity("0000ffffo.chunk").is_empty());
    assert!(severity(model_name).iter().all(|s| s == "error"));
    let passes = severity("one pass");
    assert!(
        passes.iter().all(|s| s == "info"),
        "one pass instead of two is info: {skipped:#?}"
    );
    assert!(
        skipped
            .iter()
            .all(|s| matches!(s["severity"].as_str(), Some("info" | "error"))),
        "{skipped:#?}"
    );
}

#[test]
fn a_stray_placement_fails_the_bake_unless_keep_going() {
    // Geometry far outside the space is a problem naming
    // the chunk and element, and fails the bake like other broken input.
    let dir = small();
    edit(
        dir.path(),
        CHUNK,
        "0.000000 -0.941000 0.000000",
        "0 -0.941 -2147483649",
    );
    let before = files(dir.path());
    let failed = run(&["bake", &settings(&dir)]);
    let stderr = text(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("00000000o.chunk <model[0]/transform>")
            && stderr.contains("far outside the space")
            && stderr.contains("1 problem in the input"),
        "{stderr}"
    );
    assert_eq!(files(dir.path()), before);
    let inspect = run(&["inspect", &settings(&dir)]);
    assert_eq!(
        inspect.status.code(),
        Some(1),
        "inspect lists it and exits 1"
    );
    assert!(text(&inspect.stdout).contains("far outside the space"));
    let kept = run(&["bake", &settings(&dir), "--keep-going", "--quiet"]);
    assert!(kept.status.success(), "{}", text(&kept.stderr));
}

#[test]
fn inspect_exits_1_only_when_it_lists_problems() {
    let dir = small();
    let clean = run(&["inspect", &settings(&dir)]);
    assert_eq!(clean.status.code(), Some(0), "{}", text(&clean.stderr));
    std::fs::write(dir.path().join(CHUNK), b"<root><model>").unwrap();
    let broken = run(&["inspect", &settings(&dir), "--json"]);
    assert_eq!(broken.status.code(), Some(1));
    let json: Value = serde_json::from_slice(&broken.stdout).unwrap();
    assert_eq!(json["problems"].as_array().unwrap().len(), 1);
    assert!(
        text(&broken.stderr).contains("1 problem listed"),
        "{}",
        text(&broken.stderr)
    );
}

/// The small world's settings file with `element` inserted before
/// `before`; returns where it starts as `file:line:column`.
fn insert_into_settings(dir: &TempDir, before: &str, element: &str) -> String {
    let path = dir.path().join(SETTINGS_FILE);
    let original = std::fs::read_to_string(&path).unwrap();
    let at = original.find(before).unwrap();
    std::fs::write(
        &path,
        format!("{}{element}{}", &original[..at], &original[at..]),
    )
    .unwrap();
    let line = original[..at].matches('\n').count() + 1;
    let column = at - original[..at].rfind('\n').map_or(0, |i| i + 1) + 1;
    format!("{}:{line}:{column}", path.display())
}

#[test]
fn an_unknown_settings_element_fails_a_strict_bake_naming_it_and_the_closest_name() {
    let dir = small();
    let at = insert_into_settings(&dir, "<lights>", "<heightBais> 0.5 </heightBais>\n\t");
    let named = format!(
        "{at}: unknown element <heightBais> (shadowcull/heightBais); did you mean <heightBias>?"
    );
    let before = files(dir.path());
    let partial = dir.path().join("shard.part");
    let partial = partial.to_str().unwrap();
    // Strict: bake, a shard, merge and plan fail before reading the world.
    for args in [
        &["bake", &settings(&dir)][..],
        &[
            "bake",
            &settings(&dir),
            "--shard",
            "0/2",
            "--partial",
            partial,
        ],
        &["merge", &settings(&dir), partial],
        &["plan", &settings(&dir)],
    ] {
        let out = run(args);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
        assert_eq!(stderr.matches(&named).count(), 1, "{args:?}: {stderr}");
        assert!(
            stderr.contains("1 unknown element in the settings file")
                && stderr.contains("--keep-going"),
            "{args:?}: {stderr}"
        );
        assert!(
            !stderr.lines().any(|l| l.starts_with("loaded ")),
            "{args:?}: {stderr}"
        );
        assert_eq!(files(dir.path()), before, "{args:?} wrote something");
    }
    // --keep-going: a warning, and the bake goes on with the default.
    let ignored = format!(
        "warning: {at}: unknown element <heightBais> (shadowcull/heightBais) is ignored; \
         did you mean <heightBias>?"
    );
    let kept = run(&[
        "bake",
        &settings(&dir),
        "--keep-going",
        "--dry-run",
        "--quiet",
    ]);
    let stderr = text(&kept.stderr);
    assert!(kept.status.success(), "{stderr}");
    assert_eq!(stderr.matches(&ignored).count(), 1, "{stderr}");
    assert!(text(&kept.stdout).contains("would change"));
    // inspect lists it among the problems (exit 1); render warns.
    let inspect = run(&["inspect", &settings(&dir), "--json"]);
    assert_eq!(inspect.status.code(), Some(1), "{}", text(&inspect.stderr));
    let json: Value = serde_json::from_slice(&inspect.stdout).unwrap();
    let problem = &json["problems"][0];
    assert_eq!(
        format!(
            "{}: {}",
            problem["what"].as_str().unwrap(),
            problem["why"].as_str().unwrap()
        ),
        named
    );
    let picture = dir.path().join("sun.png");
    let render = run(&[
        "render",
        &settings(&dir),
        "--light",
        "sun",
        "-o",
        picture.to_str().unwrap(),
    ]);
    let stderr = text(&render.stderr);
    assert!(render.status.success(), "{stderr}");
    assert_eq!(stderr.matches(&ignored).count(), 1, "{stderr}");
}

#[test]
fn an_unknown_element_nothing_is_close_to_lists_what_is_valid_there() {
    let dir = small();
    let at = insert_into_settings(&dir, "<texelSize>", "<colour> red </colour>");
    let out = run(&["bake", &settings(&dir), "--dry-run"]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "{at}: unknown element <colour> (shadowcull/lights/light/colour); \
             expected one of name, type, bit,"
        )),
        "{stderr}"
    );
    assert!(!stderr.contains("did you mean"), "{stderr}");
}

#[test]
fn errors_give_line_and_column() {
    let dir = small();
    let chunk = dir.path().join(CHUNK);
    let original = std::fs::read_to_string(&chunk).unwrap();
    // A mismatched end tag on the line of the first <transform>.
    let at = original.find("</transform>").unwrap();
    std::fs::write(
        &chunk,
        format!("{}</transfrom>{}", &original[..at], &original[at + 12..]),
    )
    .unwrap();
    let line = original[..at].matches('\n').count() + 1;
    let line_start = original[..at].rfind('\n').map_or(0, |i| i + 1);
    let column = original[line_start..at].chars().count() + 1;
    let out = run(&["inspect", &settings(&dir)]);
    let stdout = text(&out.stdout);
    assert!(
        stdout.contains(&format!("{}:{line}:{column}: at byte", chunk.display())),
        "{stdout}"
    );
}

// ---------------------------------------------------------------------------
// 2. Every light is checked before any is traced.

#[test]
fn every_light_is_validated_before_any_is_traced() {
    // A spot of 8192² (67 M rays) then a light over the grid limits: the
    // spot must not be traced before the bake fails. The last light here
    // is a sun of 0.1 mm texels: millions per side, over `light::MAX_SIDE`.
    let dir = small();
    edit(dir.path(), SETTINGS_FILE, "\t64\t", "\t8192\t");
    edit(
        dir.path(),
        SETTINGS_FILE,
        "</lights>",
        "<light><name>fine</name><type>directional</type>\
         <direction>0 -1 0</direction><texelSize>0.0001</texelSize></light></lights>",
    );
    let started = std::time::Instant::now();
    let out = run(&["bake", &settings(&dir), "--progress", "json"]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("light `fine`") && stderr.contains("raise <texelSize>"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("\"tracing\"") && !stderr.contains("\"calibrating\""),
        "no ray may be traced: {stderr}"
    );
    assert!(started.elapsed().as_secs() < 30, "{:?}", started.elapsed());
}

// ---------------------------------------------------------------------------
// 3. A subset of lights keeps every other bit.

#[test]
fn baking_one_light_keeps_every_other_bit() {
    let dir = small();
    let full = dir.path().join("full.json");
    let out = run(&[
        "bake",
        &settings(&dir),
        "--quiet",
        "--report",
        full.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let full = masks(&report_of(&full));
    assert!(full.values().any(|(m, _)| m & 0b101 != 0 && m & 0b010 != 0));
    let baked = files(dir.path());

    // Re-baking the spot alone changes nothing: the sun's and the point's
    // bits stay (before: every mask became the spot's bit alone).
    let one = dir.path().join("one.json");
    let out = run(&[
        "bake",
        &settings(&dir),
        "--light",
        "spot",
        "--quiet",
        "--report",
        one.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).contains("wrote 0 of 4"),
        "{}",
        text(&out.stdout)
    );
    let mut after = files(dir.path());
    after.retain(|p, _| !p.ends_with("one.json"));
    assert_eq!(after, baked);
    assert_eq!(masks(&report_of(&one)), full);
    assert_eq!(report_of(&one)["lights"].as_array().unwrap().len(), 1);

    // The sun again, from a settings file of its own at bit 7: bits 0–2
    // stay as they were, bit 7 is the sun's verdict (= bit 0).
    edit(
        dir.path(),
        SETTINGS_FILE,
        "<type>",
        "<bit>\t7\t</bit>\n\t\t\t<type>",
    );
    let seven = dir.path().join("seven.json");
    let out = run(&[
        "bake",
        &settings(&dir),
        "--light",
        "sun",
        "--quiet",
        "--report",
        seven.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let seven = masks(&report_of(&seven));
    assert_eq!(seven.len(), full.len());
    for (key, (mask, groups)) in &full {
        let (new_mask, new_groups) = &seven[key];
        assert_eq!(new_mask & 0b111, *mask, "{key:?}");
        assert_eq!((new_mask >> 7) & 1, mask & 1, "{key:?}");
        for (old, new) in groups.iter().zip(new_groups) {
            assert_eq!(*new, old | ((old & 1) << 7), "{key:?}");
        }
    }
}

#[test]
fn light_selection_and_bit_errors_name_the_lights() {
    let dir = small();
    let out = run(&["bake", &settings(&dir), "--light", "moon"]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr.contains("no light named `moon`") && stderr.contains("`sun`, `spot`, `point`"),
        "{stderr}"
    );
    // The point light given bit 0, which the sun holds by position.
    let path = dir.path().join(SETTINGS_FILE);
    let text_before = std::fs::read_to_string(&path).unwrap();
    let at = text_before.rfind("<type>").unwrap();
    std::fs::write(
        &path,
        format!("{}<bit> 0 </bit>{}", &text_before[..at], &text_before[at..]),
    )
    .unwrap();
    let out = run(&["bake", &settings(&dir)]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr.contains("light `point` and light `sun` both use bit 0"),
        "{stderr}"
    );
}

// ---------------------------------------------------------------------------
// 6. CI checks, the report.

#[test]
fn check_and_dry_run_list_what_would_change_and_write_nothing() {
    let dir = small();
    let before = files(dir.path());
    let check = run(&["bake", &settings(&dir), "--check", "--quiet"]);
    assert_eq!(check.status.code(), Some(1), "{}", text(&check.stderr));
    let stdout = text(&check.stdout);
    assert_eq!(stdout.matches("would change ").count(), 5, "{stdout}");
    assert!(stdout.contains("00000000o.chunk"), "{stdout}");
    assert!(text(&check.stderr).contains("--check: 4 chunk files would change"));
    assert_eq!(files(dir.path()), before);
    let dry = run(&["bake", &settings(&dir), "--dry-run", "--quiet"]);
    assert!(dry.status.success());
    assert!(text(&dry.stdout).contains("would change 4 of 4"));
    assert_eq!(files(dir.path()), before);

    assert!(run(&["bake", &settings(&dir), "--quiet"]).status.success());
    let check = run(&["bake", &settings(&dir), "--check", "--quiet"]);
    assert_eq!(check.status.code(), Some(0), "{}", text(&check.stderr));
    assert!(text(&check.stdout).contains("would change 0 of 4"));
}

#[test]
fn the_report_lists_files_and_versions_and_can_go_to_stdout() {
    let dir = small();
    let out = run(&["bake", &settings(&dir), "--report", "-", "--quiet"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).expect("stdout is the report alone");
    assert_eq!(report["report_version"], 3);
    assert_eq!(report["tool_version"], env!("CARGO_PKG_VERSION"));
    let written: Vec<&str> = report["files_written"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert_eq!(written.len(), 4);
    assert!(written
        .iter()
        .all(|f| f.ends_with(".chunk") && Path::new(f).is_file()));
    assert!(
        text(&out.stderr).contains("wrote 4 of 4"),
        "the table goes to stderr"
    );
    let again = run(&["bake", &settings(&dir), "--report", "-", "--quiet"]);
    let report: Value = serde_json::from_slice(&again.stdout).unwrap();
    assert_eq!(report["files_written"].as_array().unwrap().len(), 0);
}

// ---------------------------------------------------------------------------
// 4. Plan and --max-memory.

#[test]
fn plan_lists_every_light_and_max_memory_refuses_before_tracing() {
    let dir = small();
    let out = run(&["plan", &settings(&dir), "--json", "--quiet"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let plan: Value = serde_json::from_slice(&out.stdout).unwrap();
    let lights = plan["lights"].as_array().unwrap();
    assert_eq!(lights.len(), 3);
    for light in lights {
        assert!(light["rays"].as_u64().unwrap() > 0, "{light}");
        assert!(light["rays_per_second"].as_f64().unwrap() > 0.0, "{light}");
        assert!(light["instances"].as_u64().unwrap() > 0, "{light}");
    }
    let text_plan = run(&["plan", &settings(&dir), "--quiet"]);
    let lines = text(&text_plan.stdout);
    assert!(
        lines.contains("calibration") && lines.contains("peak memory"),
        "{lines}"
    );
    // The bake prints the same lines first.
    let bake = run(&["bake", &settings(&dir), "--dry-run"]);
    assert!(text(&bake.stderr).contains("plan: light 0 `sun`"));

    let before = files(dir.path());
    let refused = run(&[
        "bake",
        &settings(&dir),
        "--max-memory",
        "1k",
        "--progress",
        "json",
    ]);
    let stderr = text(&refused.stderr);
    assert_eq!(refused.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("above --max-memory 1.0 kB"), "{stderr}");
    assert!(!stderr.contains("\"tracing\""), "{stderr}");
    assert_eq!(files(dir.path()), before);
    assert_eq!(
        run(&["bake", &settings(&dir), "--max-memory", "lots"])
            .status
            .code(),
        Some(2)
    );
}

#[test]
fn plan_max_memory_exits_1_naming_the_estimate_and_the_limit() {
    let dir = small();
    let within = run(&["plan", &settings(&dir), "--max-memory", "64G", "--quiet"]);
    assert!(within.status.success(), "{}", text(&within.stderr));
    let out = run(&["plan", &settings(&dir), "--max-memory", "1k", "--json"]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    let plan: Value = serde_json::from_slice(&out.stdout).unwrap();
    let estimate = plan["estimated_peak_bytes"].as_f64().unwrap();
    assert!(estimate > 1e6, "{estimate}");
    // The message names both, in the units `plan` prints.
    let named = format!("{:.1} MB", estimate / 1e6);
    assert!(
        stderr.contains(&format!(
            "the plan's peak memory estimate {named} is above --max-memory 1.0 kB"
        )),
        "{stderr}"
    );
}

/// `plan`'s estimates against `/usr/bin/time` of the same bake. Tests run
/// in parallel on a shared machine, and the first run of a fresh binary
/// pays for cold caches, so one plan against one bake measures the noise
/// as much as the estimate: plan and bake alternate three times and the
/// medians are compared, as the README's figures are.
/// `allowance_seconds` is how far apart the two times may be whatever
/// their ratio.
fn plan_within_a_factor_two(dir: &TempDir, allowance_seconds: f64) {
    let rounds: Vec<[f64; 4]> = (0..3).map(|_| plan_and_bake(dir)).collect();
    let median = |field: usize| {
        let mut values: Vec<f64> = rounds.iter().map(|r| r[field]).collect();
        values.sort_by(f64::total_cmp);
        values[values.len() / 2]
    };
    let (seconds, bytes) = (median(0), median(1));
    let (measured_seconds, measured_bytes) = (median(2), median(3));
    let time_ratio = seconds / measured_seconds.max(0.01);
    let memory_ratio = bytes / measured_bytes;
    eprintln!(
        "medians of 3: plan {seconds:.2} s / measured {measured_seconds:.2} s; plan {bytes} B / measured {measured_bytes} B ({rounds:?})"
    );
    let within_noise = (seconds - measured_seconds).abs() <= allowance_seconds;
    assert!(
        (0.5..=2.0).contains(&time_ratio) || within_noise,
        "time: plan {seconds} s, measured {measured_seconds} s (medians of {rounds:?})"
    );
    assert!(
        (0.5..=2.0).contains(&memory_ratio),
        "memory: plan {bytes} B, measured {measured_bytes} B (medians of {rounds:?})"
    );
}

/// A fixture bakes in a few hundredths of a second, where the clock's
/// hundredths and a loaded machine's scheduling move both figures by more
/// than the estimate's own error (0.15 s measured against 0.33 s planned has
/// been seen with every test running at once): within this the ratio says
/// nothing, and `bench`, baking for longer, checks it without allowance.
const SCHEDULING_NOISE_SECONDS: f64 = 0.25;

/// One plan and one timed bake: [estimated s, estimated B, measured s, measured B].
fn plan_and_bake(dir: &TempDir) -> [f64; 4] {
    // Without a cache: a cached plan estimates what the cache leaves to
    // trace, which a bake after it no longer traces.
    let out = run(&["plan", &settings(dir), "--json", "--quiet", "--no-cache"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let plan: Value = serde_json::from_slice(&out.stdout).unwrap();
    let seconds = plan["estimated_seconds"].as_f64().unwrap();
    let bytes = plan["estimated_peak_bytes"].as_f64().unwrap();
    let target = dir.path().join("out");
    // Every round writes every file, as the first did.
    let _ = std::fs::remove_dir_all(&target);
    let timed = std::process::Command::new("/usr/bin/time")
        .args(["-f", "%e %M", env!("CARGO_BIN_EXE_shadowcull"), "bake"])
        .args([&settings(dir), "--quiet", "--no-cache", "--out"])
        .arg(&target)
        .output()
        .expect("/usr/bin/time");
    let stderr = text(&timed.stderr);
    assert!(timed.status.success(), "{stderr}");
    let last = stderr.lines().last().unwrap();
    let mut fields = last.split_whitespace();
    let measured_seconds: f64 = fields.next().unwrap().parse().unwrap();
    let measured_bytes = fields.next().unwrap().parse::<f64>().unwrap() * 1024.0;
    [seconds, bytes, measured_seconds, measured_bytes]
}

/// A ratio of measured times: other work on the machine moves it, so it
/// runs only where `SHADOWCULL_SLOW` is set (`.ci/run` sets it), never in a
/// plain `cargo test`.
#[test]
#[cfg_attr(
    not(shadowcull_slow),
    ignore = "a ratio of measured times: set SHADOWCULL_SLOW=1 (.ci/run does)"
)]
fn plan_estimates_are_within_a_factor_two_on_the_fixtures() {
    assert!(
        Path::new("/usr/bin/time").exists(),
        "{} needs /usr/bin/time (Debian package `time`)",
        "plan_estimates_are_within_a_factor_two_on_the_fixtures"
    );
    plan_within_a_factor_two(&world(Preset::Small), SCHEDULING_NOISE_SECONDS);
    plan_within_a_factor_two(&world(Preset::Village), SCHEDULING_NOISE_SECONDS);
}

#[test]
#[cfg_attr(
    not(shadowcull_slow),
    ignore = "a ratio of measured times: set SHADOWCULL_SLOW=1 (.ci/run does)"
)]
fn plan_estimates_are_within_a_factor_two_on_bench() {
    assert!(
        Path::new("/usr/bin/time").exists(),
        "{} needs /usr/bin/time (Debian package `time`)",
        "plan_estimates_are_within_a_factor_two_on_bench"
    );
    plan_within_a_factor_two(&world(Preset::Bench), 0.0);
}

// ---------------------------------------------------------------------------
// 5. Progress for machines and people.

#[test]
fn progress_json_lines_parse_and_lines_carry_time_light_and_eta() {
    let dir = small();
    let out = run(&["bake", &settings(&dir), "--dry-run", "--progress", "json"]);
    assert!(out.status.success());
    let stderr = text(&out.stderr);
    let events = json_events(&out.stderr);
    let objects = events_named(&events, "progress");
    for object in &objects {
        for field in ["phase", "light", "done", "total", "eta_s"] {
            assert!(object.get(field).is_some(), "{object}");
        }
    }
    for light in ["sun", "spot", "point"] {
        let done = objects
            .iter()
            .find(|o| o["phase"] == "tracing" && o["light"] == light && o["done"] == o["total"]);
        assert!(done.is_some(), "{light}: {stderr}");
    }
    assert!(objects.iter().any(|o| o["phase"] == "chunks"));

    let lines = run(&[
        "bake",
        &settings(&dir),
        "--dry-run",
        "--progress",
        "lines",
        "--progress-interval",
        "0",
    ]);
    let stderr = text(&lines.stderr);
    let tracing: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("tracing light"))
        .collect();
    assert!(tracing.len() >= 3, "{stderr}");
    for line in tracing {
        assert!(
            line.starts_with('[') && line.contains(" s] ") && line.contains("eta"),
            "{line}"
        );
    }
    // Preparing the output and writing it advance chunk by chunk, file by
    // file: a long write has an ETA, not a jump from 0 to the total.
    let out = dir.path().join("out");
    let written = run(&[
        "bake",
        &settings(&dir),
        "--out",
        out.to_str().unwrap(),
        "--progress",
        "json",
        "--progress-interval",
        "0",
    ]);
    let stderr = text(&written.stderr);
    assert!(written.status.success(), "{stderr}");
    let events = json_events(&written.stderr);
    let objects = events_named(&events, "progress");
    // Writing under --out counts space.settings too.
    for (phase, files) in [("output", 4), ("writing", 5)] {
        let of: Vec<&&Value> = objects.iter().filter(|o| o["phase"] == phase).collect();
        assert!(
            of.iter().any(|o| o["total"] == files && o["done"] == files),
            "{phase}: {stderr}"
        );
        assert!(
            of.iter().any(|o| o["done"].as_u64() > Some(0)
                && o["done"] != o["total"]
                && o["eta_s"].is_number()),
            "{phase}: {stderr}"
        );
    }

    let quiet = run(&["bake", &settings(&dir), "--dry-run", "--quiet"]);
    assert!(quiet.status.success());
    assert_eq!(text(&quiet.stderr), "", "--quiet prints nothing on stderr");
}

/// Every line of `stderr` as a JSON object with a string `event`: the
/// promise of `--progress json`.
fn json_events(stderr: &[u8]) -> Vec<Value> {
    let stderr = text(stderr);
    assert!(!stderr.is_empty());
    stderr
        .lines()
        .map(|line| {
            let object: Value = serde_json::from_str(line)
                .unwrap_or_else(|e| panic!("not JSON ({e}): {line}\n{stderr}"));
            assert!(object["event"].is_string(), "no event: {line}");
            object
        })
        .collect()
}

fn events_named<'a>(events: &'a [Value], name: &str) -> Vec<&'a Value> {
    events.iter().filter(|e| e["event"] == name).collect()
}

#[test]
fn progress_json_makes_every_line_on_standard_error_a_json_object() {
    let dir = small();
    // A normal bake, its table on standard error beside the report.
    let out = run(&[
        "bake",
        &settings(&dir),
        "--dry-run",
        "--report",
        "-",
        "--progress",
        "json",
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).expect("stdout is the report alone");
    assert!(report["casters"].is_array());
    let events = json_events(&out.stderr);
    let loaded = events_named(&events, "loaded");
    assert_eq!(loaded.len(), 1, "{events:?}");
    assert_eq!(loaded[0]["chunks"], 4);
    assert_eq!(events_named(&events, "plan").len(), 3);
    assert_eq!(events_named(&events, "plan_total").len(), 1);
    assert!(events_named(&events, "progress")
        .iter()
        .any(|e| e["phase"] == "tracing"));
    let summary = events_named(&events, "summary");
    assert!(summary.iter().any(|e| e["message"]
        .as_str()
        .unwrap()
        .starts_with("would change 4 of 4")));

    // Warnings and problems left out by --keep-going: an unknown element,
    // a locked chunk, a damaged chunk.
    insert_into_settings(&dir, "<lights>", "<heightBais> 0.5 </heightBais>");
    let chunk = dir.path().join(CHUNK);
    std::fs::write(&chunk, b"<root><model>").unwrap();
    let locked = dir.path().join("spaces/small/0000ffffo.chunk");
    let mut permissions = std::fs::metadata(&locked).unwrap().permissions();
    permissions.set_readonly(true);
    std::fs::set_permissions(&locked, permissions).unwrap();
    let out = run(&[
        "bake",
        &settings(&dir),
        "--keep-going",
        "--progress",
        "json",
    ]);
    let events = json_events(&out.stderr);
    let warnings = events_named(&events, "warning");
    assert!(
        warnings
            .iter()
            .any(|w| w["message"].as_str().unwrap().contains("<heightBais>")),
        "{events:?}"
    );
    assert!(
        warnings.iter().any(|w| w["message"]
            .as_str()
            .unwrap()
            .contains("cannot be replaced")),
        "{events:?}"
    );
    let problems = events_named(&events, "problem");
    assert_eq!(problems.len(), 1, "{events:?}");
    assert_eq!(problems[0]["left_out"], true);
    assert!(problems[0]["what"]
        .as_str()
        .unwrap()
        .contains("00000000o.chunk"));
    // It fails at the end: the locked chunk must change.
    assert_eq!(out.status.code(), Some(1));
    let errors = events_named(&events, "error");
    assert_eq!(errors.len(), 1, "{events:?}");
    assert_eq!(events.last(), Some(errors[0]), "the error is the last word");

    // A failing bake: the problems, then the error; plan and inspect alike.
    for args in [
        &["bake", &settings(&dir), "--progress", "json"][..],
        &["plan", &settings(&dir), "--progress", "json"],
        &["inspect", &settings(&dir), "--progress", "json"],
    ] {
        let out = run(args);
        assert_eq!(out.status.code(), Some(1), "{args:?}");
        let events = json_events(&out.stderr);
        assert_eq!(
            events.last().unwrap()["event"],
            "error",
            "{args:?}: {events:?}"
        );
    }
    let out = run(&["bake", &settings(&dir), "--progress", "json"]);
    let events = json_events(&out.stderr);
    let problems = events_named(&events, "problem");
    assert_eq!(problems.len(), 1, "the settings file's element: {events:?}");
    assert_eq!(problems[0]["left_out"], false);
    assert!(problems[0]["why"]
        .as_str()
        .unwrap()
        .contains("did you mean <heightBias>?"));
    let out = run(&[
        "bake",
        &settings(&dir),
        "--keep-going",
        "--dry-run",
        "--progress=json",
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    json_events(&out.stderr);
    // A usage error, before the arguments parse.
    let out = run(&[
        "bake",
        &settings(&dir),
        "--progress",
        "json",
        "--no-such-flag",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let events = json_events(&out.stderr);
    assert_eq!(events.len(), 1, "{events:?}");
    assert!(events[0]["message"]
        .as_str()
        .unwrap()
        .contains("--no-such-flag"));
}

#[test]
fn a_merge_says_it_merges_and_that_it_traces_refinement() {
    let dir = small();
    let parts: Vec<String> = (0..2)
        .map(|i| {
            let partial = dir.path().join(format!("{i}.part")).display().to_string();
            let out = run(&[
                "bake",
                &settings(&dir),
                "--shard",
                &format!("{i}/2"),
                "--partial",
                &partial,
            ]);
            assert!(out.status.success(), "{}", text(&out.stderr));
            partial
        })
        .collect();
    let merge = |extra: &[&str]| {
        let settings = settings(&dir);
        let mut args = vec!["merge", &settings];
        args.extend(parts.iter().map(String::as_str));
        args.extend([
            "--dry-run",
            "--progress",
            "lines",
            "--progress-interval",
            "0",
        ]);
        args.extend(extra);
        let out = run(&args);
        assert!(out.status.success(), "{}", text(&out.stderr));
        text(&out.stderr)
    };
    let plain = merge(&[]);
    assert!(
        !plain.contains("tracing"),
        "a merge traces no grid: {plain}"
    );
    for light in ["sun", "spot", "point"] {
        assert!(
            plain.contains(&format!("merging light {light}:")),
            "{plain}"
        );
    }
    assert!(plain.contains("no grid ray is traced here"), "{plain}");
    assert!(!plain.contains("refin"), "{plain}");
    let refined = merge(&["--refine"]);
    assert!(!refined.contains("tracing"), "{refined}");
    assert!(
        refined.contains("refinement rays are traced here") && refined.contains("refining light"),
        "{refined}"
    );
}

#[test]
fn plan_counts_model_parts_and_says_so() {
    // An instance with two <resource>s is two parts of a light's reach:
    // the plan's counts are parts, the loaded line's instances.
    let dir = small();
    let scene = shadowcull::scene::load_scene(&shadowcull::scene::LoadConfig {
        res_paths: shadowcull::files::ResPaths::new(vec![dir.path().to_path_buf()]),
        space: "spaces/small".into(),
        speedtrees: Default::default(),
    })
    .unwrap();
    let instances = scene.instances.len();
    let parts: usize = scene.instances.iter().map(|i| i.parts.len()).sum();
    assert!(parts > instances, "the small world has two-part instances");
    let model_triangles: usize = scene
        .instances
        .iter()
        .flat_map(|i| i.parts.iter().flatten())
        .map(|&m| scene.models[m].triangles.len())
        .sum();
    let terrain_triangles: usize = scene
        .terrain
        .iter()
        .map(|block| {
            let (cx, cz) = block.cells();
            let holes = (0..cz)
                .flat_map(|z| (0..cx).map(move |x| (x, z)))
                .filter(|&(x, z)| block.cell_is_hole(x, z))
                .count();
            2 * (cx * cz - holes)
        })
        .sum();
    let blocks = scene.terrain.len();

    let out = run(&["bake", &settings(&dir), "--dry-run", "--progress", "lines"]);
    let stderr = text(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "loaded 4 chunks, {instances} instances ({parts} model parts), {model_triangles} model triangles, {blocks} terrain blocks"
        )),
        "{stderr}"
    );
    // The sun's grid covers the world: everything is in its reach.
    assert!(
        stderr.contains(&format!(
            "in reach {parts} model parts, {blocks} terrain blocks, {} triangles (parts' and blocks')",
            model_triangles + terrain_triangles
        )),
        "{stderr}"
    );
    let out = run(&["plan", &settings(&dir), "--json", "--quiet"]);
    let plan: Value = serde_json::from_slice(&out.stdout).unwrap();
    let sun = &plan["lights"][0];
    assert_eq!(
        sun["instances"], parts,
        "`instances` in the plan counts parts"
    );
    let out = run(&["bake", &settings(&dir), "--dry-run", "--progress", "json"]);
    let events = json_events(&out.stderr);
    let loaded = events_named(&events, "loaded")[0];
    assert_eq!(loaded["instances"], instances);
    assert_eq!(loaded["model_parts"], parts);
    assert_eq!(loaded["model_triangles"], model_triangles);
}

// ---------------------------------------------------------------------------
// 8. Small things.

#[test]
fn small_things() {
    // A missing file's OS error once.
    let missing = run(&["inspect", "/nonexistent/bake.xml"]);
    let stderr = text(&missing.stderr);
    assert_eq!(stderr.matches("No such file").count(), 1, "{stderr}");
    // A negative number is a value, not an unknown flag.
    let dir = small();
    let out = run(&["bake", &settings(&dir), "--height-bias", "-1"]);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("--height-bias must be a number ≥ 0, got -1"),
        "{stderr}"
    );
    // "1 problem", not "1 problems"; where the problems are is true
    // whether or not a report is written.
    std::fs::write(dir.path().join(CHUNK), b"<root><model>").unwrap();
    let report = dir.path().join("report.json");
    let kept = run(&["bake", &settings(&dir), "--keep-going", "--dry-run"]);
    let refused = run(&[
        "bake",
        &settings(&dir),
        "--report",
        report.to_str().unwrap(),
    ]);
    assert_eq!(refused.status.code(), Some(1));
    assert!(!report.exists(), "a refused bake writes no report");
    for (out, said) in [
        (kept, "; 1 problem (listed below), left out by --keep-going"),
        (refused, "; 1 problem (listed below)\n"),
    ] {
        let stderr = text(&out.stderr);
        assert!(stderr.contains(said), "{stderr}");
        assert!(!stderr.contains("1 problems"), "{stderr}");
        assert!(!stderr.contains("the report's"), "{stderr}");
        let listed = stderr.split(said).nth(1).unwrap_or_default();
        assert!(listed.contains("00000000o.chunk"), "{stderr}");
    }
}

/// The folders and files a person who clones the repository reads: the
/// guard scans every text file under them (fixtures are generated data).
const SELF_CONTAINED_ROOTS: &[&str] = &[
    "README.md",
    "ARCHITECTURE.md",
    "Cargo.toml",
    "docs",
    "src",
    "tests",
    "benches",
    "deploy",
    ".ci",
];

#[test]
fn the_repository_stands_on_its_own() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for name in SELF_CONTAINED_ROOTS {
        text_files(&root.join(name), &mut files);
    }
    assert!(files.len() > 50, "the walk found {} files", files.len());
    let mut found = Vec::new();
    for path in &files {
        let text = std::fs::read_to_string(path).unwrap();
        let shown = path.strip_prefix(root).unwrap().display().to_string();
        for (number, line) in text.lines().enumerate() {
            for what in outward_or_process_words(line) {
                found.push(format!("{shown}:{}: {what}: {}", number + 1, line.trim()));
            }
        }
        if shown.ends_with(".md") {
            found.extend(broken_links(root, path, &text));
        }
    }
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    if !readme.contains("docs/contract.md") || !root.join("docs/contract.md").is_file() {
        found.push("README.md: cites no docs/contract.md".to_string());
    }
    for line in readme.lines().filter(|l| l.contains("cargo run")) {
        if !line.contains("--release") {
            found.push(format!(
                "README.md: one build for every example, `cargo run --release`: {line}"
            ));
        }
    }
    assert!(
        found.is_empty(),
        "cite docs/contract.md §N and keep history in git:\n{}",
        found.join("\n")
    );
}

/// Every UTF-8 file under `path` (pictures and other binary files are
/// skipped), in a fixed order.
fn text_files(path: &Path, files: &mut Vec<PathBuf>) {
    if path.is_dir() {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(path)
            .unwrap()
            .map(|entry| entry.unwrap().path())
            .collect();
        entries.sort();
        for entry in entries {
            text_files(&entry, files);
        }
    } else if path.is_file() && std::fs::read_to_string(path).is_ok() {
        files.push(path.to_path_buf());
    }
}

/// What a line says that only its author's workspace would understand: a
/// document outside the repository, a ticket or work-round number, a
/// commit hash in prose. The needles are assembled here so that this file
/// does not match itself.
fn outward_or_process_words(line: &str) -> Vec<String> {
    let mut found = Vec::new();
    let outward = [
        ["..", "/shared"].concat(),
        ["SPEC", ".md"].concat(),
        ["SPEC", " \u{a7}"].concat(),
    ];
    for needle in &outward {
        if line.contains(needle.as_str()) {
            found.push(format!("`{needle}` lies outside the repository"));
        }
    }
    let lower = line.to_lowercase();
    for word in ["issue", "issues", "ticket", "stop", "round"] {
        if word_then_number(&lower, word) {
            found.push(format!("`{word} N` is development history"));
        }
    }
    let process = ["sess", "ion"].concat();
    if words(&lower).any(|w| w.starts_with(process.as_str())) {
        found.push(format!("`{process}` is development history"));
    }
    if let Some(hash) = commit_hash(line) {
        found.push(format!("`{hash}` looks like a commit hash"));
    }
    found
}

/// The line's words: maximal runs of letters and digits.
fn words(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| !c.is_ascii_alphanumeric())
        .filter(|w| !w.is_empty())
}

/// Whether `word` stands in `line` as a word followed by a space and a
/// digit, as numbered work rounds and tickets are written.
fn word_then_number(line: &str, word: &str) -> bool {
    line.match_indices(word).any(|(at, _)| {
        let before = line[..at].chars().next_back();
        let after = &line[at + word.len()..];
        !before.is_some_and(|c| c.is_ascii_alphanumeric())
            && after.starts_with(' ')
            && after[1..].starts_with(|c: char| c.is_ascii_digit())
    })
}

/// A run of 7 to 40 lowercase hex digits holding both a digit and a letter
/// (not a `0b`/`0x` literal) that is followed by a colon or stands in
/// parentheses, as a short commit hash is cited in prose.
fn commit_hash(line: &str) -> Option<&str> {
    let bytes = line.as_bytes();
    let mut start = 0;
    while start < bytes.len() {
        if !bytes[start].is_ascii_alphanumeric() {
            start += 1;
            continue;
        }
        let end = (start..bytes.len())
            .find(|&i| !bytes[i].is_ascii_alphanumeric())
            .unwrap_or(bytes.len());
        let token = &line[start..end];
        let hex = token
            .bytes()
            .all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'));
        let mixed = token.bytes().any(|b| b.is_ascii_digit())
            && token.bytes().any(|b| b.is_ascii_lowercase());
        let literal = token.starts_with("0b") || token.starts_with("0x");
        let cited = bytes.get(end).is_some_and(|&b| b == b':' || b == b')')
            || (start > 0 && bytes[start - 1] == b'(');
        if (7..=40).contains(&token.len()) && hex && mixed && !literal && cited {
            return Some(token);
        }
        start = end;
    }
    None
}

/// The relative links of a Markdown file whose target is missing or lies
/// outside the repository.
fn broken_links(root: &Path, path: &Path, text: &str) -> Vec<String> {
    let mut broken = Vec::new();
    for piece in text.split("](").skip(1) {
        let Some(target) = piece.split(')').next() else {
            continue;
        };
        let target = target.split('#').next().unwrap_or_default();
        if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
            continue;
        }
        let resolved = path.parent().unwrap().join(target);
        let inside = resolved
            .canonicalize()
            .is_ok_and(|p| p.starts_with(root.canonicalize().unwrap()));
        if !inside {
            broken.push(format!(
                "{}: link `{target}` is missing or outside the repository",
                path.strip_prefix(root).unwrap().display()
            ));
        }
    }
    broken
}

// ---------------------------------------------------------------------------
// 7. Pictures that find problems.

#[test]
fn render_from_chunks_draws_the_written_masks_and_lists_culled_casters() {
    let dir = small();
    let picture = dir.path().join("point.png");
    let legend_path = dir.path().join("point.txt");
    let settings_path = settings(&dir);
    let render = |extra: &[&str]| {
        let mut args = vec![
            "render",
            settings_path.as_str(),
            "--light",
            "point",
            "-o",
            picture.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let out = run(&args);
        assert!(out.status.success(), "{}", text(&out.stderr));
        (
            text(&out.stdout),
            std::fs::read_to_string(&legend_path).unwrap(),
        )
    };
    // Nothing baked yet: the chunks hold no masks, so no caster is useful
    // or culled; each is "no mask", counted and coloured as such.
    let (said, unbaked) = render(&["--from-chunks"]);
    assert!(
        unbaked.contains("from the masks in the chunk files (bit 2"),
        "{unbaked}"
    );
    let report = dir.path().join("r.json");
    let bake = run(&[
        "bake",
        &settings(&dir),
        "--quiet",
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(bake.status.success());
    let report = report_of(&report);
    let point = &report["lights"][2];
    let culled = point["culled_casters"].as_u64().unwrap();
    let useful = point["useful_casters"].as_u64().unwrap();
    let casters = useful + culled;
    assert!(
        unbaked.contains(&format!(
            "0 useful casters, 0 culled casters, {casters} casters without a mask"
        )),
        "{unbaked}"
    );
    assert!(
        said.contains(&format!("0 useful / 0 culled / {casters} no-mask casters")),
        "{said}"
    );
    assert!(
        unbaked.contains("culled casters (chunk, index, resource): 0\n"),
        "{unbaked}"
    );
    let no_mask_pixels = |legend: &str| -> u64 {
        let line = legend
            .lines()
            .find(|l| l.trim_start().starts_with("no mask"))
            .unwrap_or_else(|| panic!("no `no mask` colour in the legend:\n{legend}"));
        line.split_whitespace().last().unwrap().parse().unwrap()
    };
    assert!(no_mask_pixels(&unbaked) > 0, "{unbaked}");
    let (said, baked) = render(&["--from-chunks"]);
    assert!(
        baked.contains(&format!(
            "{useful} useful casters, {culled} culled casters, 0 casters without a mask"
        )),
        "{baked}"
    );
    assert!(
        said.contains(&format!(
            "{useful} useful / {culled} culled / 0 no-mask casters"
        )),
        "{said}"
    );
    assert_eq!(no_mask_pixels(&baked), 0, "{baked}");
    let listed = baked
        .split("culled casters (chunk, index, resource): ")
        .nth(1)
        .unwrap();
    let count: u64 = listed.split_whitespace().next().unwrap().parse().unwrap();
    assert_eq!(count, culled);
    // Each model entry names chunk, element, index and resource.
    assert!(
        listed.lines().skip(1).take(count as usize).all(|l| {
            let l = l.trim();
            l.ends_with(" terrain") || (l.contains(" model ") && l.contains(".model group "))
        }),
        "{listed}"
    );
    assert!(baked.contains("Okabe-Ito") && baked.contains("colour blindness"));
    assert!(baked.contains("each face is labelled"), "{baked}");
    // The bake's own verdicts agree with the masks it wrote.
    let (_, fresh) = render(&[]);
    assert!(fresh.contains(&format!("{useful} useful casters, {culled} culled casters")));
    // One chunk put back unbaked: its casters have no mask, every other
    // caster keeps its verdict.
    let unbaked_chunk = generate(Preset::Small, 1)
        .files
        .into_iter()
        .find(|(path, _)| path.as_str() == CHUNK)
        .unwrap()
        .1;
    std::fs::write(dir.path().join(CHUNK), unbaked_chunk).unwrap();
    let (mut here, mut kept) = (0, [0, 0]);
    for caster in report["casters"].as_array().unwrap() {
        if caster["receiver_only"] == true {
            continue;
        }
        let masks: Vec<u64> = match caster["groups"].as_array() {
            Some(groups) => groups.iter().map(|g| g.as_u64().unwrap()).collect(),
            None => vec![caster["mask"].as_u64().unwrap()],
        };
        if caster["chunk"] == "00000000o" {
            here += masks.len();
        } else {
            for mask in masks {
                kept[usize::from(mask & 4 == 0)] += 1;
            }
        }
    }
    assert!(here > 0 && kept[0] > 0 && kept[1] > 0, "{here} {kept:?}");
    let (said, partly) = render(&["--from-chunks"]);
    assert!(
        said.contains(&format!(
            "{} useful / {} culled / {here} no-mask casters",
            kept[0], kept[1]
        )),
        "{said}"
    );
    assert!(!partly.contains("00000000o model"), "{partly}");
}

#[test]
fn a_bake_out_copy_is_a_res_root_that_reads_before_the_original() {
    let dir = small();
    let settings_path = settings(&dir);
    let original = dir.path().display().to_string();
    let out = tempfile::tempdir().unwrap();
    let copy = out.path().join("baked");
    let copy_root = copy.display().to_string();
    let report = out.path().join("r.json");
    let bake = run(&[
        "bake",
        &settings_path,
        "--quiet",
        "--out",
        &copy_root,
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(bake.status.success(), "{}", text(&bake.stderr));
    let said = text(&bake.stdout);
    assert!(
        said.contains("chunk files and space.settings under"),
        "{said}"
    );
    // The space's settings beside the chunks, byte for byte.
    let space_settings = "spaces/small/space.settings";
    assert_eq!(
        std::fs::read(copy.join(space_settings)).unwrap(),
        std::fs::read(dir.path().join(space_settings)).unwrap()
    );
    let point = &report_of(&report)["lights"][2];
    let (useful, culled) = (
        point["useful_casters"].as_u64().unwrap(),
        point["culled_casters"].as_u64().unwrap(),
    );
    assert!(useful > 0);
    // The copy first, the original root (models, terrain) after it.
    let from_copy = ["--res-path", &copy_root, "--res-path", &original];
    let picture = out.path().join("point.png");
    let mut args = vec!["render", &settings_path, "--light", "point"];
    args.extend(from_copy);
    args.extend(["--from-chunks", "-o", picture.to_str().unwrap()]);
    let render = run(&args);
    assert!(render.status.success(), "{}", text(&render.stderr));
    assert!(
        text(&render.stdout).contains(&format!(
            "{useful} useful / {culled} culled / 0 no-mask casters"
        )),
        "{}",
        text(&render.stdout)
    );
    // The copy with the original loads without problems: each chunk's
    // terrain is found as SPACE/NAME.cdata in the original root.
    let mut args = vec!["inspect", &settings_path, "--json"];
    args.extend(from_copy);
    let inspect = run(&args);
    assert!(inspect.status.success(), "{}", text(&inspect.stdout));
    let inspected: Value = serde_json::from_slice(&inspect.stdout).unwrap();
    assert_eq!(inspected["terrain_blocks"], 4, "{inspected}");
    assert_eq!(inspected["problems"].as_array().map(Vec::len), Some(0));
    assert!(
        inspected["space"].as_str().unwrap().starts_with(&copy_root),
        "{inspected}"
    );
    // A later bake of the copy finds its masks current.
    let mut args = vec!["bake", &settings_path, "--check", "--quiet"];
    args.extend(from_copy);
    let check = run(&args);
    assert!(check.status.success(), "{}", text(&check.stdout));
    // Baking into the copy again changes nothing, space.settings included.
    let again = run(&["bake", &settings_path, "--quiet", "--out", &copy_root]);
    assert!(again.status.success(), "{}", text(&again.stderr));
    assert!(
        text(&again.stdout).contains("wrote 0 of 4 chunk files under"),
        "{}",
        text(&again.stdout)
    );
}

#[test]
fn the_report_lists_casters_sorted_by_chunk_kind_and_index_to_a_file_and_to_stdout() {
    let dir = world(Preset::Forest);
    let settings = settings(&dir);
    let path = dir.path().join("report.json");
    let baked = run(&["bake", &settings, "--dry-run", "--no-cache", "--report"]);
    assert!(!baked.status.success(), "--report needs a file");
    let to_file = run(&[
        "bake",
        &settings,
        "--dry-run",
        "--no-cache",
        "--report",
        path.to_str().unwrap(),
    ]);
    assert!(to_file.status.success(), "{}", text(&to_file.stderr));
    let to_stdout = run(&[
        "bake",
        &settings,
        "--dry-run",
        "--no-cache",
        "--report",
        "-",
    ]);
    assert!(to_stdout.status.success(), "{}", text(&to_stdout.stderr));
    let from_stdout: Value = serde_json::from_slice(&to_stdout.stdout).unwrap();
    let report = report_of(&path);
    assert_eq!(report["casters"], from_stdout["casters"]);
    let casters = report["casters"].as_array().unwrap();
    let kinds: std::collections::BTreeSet<&str> = casters
        .iter()
        .map(|c| c["kind"].as_str().unwrap())
        .collect();
    assert_eq!(
        kinds.into_iter().collect::<Vec<_>>(),
        ["model", "speedtree", "terrain"]
    );
    let keys: Vec<(String, String, i64)> = casters
        .iter()
        .map(|c| {
            (
                c["chunk"].as_str().unwrap().to_string(),
                c["kind"].as_str().unwrap().to_string(),
                c["index"].as_i64().unwrap_or(-1),
            )
        })
        .collect();
    let mut sorted = keys.clone();
    sorted.sort();
    sorted.dedup();
    assert_eq!(keys, sorted, "sorted, each caster once");
}

#[test]
fn savings_count_the_casters_the_report_lists_for_a_light_that_reaches_everything() {
    let dir = world(Preset::Village);
    let path = dir.path().join("report.json");
    let settings = settings(&dir);
    let baked = run(&[
        "bake",
        &settings,
        "--dry-run",
        "--no-cache",
        "--report",
        path.to_str().unwrap(),
    ]);
    assert!(baked.status.success(), "{}", text(&baked.stderr));
    assert!(text(&baked.stdout).contains("shadow pass"));
    let report = report_of(&path);
    let casters = report["casters"].as_array().unwrap();
    let parts: u64 = casters
        .iter()
        .filter_map(|c| c["resources"].as_array())
        .map(|r| r.len() as u64)
        .sum();
    let everything = report["lights"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|l| l["instances"].as_u64() == Some(parts))
        .collect::<Vec<_>>();
    assert!(!everything.is_empty(), "the sun reaches every part");
    for light in everything {
        let bit = 1u64 << light["bit"].as_u64().unwrap();
        let (mut instances, mut draw_calls) = ((0, 0), (0, 0));
        for caster in casters {
            if caster["receiver_only"] == true {
                continue;
            }
            let groups: Vec<u64> = match caster["groups"].as_array() {
                Some(groups) => groups.iter().map(|m| m.as_u64().unwrap()).collect(),
                None if caster["kind"] == "terrain" => vec![caster["mask"].as_u64().unwrap()],
                None => continue,
            };
            let kept = groups.iter().filter(|&&m| m & bit != 0).count();
            draw_calls.0 += groups.len() as u64;
            draw_calls.1 += kept as u64;
            if caster["kind"] != "terrain" && !groups.is_empty() {
                instances.0 += 1;
                instances.1 += u64::from(kept > 0);
            }
        }
        let savings = &light["savings"];
        let pair = |what: &str| {
            (
                savings[what]["before"].as_u64().unwrap(),
                savings[what]["after"].as_u64().unwrap(),
            )
        };
        assert_eq!(pair("draw_calls"), draw_calls, "{}", light["name"]);
        assert_eq!(pair("instances"), instances, "{}", light["name"]);
        let (before, after) = pair("triangles");
        assert!(after <= before && before <= light["triangles"].as_u64().unwrap());
        let removed = savings["triangles_removed"].as_f64().unwrap();
        assert!((removed - (1.0 - after as f64 / before as f64)).abs() < 1e-12);
        assert!(draw_calls.1 < draw_calls.0, "the village culls something");
    }
}
