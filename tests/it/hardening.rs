//! Files that are not files, stray placements, paths out of the res roots,
//! locked and linked chunks, interrupted runs. Each test fails when the
//! guard it names is taken out.

use shadowcull::bake::{self, output, BakeConfig, Silent};
use shadowcull::files::read_bake_settings;
use shadowcull::files::{host_name, write_tree, ResPaths, STALE_TEMPORARY_AGE};
use shadowcull::gen::{generate, stack_first_model, Preset, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig, Problem, Scene};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};
use tempfile::TempDir;

const SPACE: &str = "spaces/small";
const CHUNK: &str = "spaces/small/00000000o.chunk";

fn small_world() -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(Preset::Small, 1).files).unwrap();
    dir
}

fn load(dir: &Path) -> Scene {
    let settings = read_bake_settings(&dir.join(SETTINGS_FILE)).unwrap();
    load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths),
        space: settings.space,
        speedtrees: settings.speedtrees,
    })
    .unwrap()
}

fn replace_text(dir: &Path, file: &str, from: &str, to: &str) {
    let path = dir.join(file);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains(from), "{file} holds no `{from}`");
    std::fs::write(path, text.replacen(from, to, 1)).unwrap();
}

fn problem<'a>(scene: &'a Scene, what_contains: &str) -> &'a Problem {
    scene
        .problems
        .iter()
        .find(|p| p.what.contains(what_contains))
        .unwrap_or_else(|| panic!("no problem about {what_contains}: {:#?}", scene.problems))
}

/// Runs the binary, killing it and failing when it takes longer than
/// `limit` (a hang).
fn run_bounded(args: &[&str], limit: Duration) -> Output {
    run_command_bounded(
        Command::new(env!("CARGO_BIN_EXE_shadowcull")).args(args),
        limit,
    )
}

fn run_command_bounded(command: &mut Command, limit: Duration) -> Output {
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run shadowcull");
    let started = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{command:?} still ran after {limit:?}: it hangs");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Every file of the world under `dir` (not following links to folders;
/// not the bake cache a bake keeps beside its settings file): bytes and
/// modification time, by path; links as their target path.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, (Vec<u8>, Option<SystemTime>)> {
    let mut files = BTreeMap::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(dir) = pending.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let entry = entry.unwrap();
            let path = entry.path();
            let kind = entry.file_type().unwrap();
            if kind.is_dir() && entry.file_name() == ".shadowcull-cache" {
                continue;
            }
            if kind.is_dir() {
                pending.push(path);
            } else if kind.is_symlink() {
                let target = std::fs::read_link(&path).unwrap();
                files.insert(path, (target.to_string_lossy().as_bytes().to_vec(), None));
            } else if kind.is_file() {
                let modified = entry.metadata().unwrap().modified().ok();
                files.insert(path, (std::fs::read(entry.path()).unwrap(), modified));
            }
        }
    }
    files
}

/// Temporary files of the write path anywhere under `dir`.
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    snapshot(dir)
        .into_keys()
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.contains(".shadowcull-"))
        })
        .collect()
}

/// The bake settings of the small world with coarse lights (the tests here
/// are about files, not rays).
fn coarse_settings(dir: &Path) -> PathBuf {
    let path = dir.join(SETTINGS_FILE);
    replace_text(dir, SETTINGS_FILE, "0.195312", "1.000000");
    replace_text(dir, SETTINGS_FILE, "\t512\t", "\t64\t");
    replace_text(dir, SETTINGS_FILE, "\t256\t", "\t32\t");
    path
}

fn bake_in_place(settings: &Path) -> Output {
    run_bounded(
        &["bake", settings.to_str().unwrap()],
        Duration::from_secs(120),
    )
}

// ---------------------------------------------------------------------------
// 1. Files that are not files.

#[cfg(unix)]
fn mkfifo(path: &Path) {
    let status = Command::new("mkfifo").arg(path).status().expect("mkfifo");
    assert!(status.success(), "mkfifo {}", path.display());
}

#[cfg(unix)]
#[test]
fn fifo_chunk_and_cdata_are_problems_not_hangs() {
    // `mkfifo W/spaces/small/x.chunk` must not block inspect and bake
    // (opening a FIFO waits for a writer).
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let space = dir.path().join(SPACE);
    mkfifo(&space.join("x.chunk"));
    std::fs::remove_file(space.join("0000ffffo.cdata")).unwrap();
    mkfifo(&space.join("0000ffffo.cdata"));

    let output = run_bounded(
        &["inspect", settings.to_str().unwrap(), "--json"],
        Duration::from_secs(60),
    );
    assert_eq!(output.status.code(), Some(1), "{}", text(&output.stderr));
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let problems = json["problems"].as_array().unwrap();
    let about = |what: &str| {
        problems
            .iter()
            .find(|p| p["what"].as_str().unwrap().ends_with(what))
            .unwrap_or_else(|| panic!("no problem about {what}: {problems:#?}"))["why"]
            .as_str()
            .unwrap()
            .to_string()
    };
    assert!(about("x.chunk").contains("is a FIFO (named pipe), not a regular file"));
    assert!(about("0000ffffo.chunk <terrain>").contains("0000ffffo.cdata: is a FIFO"));
    assert_eq!(json["chunks"], 4);
    assert_eq!(json["terrain_blocks"], 3);

    let out = tempfile::tempdir().unwrap();
    let output = run_bounded(
        &[
            "bake",
            settings.to_str().unwrap(),
            "--out",
            out.path().to_str().unwrap(),
            "--keep-going",
        ],
        Duration::from_secs(120),
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(text(&output.stderr).contains("problems"));
}

#[cfg(unix)]
#[test]
fn links_to_dev_zero_and_oversized_files_are_refused_without_reading() {
    // A chunk linked to /dev/zero would be read until memory ran out.
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let space = dir.path().join(SPACE);
    std::os::unix::fs::symlink("/dev/zero", space.join("zero.chunk")).unwrap();
    std::fs::remove_file(space.join("ffff0000o.cdata")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", space.join("ffff0000o.cdata")).unwrap();
    // A 1 GiB + 1 byte terrain file (sparse: nothing is stored).
    let huge = std::fs::File::create(space.join("ffffffffo.cdata")).unwrap();
    huge.set_len((1 << 30) + 1).unwrap();
    drop(huge);

    let output = run_bounded(
        &["inspect", settings.to_str().unwrap()],
        Duration::from_secs(60),
    );
    assert_eq!(output.status.code(), Some(1), "{}", text(&output.stderr));
    let report = text(&output.stdout);
    for expected in [
        "zero.chunk: is a character device (through a symbolic link), not a regular file",
        // Terrain files must lie inside the res roots: refused before that.
        "ffff0000o.cdata: leads to /dev/zero, outside every res path",
        "ffffffffo.cdata: holds 1073741825 bytes, more than the cap of 1024 MiB for .cdata files",
    ] {
        assert!(report.contains(expected), "no `{expected}` in\n{report}");
    }
    let scene = load(dir.path());
    assert_eq!((scene.chunks.len(), scene.terrain.len()), (4, 2));
}

// ---------------------------------------------------------------------------
// 2. Stacked coincident geometry.

/// Each instance's per-group masks from a bake report, in report order.
fn group_masks(report: &Path) -> Vec<(String, usize, Vec<u64>)> {
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(report).unwrap()).unwrap();
    json["casters"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["kind"] == "model")
        .map(|c| {
            let groups = c["groups"].as_array().unwrap();
            (
                c["chunk"].as_str().unwrap().to_string(),
                c["index"].as_u64().unwrap() as usize,
                groups.iter().map(|g| g.as_u64().unwrap()).collect(),
            )
        })
        .collect()
}

#[test]
fn stacked_coincident_copies_bake_in_near_linear_time_and_tie() {
    // Copies of one house at one transform (a level editor's duplicate
    // key) tie at every ray through them: a ray that re-sorted its hit list
    // after every tied hit would take quadratic time in the copies. The
    // bound leaves a debug build ten times its need.
    const COPIES: usize = 2000;
    let single = small_world();
    let stacked = small_world();
    let chunk = stacked.path().join(CHUNK);
    let bytes = std::fs::read(&chunk).unwrap();
    std::fs::write(&chunk, stack_first_model(&bytes, COPIES).unwrap()).unwrap();
    let mut masks = Vec::new();
    for world in [&single, &stacked] {
        let settings = coarse_settings(world.path());
        let report = world.path().join("report.json");
        let out = run_bounded(
            &[
                "bake",
                settings.to_str().unwrap(),
                "--dry-run",
                "--report",
                report.to_str().unwrap(),
            ],
            Duration::from_secs(60),
        );
        assert!(out.status.success(), "{}", text(&out.stderr));
        masks.push(group_masks(&report));
    }
    let (single, stacked) = (&masks[0], &masks[1]);
    assert_eq!(stacked.len(), single.len() + COPIES - 1);
    // The copies tie on every ray, so they share one verdict; and each copy
    // is useful wherever the lone house was (a copy behind it only adds
    // surface crossings).
    let copies: Vec<_> = stacked
        .iter()
        .filter(|(c, i, _)| c == "00000000o" && *i < COPIES)
        .collect();
    assert_eq!(copies.len(), COPIES);
    let lone = &single
        .iter()
        .find(|(c, i, _)| c == "00000000o" && *i == 0)
        .unwrap()
        .2;
    for (_, index, groups) in &copies {
        assert_eq!(groups, &copies[0].2, "copy {index}");
    }
    for (stacked, lone) in copies[0].2.iter().zip(lone) {
        assert_eq!(
            stacked & lone,
            *lone,
            "a copy lost a bit the lone house has"
        );
    }
}

// ---------------------------------------------------------------------------
// 3. One stray placement.

#[test]
fn a_stray_placement_is_a_problem_and_the_sun_grid_stays_the_space() {
    // Model 0's <row3> moved 2^31 m along z must not make every light
    // fail (a shadow map of billions of texels a side) while inspect says
    // "no problems". Model 1 lifted 20 km.
    let clean = small_world();
    let stray = small_world();
    replace_text(
        stray.path(),
        CHUNK,
        "0.000000 -0.941000 0.000000",
        "0 -0.941 -2147483649",
    );
    replace_text(
        stray.path(),
        CHUNK,
        "16.000000 -0.371000 4.000000",
        "16 20000 4",
    );
    let clean_scene = load(clean.path());
    let scene = load(stray.path());
    for element in ["model[0]/transform", "model[1]/transform"] {
        let problem = problem(&scene, &format!("00000000o.chunk <{element}>"));
        assert!(
            problem
                .why
                .starts_with("far outside the space: its world box")
                && problem.why.contains("x -100.0..100.0, z -100.0..100.0"),
            "{problem:?}"
        );
    }
    assert_eq!(scene.problems.len(), 2, "{:#?}", scene.problems);
    assert_eq!(scene.instances.len() + 2, clean_scene.instances.len());
    let inspection = shadowcull::inspect::inspect(&scene, Default::default()).to_text();
    assert!(
        inspection.contains("2 problems;") && inspection.contains("far outside the space"),
        "{inspection}"
    );

    let settings = read_bake_settings(&stray.path().join(SETTINGS_FILE)).unwrap();
    let mut config = BakeConfig::from_settings(&settings);
    config.lights.truncate(1);
    let baked = bake::bake(&scene, &config, &Silent).expect("the bake runs");
    let clean_baked = bake::bake(&clean_scene, &config, &Silent).unwrap();
    // The sun's grid covers the same ground as without the stray house.
    assert_eq!(baked.lights[0].rays, clean_baked.lights[0].rays);
    assert!(baked.lights[0].rays < 1_000_000);
    for element in ["model[0]/transform", "model[1]/transform"] {
        assert!(
            baked
                .skipped
                .iter()
                .any(|s| s.what.contains(element) && s.why.contains("far outside")),
            "{:#?}",
            baked.skipped
        );
    }
}

/// The rays of the report's first light (the sun).
fn sun_rays(report: &Path) -> u64 {
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report).unwrap()).unwrap();
    assert_eq!(report["lights"][0]["name"], "sun");
    report["lights"][0]["rays"].as_u64().unwrap()
}

#[test]
fn a_placement_kilometres_above_the_terrain_is_a_stray_and_fails_the_bake() {
    // Inside the old ±10 km, one house lifted to 9 km gave "no problems"
    // and a sun grid 351× larger (its slant moves the box kilometres
    // sideways). The space's terrain lies within a few metres of 0.
    let clean = small_world();
    let clean_settings = coarse_settings(clean.path());
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    replace_text(
        dir.path(),
        CHUNK,
        "16.000000 -0.371000 4.000000",
        "0 9000 0",
    );
    let scene = load(dir.path());
    let stray = problem(&scene, "00000000o.chunk <model[1]/transform>");
    assert!(
        stray
            .why
            .starts_with("far outside the space: its world box")
            && stray.why.contains("the terrain's")
            && stray.why.contains("± 2000 m"),
        "{stray:?}"
    );
    assert_eq!(scene.problems.len(), 1, "{:#?}", scene.problems);
    assert_eq!(
        scene.instances.len() + 1,
        load(clean.path()).instances.len()
    );
    for (index, chunk) in scene.chunks.iter().enumerate() {
        assert!(scene.instances[chunk.instances.clone()]
            .iter()
            .all(|i| i.chunk == index));
    }

    let before = snapshot(dir.path());
    let failed = bake_in_place(&settings);
    let stderr = text(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("00000000o.chunk <model[1]/transform>")
            && stderr.contains("far outside the space"),
        "{stderr}"
    );
    assert_eq!(snapshot(dir.path()), before, "nothing is written");

    let report = dir.path().join("report.json");
    let kept = run_bounded(
        &[
            "bake",
            settings.to_str().unwrap(),
            "--keep-going",
            "--report",
            report.to_str().unwrap(),
        ],
        Duration::from_secs(120),
    );
    assert!(kept.status.success(), "{}", text(&kept.stderr));
    let clean_report = clean.path().join("report.json");
    let output = run_bounded(
        &[
            "bake",
            clean_settings.to_str().unwrap(),
            "--dry-run",
            "--report",
            clean_report.to_str().unwrap(),
        ],
        Duration::from_secs(120),
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert_eq!(sun_rays(&report), sun_rays(&clean_report));
}

#[test]
fn a_tall_placement_within_the_height_margin_is_no_problem() {
    // A 300 m tower (the house scaled 60× in height) is real content.
    let dir = small_world();
    replace_text(
        dir.path(),
        CHUNK,
        "0.000000 1.000000 0.000000\t</row1>\n\t\t\t<row2>\t0.410424",
        "0 60 0\t</row1>\n\t\t\t<row2>\t0.410424",
    );
    let scene = load(dir.path());
    assert!(scene.problems.is_empty(), "{:#?}", scene.problems);
    let (_, max) = bake::geometry::world_bounds(&scene).unwrap();
    assert!(max.y > 250.0, "the tower reaches {} m", max.y);
}

// ---------------------------------------------------------------------------
// 4. Paths out of the res roots.

#[test]
fn terrain_resource_climbing_out_of_the_res_roots_is_refused() {
    let dir = small_world();
    let outside = tempfile::tempdir().unwrap();
    std::fs::copy(
        dir.path().join("spaces/small/00000000o.cdata"),
        outside.path().join("evil.cdata"),
    )
    .unwrap();
    let climb = format!(
        "{}{}/evil.cdata/terrain2",
        "../".repeat(12),
        outside.path().display().to_string().trim_start_matches('/')
    );
    replace_text(dir.path(), CHUNK, "00000000o.cdata/terrain2", &climb);
    // An absolute name is taken relative to the chunk's folder, where no
    // such file is: not found, never read from outside.
    let absolute = format!("{}/evil.cdata/terrain2", outside.path().display());
    replace_text(
        dir.path(),
        "spaces/small/0000ffffo.chunk",
        "0000ffffo.cdata/terrain2",
        &absolute,
    );
    let scene = load(dir.path());
    let climbed = problem(&scene, "00000000o.chunk <terrain>");
    assert!(
        climbed.why.contains("00000000o.chunk")
            && climbed.why.contains("climbs out of the chunk's folder"),
        "{climbed:?}"
    );
    let absolute = problem(&scene, "0000ffffo.chunk <terrain>");
    assert!(
        absolute.why.contains("spaces/small/evil.cdata"),
        "{absolute:?}"
    );
    assert_eq!(scene.terrain.len(), 2);
}

#[cfg(unix)]
#[test]
fn links_leading_out_of_the_res_roots_are_refused() {
    let dir = small_world();
    let outside = tempfile::tempdir().unwrap();
    for (from, to) in [
        ("spaces/small/ffffffffo.cdata", "evil.cdata"),
        ("sets/gen/props/crate.model", "crate.model"),
    ] {
        let inside = dir.path().join(from);
        std::fs::rename(&inside, outside.path().join(to)).unwrap();
        std::os::unix::fs::symlink(outside.path().join(to), &inside).unwrap();
    }
    let scene = load(dir.path());
    let terrain = problem(&scene, "ffffffffo.chunk <terrain>");
    assert!(
        terrain.why.contains("outside every res path"),
        "{terrain:?}"
    );
    let model = problem(&scene, "sets/gen/props/crate.model");
    assert!(model.why.contains("outside every res path"), "{model:?}");
    assert_eq!(scene.terrain.len(), 3);
}

// ---------------------------------------------------------------------------
// 5. Locked and linked chunks.

#[test]
fn read_only_chunks_are_refused_and_nothing_is_written() {
    // Perforce leaves files not checked out read-only (0444); the bake used
    // to replace them with writable files, even as a non-root user.
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    for chunk in ["00000000o.chunk", "ffffffffo.chunk"] {
        let path = dir.path().join(SPACE).join(chunk);
        let mut permissions = std::fs::metadata(&path).unwrap().permissions();
        permissions.set_readonly(true);
        std::fs::set_permissions(&path, permissions).unwrap();
    }
    let before = snapshot(dir.path());
    let output = bake_in_place(&settings);
    assert_eq!(output.status.code(), Some(1), "{}", text(&output.stderr));
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains("nothing was written: 2 file(s) cannot be replaced"),
        "{stderr}"
    );
    for chunk in ["00000000o.chunk", "ffffffffo.chunk"] {
        assert!(
            stderr.contains(&format!("{chunk}: is read-only (mode 0444)")),
            "{stderr}"
        );
    }
    assert_eq!(snapshot(dir.path()), before, "nothing is written");
}

#[test]
fn locked_chunks_are_named_before_tracing_and_refused_when_they_change() {
    // The refusal comes after the whole trace (hours on a big world), when
    // it is known which chunks change; the targets are checked right after
    // loading, and every locked one is named then.
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let locked = dir.path().join(SPACE).join("0000ffffo.chunk");
    let mut permissions = std::fs::metadata(&locked).unwrap().permissions();
    permissions.set_readonly(true);
    std::fs::set_permissions(&locked, permissions).unwrap();
    let before = snapshot(dir.path());
    let output = run_bounded(
        &["bake", settings.to_str().unwrap(), "--progress", "json"],
        Duration::from_secs(120),
    );
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("nothing was written: 1 file(s) cannot be replaced")
            && stderr.contains("0000ffffo.chunk: is read-only (mode 0444)"),
        "{stderr}"
    );
    // With --progress json the warning is an event among the progress.
    let events: Vec<serde_json::Value> = stderr
        .lines()
        .map(|l| serde_json::from_str(l).expect(l))
        .collect();
    let warning = events
        .iter()
        .position(|e| {
            e["event"] == "warning"
                && e["message"].as_str().is_some_and(|m| {
                    m.starts_with("1 chunk file(s) cannot be replaced")
                        && m.contains("0000ffffo.chunk: is read-only (mode 0444)")
                })
        })
        .expect(&stderr);
    let tracing = events
        .iter()
        .position(|e| e["event"] == "progress" && e["phase"] == "tracing")
        .expect(&stderr);
    assert!(warning < tracing, "named before tracing: {stderr}");
    assert_eq!(snapshot(dir.path()), before, "nothing is written");
    // Baked once writable, locked again: nothing changes, so nothing is
    // refused (a locked chunk the bake leaves alone is no problem).
    let mut permissions = std::fs::metadata(&locked).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    permissions.set_readonly(false);
    std::fs::set_permissions(&locked, permissions.clone()).unwrap();
    let output = run_bounded(
        &["bake", settings.to_str().unwrap(), "--quiet"],
        Duration::from_secs(120),
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    permissions.set_readonly(true);
    std::fs::set_permissions(&locked, permissions).unwrap();
    let output = run_bounded(
        &["bake", settings.to_str().unwrap(), "--quiet"],
        Duration::from_secs(120),
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
    // Writing elsewhere, or not at all, does not need the chunks writable.
    let output = run_bounded(
        &["bake", settings.to_str().unwrap(), "--dry-run", "--quiet"],
        Duration::from_secs(120),
    );
    assert!(output.status.success(), "{}", text(&output.stderr));
}

/// The effective user is root (who can chown and drop privileges).
#[cfg(unix)]
fn running_as_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| text(&o.stdout).trim() == "0")
}

#[cfg(unix)]
#[test]
fn a_non_root_user_cannot_replace_locked_or_foreign_chunks() {
    // As root, run the bake as `nobody` (uid 65534) on a world nobody owns,
    // with one chunk 0444 and one owned by root (0644: nobody cannot write
    // it). As a non-root user the test above already runs as non-root.
    let setpriv = Path::new("/usr/bin/setpriv");
    if !running_as_root() || !setpriv.exists() {
        crate::support::say_not_run("a_non_root_user_cannot_replace_locked_or_foreign_chunks needs root and setpriv (as non-root, read_only_chunks_are_refused_and_nothing_is_written covers it)");
        return;
    }
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let chown = |owner: &str, path: &Path, recursive: bool| {
        let mut command = Command::new("chown");
        if recursive {
            command.arg("-R");
        }
        assert!(command.arg(owner).arg(path).status().unwrap().success());
    };
    chown("65534:65534", dir.path(), true);
    let locked = dir.path().join(SPACE).join("00000000o.chunk");
    let mut permissions = std::fs::metadata(&locked).unwrap().permissions();
    permissions.set_readonly(true);
    std::fs::set_permissions(&locked, permissions).unwrap();
    chown(
        "0:0",
        &dir.path().join(SPACE).join("0000ffffo.chunk"),
        false,
    );

    let before = snapshot(dir.path());
    let output = run_command_bounded(
        Command::new(setpriv)
            .args([
                "--reuid=65534",
                "--regid=65534",
                "--clear-groups",
                env!("CARGO_BIN_EXE_shadowcull"),
                "bake",
            ])
            .arg(&settings),
        Duration::from_secs(120),
    );
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("00000000o.chunk: is read-only (mode 0444)")
            && stderr.contains("0000ffffo.chunk: cannot be written by this user (mode 0644"),
        "{stderr}"
    );
    assert!(stderr.contains("2 file(s) cannot be replaced"), "{stderr}");
    assert_eq!(snapshot(dir.path()), before, "nothing is written");
}

#[cfg(unix)]
#[test]
fn a_linked_chunk_is_written_through_and_modes_and_owners_are_kept() {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let reference = small_world();
    let reference_settings = coarse_settings(reference.path());
    let output = bake_in_place(&reference_settings);
    assert!(output.status.success(), "{}", text(&output.stderr));

    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let space = dir.path().join(SPACE);
    // 00000000o.chunk: a link to a file in another folder (a shared
    // checkout); ffffffffo.chunk: mode 0640; 0000ffffo.chunk (as root):
    // owned by uid/gid 12345.
    let store = tempfile::tempdir().unwrap();
    let target = store.path().join("00000000o.chunk");
    std::fs::rename(space.join("00000000o.chunk"), &target).unwrap();
    std::os::unix::fs::symlink(&target, space.join("00000000o.chunk")).unwrap();
    std::fs::set_permissions(
        space.join("ffffffffo.chunk"),
        std::fs::Permissions::from_mode(0o640),
    )
    .unwrap();
    let root = running_as_root();
    if root {
        std::os::unix::fs::chown(space.join("0000ffffo.chunk"), Some(12345), Some(12345)).unwrap();
    }
    let output = bake_in_place(&settings);
    assert!(output.status.success(), "{}", text(&output.stderr));

    let link = std::fs::symlink_metadata(space.join("00000000o.chunk")).unwrap();
    assert!(link.file_type().is_symlink(), "the link is still a link");
    let baked = |world: &Path, chunk: &str| std::fs::read(world.join(SPACE).join(chunk)).unwrap();
    assert_eq!(
        std::fs::read(&target).unwrap(),
        baked(reference.path(), "00000000o.chunk"),
        "the link's target holds the baked chunk"
    );
    for chunk in ["0000ffffo.chunk", "ffffffffo.chunk"] {
        assert_eq!(baked(dir.path(), chunk), baked(reference.path(), chunk));
    }
    let mode = std::fs::metadata(space.join("ffffffffo.chunk"))
        .unwrap()
        .permissions()
        .mode();
    assert_eq!(mode & 0o7777, 0o640);
    if root {
        let meta = std::fs::metadata(space.join("0000ffffo.chunk")).unwrap();
        assert_eq!((meta.uid(), meta.gid()), (12345, 12345));
    } else {
        crate::support::say_not_run("the owner part of a_linked_chunk_is_written_through_and_modes_and_owners_are_kept needs root");
    }
    assert!(temporaries(dir.path()).is_empty());
    assert!(temporaries(store.path()).is_empty());
}

// ---------------------------------------------------------------------------
// 6. Interrupted runs.

#[test]
fn a_rerun_removes_stale_temporaries_and_completes_an_interrupted_bake() {
    // What a kill during the renames leaves: some chunks baked, the others
    // as they were, and the temporary files of those others. A re-run
    // removes the temporaries and gives the same files as one whole bake.
    let whole = small_world();
    let output = bake_in_place(&coarse_settings(whole.path()));
    assert!(output.status.success(), "{}", text(&output.stderr));

    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let output = bake_in_place(&settings);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let generated = generate(Preset::Small, 1);
    // No process has this id (above Linux's pid_max, 2^22).
    let dead = 4_194_305;
    for chunk in ["ffff0000o.chunk", "ffffffffo.chunk"] {
        let relative = format!("{SPACE}/{chunk}");
        let path = dir.path().join(&relative);
        let baked = std::fs::read(&path).unwrap();
        let original = generated.file(&relative).unwrap();
        assert_ne!(baked, original, "the bake changes {chunk}");
        std::fs::write(&path, original).unwrap();
        let temp = dir
            .path()
            .join(SPACE)
            .join(format!(".{chunk}.shadowcull-{}-{dead}.tmp", host_name()));
        std::fs::write(temp, &baked[..baked.len() / 2]).unwrap();
    }
    assert_eq!(temporaries(dir.path()).len(), 2);

    let output = bake_in_place(&settings);
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(
        text(&output.stdout).contains("wrote 2 of 4 chunk files in place"),
        "{}",
        text(&output.stdout)
    );
    assert!(
        temporaries(dir.path()).is_empty(),
        "stale temporaries removed"
    );
    let chunks = |world: &Path| {
        snapshot(&world.join(SPACE))
            .into_iter()
            .map(|(path, (bytes, _))| (path.file_name().unwrap().to_owned(), bytes))
            .collect::<BTreeMap<_, _>>()
    };
    assert_eq!(chunks(dir.path()), chunks(whole.path()));
}

/// A temporary file named as host `host`'s process `pid` names it, last
/// written `age` ago.
fn temporary_of(folder: &Path, chunk: &str, host: &str, pid: u32, age: Duration) -> PathBuf {
    let path = folder.join(format!(".{chunk}.shadowcull-{host}-{pid}.tmp"));
    std::fs::write(&path, b"half a chunk").unwrap();
    let file = std::fs::File::options().write(true).open(&path).unwrap();
    file.set_modified(SystemTime::now() - age).unwrap();
    path
}

#[test]
fn a_rerun_that_changes_nothing_still_removes_stale_temporaries() {
    // The sweep covers every folder of the output, not only those a run
    // writes: a re-run finding every chunk baked ("wrote 0 of 4") still
    // removes them. And a temporary of another machine sharing the volume
    // is judged by its age, not by a process id this machine cannot look
    // up.
    let dir = small_world();
    let settings = coarse_settings(dir.path());
    let out = tempfile::tempdir().unwrap();
    let bake_out = || {
        run_bounded(
            &[
                "bake",
                settings.to_str().unwrap(),
                "--out",
                out.path().to_str().unwrap(),
            ],
            Duration::from_secs(120),
        )
    };
    for output in [bake_in_place(&settings), bake_out()] {
        assert!(output.status.success(), "{}", text(&output.stderr));
    }
    let old = STALE_TEMPORARY_AGE + Duration::from_secs(60);
    let mut stale = Vec::new();
    let mut live = Vec::new();
    for folder in [dir.path().join(SPACE), out.path().join(SPACE)] {
        // This host, no process has the id (above Linux's pid_max, 2^22).
        stale.push(temporary_of(
            &folder,
            "ffff0000o.chunk",
            host_name(),
            4_194_305,
            Duration::ZERO,
        ));
        stale.push(temporary_of(
            &folder,
            "ffffffffo.chunk",
            "elsewhere",
            1,
            old,
        ));
        live.push(temporary_of(
            &folder,
            "0000ffffo.chunk",
            "elsewhere",
            1,
            Duration::ZERO,
        ));
    }
    for output in [bake_in_place(&settings), bake_out()] {
        let stdout = text(&output.stdout);
        assert!(output.status.success(), "{}", text(&output.stderr));
        assert!(stdout.contains("wrote 0 of 4 chunk files"), "{stdout}");
    }
    for path in &stale {
        assert!(!path.exists(), "{} is stale", path.display());
    }
    for path in &live {
        assert!(
            path.exists(),
            "{} may be another machine's live bake",
            path.display()
        );
    }
    // --dry-run and --check write nothing, temporaries included.
    let kept = temporary_of(
        &dir.path().join(SPACE),
        "ffff0000o.chunk",
        host_name(),
        4_194_305,
        Duration::ZERO,
    );
    for flag in ["--dry-run", "--check"] {
        let output = run_bounded(
            &["bake", settings.to_str().unwrap(), flag, "--quiet"],
            Duration::from_secs(120),
        );
        assert!(output.status.success(), "{}", text(&output.stderr));
    }
    assert!(kept.exists());
}

// ---------------------------------------------------------------------------
// The library's write path, as `bake --out` uses it.

#[test]
fn bake_out_refuses_a_read_only_target_before_writing_any() {
    let dir = small_world();
    let out = tempfile::tempdir().unwrap();
    let scene = load(dir.path());
    let settings = read_bake_settings(&dir.path().join(SETTINGS_FILE)).unwrap();
    let mut config = BakeConfig::from_settings(&settings);
    config.lights.truncate(1);
    let mut result = bake::bake(&scene, &config, &Silent).unwrap();
    let res_paths = ResPaths::new(settings.res_paths);
    let outputs =
        output::chunk_outputs(&scene, &mut result, &res_paths, Some(out.path()), &Silent).unwrap();
    // An old output, locked.
    let locked = out.path().join(SPACE).join("ffffffffo.chunk");
    std::fs::create_dir_all(locked.parent().unwrap()).unwrap();
    std::fs::write(&locked, b"old").unwrap();
    let mut permissions = std::fs::metadata(&locked).unwrap().permissions();
    permissions.set_readonly(true);
    std::fs::set_permissions(&locked, permissions).unwrap();
    let message = output::write_outputs(&outputs, &Silent)
        .unwrap_err()
        .to_string();
    assert!(
        message.contains("ffffffffo.chunk: is read-only"),
        "{message}"
    );
    assert_eq!(
        snapshot(out.path()).len(),
        1,
        "only the locked file is there"
    );
}
