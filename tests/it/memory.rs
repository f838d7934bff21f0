//! The memory model (`bake::memory`) against a real bake: a generated
//! bench-density world baked by the binary, its peak resident set read from
//! the kernel (wait4), checked loosely against the model's prediction. A
//! bake that held ~350 bytes per *placed* triangle (flat triangle lists
//! instead of one bottom level per model) fails this by a factor of ten.
//! The camera view, which traces the same structure, stays within twice
//! the bake's peak on the same world.
//! `SHADOWCULL_SLOW=1` (set by CI) bakes a 16×16-chunk world instead of
//! 6×6.

use shadowcull::bake::memory::{peak_resident, WorldSize};
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::gen::{generate_each, WorldSize as GenSize, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig};
use std::process::{Command, Stdio};

/// Runs the binary and returns its exit status and peak resident bytes.
#[cfg(target_os = "linux")]
#[allow(clippy::zombie_processes)] // reaped by wait4, which std cannot see
fn run_measured(args: &[&str]) -> (i32, u64) {
    let child = Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("run shadowcull");
    let mut status = 0;
    // SAFETY: rusage is plain data; wait4 reaps exactly this child, which
    // std has not waited for.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let pid = unsafe { libc::wait4(child.id() as libc::pid_t, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as libc::pid_t, "wait4 failed");
    (libc::WEXITSTATUS(status), usage.ru_maxrss as u64 * 1024)
}

#[cfg(target_os = "linux")]
#[test]
fn peak_memory_follows_the_memory_model_not_placed_triangles() {
    let chunks = if std::env::var_os("SHADOWCULL_SLOW").is_some() {
        16
    } else {
        6
    };
    let dir = tempfile::tempdir().unwrap();
    generate_each(GenSize::BenchChunks(chunks), 1, |path, bytes| {
        write_tree(dir.path(), &[(path.to_string(), bytes)])
    })
    .unwrap();
    let settings_path = dir.path().join(SETTINGS_FILE);
    let settings = shadowcull::files::read_bake_settings(&settings_path).unwrap();
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
        speedtrees: settings.speedtrees.clone(),
    })
    .unwrap();
    let size = WorldSize::of(&scene);
    let placed_triangles: u64 = scene
        .instances
        .iter()
        .flat_map(|i| i.parts.iter().flatten())
        .map(|&m| scene.models[m].triangles.len() as u64)
        .sum();
    drop(scene);

    let (status, peak) = run_measured(&[
        "bake",
        settings_path.to_str().unwrap(),
        "--dry-run",
        "--threads",
        "2",
    ]);
    assert_eq!(status, 0);
    let predicted = peak_resident(&size, 2);
    eprintln!(
        "{chunks}×{chunks} chunks: peak RSS {:.1} MB, model {:.1} MB, {placed_triangles} placed triangles",
        peak as f64 / 1e6,
        predicted as f64 / 1e6
    );
    // Loose: a debug build and another allocator state move the peak
    // away from the model.
    assert!(
        peak <= predicted * 3 / 2,
        "peak RSS {peak} above 1.5 × the model's {predicted}: {size:?}"
    );
    // The test can tell the two apart: per placed triangle the flat
    // lists' bound alone is over ten times this.
    assert!(
        placed_triangles * 350 > 10 * predicted,
        "{placed_triangles}"
    );
}

#[cfg(target_os = "linux")]
#[test]
fn the_camera_view_needs_about_what_the_bake_needs() {
    // The camera traces the bake's own bottom levels under one top level
    // over every placement: its peak is the bake's and a top-level entry a
    // placement, plus the picture. A view over a flat list of the placed
    // triangles and terrain cells needs tens of times the bake's peak
    // here.
    let dir = tempfile::tempdir().unwrap();
    generate_each(GenSize::BenchChunks(6), 1, |path, bytes| {
        write_tree(dir.path(), &[(path.to_string(), bytes)])
    })
    .unwrap();
    let settings = dir.path().join(SETTINGS_FILE);
    let settings = settings.to_str().unwrap();
    let (status, bake_peak) = run_measured(&["bake", settings, "--dry-run", "--threads", "2"]);
    assert_eq!(status, 0);
    let picture = dir.path().join("camera.png");
    let (status, camera_peak) = run_measured(&[
        "render",
        settings,
        "--light",
        "sun",
        "--view",
        "camera",
        "--size",
        "320x240",
        "--threads",
        "2",
        "-o",
        picture.to_str().unwrap(),
    ]);
    assert_eq!(status, 0);
    eprintln!(
        "peak RSS: bake {:.1} MB, camera view {:.1} MB",
        bake_peak as f64 / 1e6,
        camera_peak as f64 / 1e6
    );
    assert!(
        camera_peak <= 2 * bake_peak,
        "camera view {camera_peak} bytes, bake {bake_peak}"
    );
}

#[cfg(target_os = "linux")]
#[test]
fn running_out_of_memory_names_the_phase_and_exits_1() {
    // A world that needs far more than the address space it is given: the
    // allocation fails in some phase of loading or building, and the bake
    // must say which and exit 1, not abort (134) with Rust's bare
    // "memory allocation of N bytes failed".
    let dir = tempfile::tempdir().unwrap();
    generate_each(GenSize::BenchChunks(16), 1, |path, bytes| {
        write_tree(dir.path(), &[(path.to_string(), bytes)])
    })
    .unwrap();
    let settings = dir.path().join(SETTINGS_FILE);
    let named = shadowcull::progress::Phase::ALL.map(|p| p.name());
    let names_a_phase = |text: &str| {
        named
            .iter()
            .any(|p| text.contains(&format!("out of memory in phase `{p}`: could not allocate")))
    };
    let stderr = bake_in_48_mib(&settings, &[]);
    // A phase the bake names (loading's `chunks` here: the limit leaves
    // little beyond the program and its threads), not `starting`: before
    // the first phase the bake holds only its arguments and settings.
    assert!(
        stderr
            .lines()
            .any(|l| l.starts_with("error: ") && names_a_phase(l)),
        "{stderr}"
    );
    // With --progress json the last word is an `error` event too.
    let stderr = bake_in_48_mib(&settings, &["--progress", "json"]);
    let last: serde_json::Value =
        serde_json::from_str(stderr.lines().last().unwrap_or_default()).expect(&stderr);
    assert_eq!(last["event"], "error", "{stderr}");
    assert!(names_a_phase(last["message"].as_str().unwrap()), "{stderr}");
    // Nothing was written in place.
    let changed = std::fs::read_dir(dir.path().join("spaces"))
        .unwrap()
        .flatten()
        .flat_map(|space| std::fs::read_dir(space.path()).unwrap().flatten())
        .filter(|f| f.file_name().to_string_lossy().contains("shadowcull"))
        .count();
    assert_eq!(changed, 0, "temporary files left behind");
}

/// Bakes `settings` in place with 48 MiB of address space; expects exit 1
/// and no panic, and returns standard error.
#[cfg(target_os = "linux")]
fn bake_in_48_mib(settings: &std::path::Path, extra: &[&str]) -> String {
    use std::os::unix::process::CommandExt;
    let mut command = Command::new(env!("CARGO_BIN_EXE_shadowcull"));
    command.args(["bake", settings.to_str().unwrap(), "--threads", "1"]);
    command.args(extra);
    // SAFETY: setrlimit is async-signal-safe; it only limits the child.
    unsafe {
        command.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: 48 << 20,
                rlim_max: 48 << 20,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let out = command.output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    stderr
}
