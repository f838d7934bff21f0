//! Mutation fuzzing kept as a test: damaged copies of generated
//! worlds and, with `$SHADOWCULL_REALDATA`, of real BigWorld models, terrain
//! and the arctic chunks are loaded, inspected and baked in-process into an
//! `--out` folder. Each case must finish (no panic, no hang past
//! [`CASE_LIMIT`]) and leave every input file as it was (bytes and
//! modification time): nothing is written outside the output folder.
//!
//! `SHADOWCULL_FUZZ_CASES=N` runs N cases instead of [`DEFAULT_CASES`];
//! `SHADOWCULL_FUZZ_SEED=S` changes the stream.

use crate::support::realdata;
use glam::DVec3;
use shadowcull::bake::{self, output, BakeConfig, Silent};
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::formats::bake_settings::{FaceCulling, LightKind, LightSettings, SpeedTreeProxies};
use shadowcull::gen::{generate, Preset};
use shadowcull::rng::Rng;
use shadowcull::scene::{load_scene, LoadConfig};
use std::collections::BTreeMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime};
use tempfile::TempDir;

const DEFAULT_CASES: usize = 300;
const DEFAULT_SEED: u64 = 16;
/// A case that runs longer hangs (a case takes milliseconds).
const CASE_LIMIT: Duration = Duration::from_secs(60);
const MUTABLE: [&str; 5] = [".chunk", ".model", ".visual", ".primitives", ".cdata"];

/// One world on disk whose files the cases damage, one at a time.
struct Corpus {
    name: &'static str,
    input: TempDir,
    res_roots: Vec<PathBuf>,
    space: String,
    /// The settings' speedtree proxies (the forest's; none elsewhere).
    speedtrees: SpeedTreeProxies,
    /// The files a case may damage.
    targets: Vec<PathBuf>,
    out: TempDir,
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_tree(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).unwrap();
        }
    }
}

fn files_under(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let entry = entry.unwrap();
        if entry.file_type().unwrap().is_dir() {
            files_under(&entry.path(), out);
        } else {
            out.push(entry.path());
        }
    }
}

fn mutable_files(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    files_under(dir, &mut files);
    files.retain(|p| {
        let name = p.to_string_lossy();
        MUTABLE.iter().any(|suffix| name.ends_with(suffix))
    });
    files.sort();
    files
}

fn corpus(name: &'static str, input: TempDir, res_roots: Vec<PathBuf>, space: &str) -> Corpus {
    let targets = mutable_files(input.path());
    assert!(!targets.is_empty(), "{name}: nothing to damage");
    Corpus {
        name,
        input,
        res_roots,
        space: space.into(),
        speedtrees: SpeedTreeProxies::default(),
        targets,
        out: tempfile::tempdir().unwrap(),
    }
}

fn corpora() -> Vec<Corpus> {
    let generated = tempfile::tempdir().unwrap();
    write_tree(generated.path(), &generate(Preset::Small, 1).files).unwrap();
    let root = generated.path().to_path_buf();
    let mut corpora = vec![corpus(
        "generated small",
        generated,
        vec![root],
        "spaces/small",
    )];
    // Speedtrees with their proxies, every item kind, packed chunks.
    let forest = tempfile::tempdir().unwrap();
    let world = generate(Preset::Forest, 1);
    write_tree(forest.path(), &world.files).unwrap();
    let settings = shadowcull::files::read_bake_settings(&forest.path().join("bake.xml")).unwrap();
    let root = forest.path().to_path_buf();
    let mut forest = corpus("generated forest", forest, vec![root], "spaces/forest");
    forest.speedtrees = settings.speedtrees;
    corpora.push(forest);

    let Some(data) = realdata("fuzzing_real_files (the generated world is fuzzed regardless)")
    else {
        return corpora;
    };
    // Every real model in a row over a slab, on the engine's blank terrain.
    let real = tempfile::tempdir().unwrap();
    let res = real.path().join("res");
    let world = real.path().join("world");
    copy_tree(&data.join("bigworld-14.4.1/res"), &res);
    let models = crate::real_scene::real_model_names(&res);
    let mut files = crate::real_scene::world_placing(&models);
    let chunk = String::from_utf8(files[0].1.clone()).unwrap();
    let extra = "\t<model>\n\t\t<resource>\thelpers/models/unit_cube.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t90 0 0\t</row0>\n\t\t\t<row1>\t0 0.1 0\t</row1>\n\t\t\t<row2>\t0 0 20\t</row2>\n\t\t\t<row3>\t-5 -0.1 40\t</row3>\n\t\t</transform>\n\t</model>\n\t<terrain>\n\t\t<resource>\t00000000o.cdata/terrain2\t</resource>\n\t</terrain>\n</root>\n";
    files[0].1 = chunk.replace("</root>\n", extra).into_bytes();
    files.push((
        "spaces/real/00000000o.cdata".into(),
        std::fs::read(res.join("terrain/blank.cdata")).unwrap(),
    ));
    write_tree(&world, &files).unwrap();
    corpora.push(corpus("real models", real, vec![world, res], "spaces/real"));

    // The real arctic chunks (their models' binaries were not collected).
    let arctic = tempfile::tempdir().unwrap();
    let res = arctic.path().join("res");
    copy_tree(&data.join("fantasydemo-arctic/res"), &res);
    corpora.push(corpus("arctic", arctic, vec![res], "spaces/arctic"));
    corpora
}

/// Cheap lights: the cases are about input, not rays.
fn config() -> BakeConfig {
    let light = |name: &str, kind| LightSettings {
        name: name.into(),
        kind,
    };
    BakeConfig {
        face_culling: FaceCulling::Back,
        lights: vec![
            light(
                "sun",
                LightKind::Directional {
                    direction: DVec3::new(-0.3, -1.0, 0.2).normalize(),
                    texel_size: 2.0,
                },
            ),
            light(
                "spot",
                LightKind::Spot {
                    position: DVec3::new(10.0, 20.0, 10.0),
                    direction: DVec3::new(0.1, -1.0, 0.06).normalize(),
                    fov_degrees: 60.0,
                    near: 0.1,
                    far: 80.0,
                    resolution: 32,
                },
            ),
            light(
                "point",
                LightKind::Point {
                    position: DVec3::new(-12.0, 8.0, -5.0),
                    near: 0.1,
                    far: 30.0,
                    resolution: 16,
                },
            ),
        ],
        ..BakeConfig::default()
    }
}

/// Damages `bytes`: a truncation, bit flips (half of them in the first 64
/// bytes, where headers are) or a splice of `donor`'s bytes (overwritten or
/// inserted). Returns the new bytes and what was done.
fn mutate(rng: &mut Rng, bytes: &[u8], donor: &[u8]) -> (Vec<u8>, String) {
    let mut out = bytes.to_vec();
    let len = out.len();
    match rng.below(3) {
        0 => {
            let at = rng.below(len + 1);
            out.truncate(at);
            (out, format!("truncated to {at} bytes"))
        }
        1 if len > 0 => {
            let flips = 1 + rng.below(8);
            let mut at = Vec::new();
            for _ in 0..flips {
                let offset = if rng.chance(0.5) {
                    rng.below(len.min(64))
                } else {
                    rng.below(len)
                };
                let bit = rng.below(8);
                out[offset] ^= 1 << bit;
                at.push(format!("{offset}.{bit}"));
            }
            (out, format!("bits flipped at {}", at.join(", ")))
        }
        _ => {
            let start = rng.below(donor.len() + 1);
            let take = rng.below(4096).min(donor.len() - start);
            let piece = &donor[start..start + take];
            let at = rng.below(len + 1);
            if rng.chance(0.5) {
                out.splice(at..at, piece.iter().copied());
                (out, format!("{take} bytes inserted at {at}"))
            } else {
                let end = (at + take).min(len);
                out.splice(at..end, piece.iter().copied());
                (out, format!("{take} bytes written over {at}"))
            }
        }
    }
}

/// Every file under `dir`: bytes and modification time.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, (Vec<u8>, Option<SystemTime>)> {
    let mut files = Vec::new();
    files_under(dir, &mut files);
    files
        .into_iter()
        .map(|path| {
            let modified = std::fs::metadata(&path).unwrap().modified().ok();
            let bytes = std::fs::read(&path).unwrap();
            (path, (bytes, modified))
        })
        .collect()
}

fn panic_message(payload: Box<dyn std::any::Any + Send>) -> String {
    payload
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "a panic".into())
}

/// How far a case got: 0 the world did not load, 1 loaded, 2 baked,
/// 3 chunks written.
type Stage = usize;
const STAGES: [&str; 4] = ["did not load", "loaded only", "baked only", "written"];

/// Load, inspect, bake and write into the corpus's output folder, on a
/// thread: how far it got, or `Err` on a panic or when it runs past `limit`.
fn run_case(corpus: &Corpus, config: &BakeConfig, limit: Duration) -> Result<Stage, String> {
    let res_paths = ResPaths::new(corpus.res_roots.clone());
    let space = corpus.space.clone();
    let speedtrees = corpus.speedtrees.clone();
    let out = corpus.out.path().to_path_buf();
    let config = config.clone();
    let (sender, receiver) = mpsc::channel();
    std::thread::spawn(move || {
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            let Ok(scene) = load_scene(&LoadConfig {
                res_paths: res_paths.clone(),
                space,
                speedtrees,
            }) else {
                return 0;
            };
            let _ = shadowcull::inspect::inspect(&scene, Default::default()).to_text();
            let Ok(mut result) = bake::bake(&scene, &config, &Silent) else {
                return 1;
            };
            let _ = output::report(&scene, &result);
            match output::chunk_outputs(&scene, &mut result, &res_paths, Some(&out), &Silent) {
                Ok(outputs) if output::write_outputs(&outputs, &Silent).is_ok() => 3,
                _ => 2,
            }
        }));
        let _ = sender.send(outcome.map_err(panic_message));
    });
    match receiver.recv_timeout(limit) {
        Ok(outcome) => outcome,
        Err(_) => Err(format!("still running after {limit:?}: a hang")),
    }
}

fn env_number(name: &str) -> Option<u64> {
    std::env::var(name).ok().map(|v| {
        v.trim()
            .parse()
            .unwrap_or_else(|_| panic!("{name}={v} is not a number"))
    })
}

#[test]
fn damaged_worlds_never_panic_hang_or_write_outside_the_output_folder() {
    let cases = env_number("SHADOWCULL_FUZZ_CASES").map_or(DEFAULT_CASES, |n| n as usize);
    let seed = env_number("SHADOWCULL_FUZZ_SEED").unwrap_or(DEFAULT_SEED);
    let corpora = corpora();
    let config = config();
    // The undamaged worlds run clean first.
    for corpus in &corpora {
        run_case(corpus, &config, CASE_LIMIT).unwrap();
    }
    let started = Instant::now();
    let mut rng = Rng::new(seed);
    let mut failures = Vec::new();
    let mut per_corpus = vec![0usize; corpora.len()];
    let mut stages = [0usize; STAGES.len()];
    for case in 0..cases {
        let which = rng.below(corpora.len());
        per_corpus[which] += 1;
        let corpus = &corpora[which];
        let target = &corpus.targets[rng.below(corpus.targets.len())];
        let donor = &corpus.targets[rng.below(corpus.targets.len())];
        let original = std::fs::read(target).unwrap();
        let donor_bytes = std::fs::read(donor).unwrap();
        let (damaged, how) = mutate(&mut rng, &original, &donor_bytes);
        std::fs::write(target, &damaged).unwrap();
        let what = format!(
            "case {case} (seed {seed}), {}: {} {how}",
            corpus.name,
            target.strip_prefix(corpus.input.path()).unwrap().display()
        );
        let before = snapshot(corpus.input.path());
        let outcome = run_case(corpus, &config, CASE_LIMIT);
        let after = snapshot(corpus.input.path());
        std::fs::write(target, &original).unwrap();
        match &outcome {
            Ok(stage) => stages[*stage] += 1,
            Err(err) if err.contains("a hang") => panic!("{what}: {err}"),
            Err(err) => failures.push(format!("{what}: panicked: {err}")),
        }
        if before != after {
            let changed: Vec<_> = before
                .keys()
                .chain(after.keys())
                .filter(|p| before.get(*p) != after.get(*p))
                .map(|p| p.display().to_string())
                .collect();
            failures.push(format!("{what}: input files changed: {changed:?}"));
        }
    }
    eprintln!(
        "fuzz: {cases} cases ({}; {}) in {:.1} s, seed {seed}",
        corpora
            .iter()
            .zip(&per_corpus)
            .map(|(c, n)| format!("{n} {}", c.name))
            .collect::<Vec<_>>()
            .join(", "),
        STAGES
            .iter()
            .zip(&stages)
            .map(|(s, n)| format!("{n} {s}"))
            .collect::<Vec<_>>()
            .join(", "),
        started.elapsed().as_secs_f64()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
