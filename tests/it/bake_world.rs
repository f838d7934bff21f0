//! Whole bakes: the BVH path against the brute-force oracle on seeded random
//! worlds, thread-count determinism, idempotent re-bakes, the report and the
//! command line.

use crate::generated::{fixture_dir, load_world};
use crate::micro::*;
use glam::{DMat4, DQuat, DVec3, Vec3};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::files::write_tree;
use shadowcull::formats::bake_settings::{FaceCulling, LightKind, LightSettings};
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use shadowcull::rng::Rng;
use std::path::Path;
use std::process::Command;

pub fn random_light(rng: &mut Rng, centre: DVec3) -> LightSettings {
    let direction = loop {
        let d = DVec3::new(
            rng.range(-1.0, 1.0),
            rng.range(-1.0, -0.1),
            rng.range(-1.0, 1.0),
        );
        if d.length() > 0.1 {
            break d.normalize();
        }
    };
    let kind = match rng.below(3) {
        0 => LightKind::Directional {
            direction,
            texel_size: rng.range(0.2, 0.5),
        },
        1 => LightKind::Spot {
            position: centre - direction * rng.range(8.0, 20.0),
            direction,
            fov_degrees: rng.range(30.0, 120.0),
            near: 0.1,
            far: 60.0,
            resolution: 40,
        },
        _ => LightKind::Point {
            position: centre
                + DVec3::new(
                    rng.range(-4.0, 4.0),
                    rng.range(3.0, 8.0),
                    rng.range(-4.0, 4.0),
                ),
            near: 0.1,
            far: rng.range(10.0, 40.0),
            resolution: 20,
        },
    };
    LightSettings {
        name: format!("random{}", rng.below(1000)),
        kind,
    }
}

/// A random 2×2-chunk world: hilly terrain on some chunks, boxes and cards
/// with random flags, rotations, scales and mirrors, some receiver-only,
/// some sunk, some two-part.
pub fn random_world(seed: u64) -> World {
    let mut rng = Rng::new(seed);
    let mut world = World::new(2, 2);
    for grid in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        if rng.below(4) != 0 {
            let (a, b, c) = (
                rng.range(0.5, 3.0),
                rng.range(0.2, 0.6),
                rng.range(0.2, 0.6),
            );
            world.terrain(grid, move |x, z| a * (b * x).sin() * (c * z).cos());
        }
    }
    let mut models = Vec::new();
    for _ in 0..6 {
        let size = Vec3::new(
            rng.range(0.5, 3.0) as f32,
            rng.range(0.5, 3.0) as f32,
            rng.range(0.5, 3.0) as f32,
        );
        let flags = Flags {
            alpha_tested: rng.below(4) == 0,
            double_sided: rng.below(3) == 0,
        };
        let mesh = if rng.below(3) == 0 {
            Mesh {
                groups: vec![(quad_up(-size.x, -size.z, size.x, size.z, 0.0), flags)],
            }
        } else {
            Mesh {
                groups: vec![
                    (cube(-size, size), flags),
                    (
                        quad_up(-size.x, -size.z, size.x, size.z, size.y + 0.5),
                        OPAQUE,
                    ),
                ],
            }
        };
        models.push(world.model(mesh));
    }
    for _ in 0..14 {
        let grid = (rng.below(2) as i32, rng.below(2) as i32);
        let rotation = DQuat::from_euler(
            glam::EulerRot::YXZ,
            rng.range(0.0, 6.3),
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
        );
        let mut scale = DVec3::new(
            rng.range(0.5, 2.0),
            rng.range(0.5, 2.0),
            rng.range(0.5, 2.0),
        );
        if rng.below(4) == 0 {
            scale.x = -scale.x;
        }
        let position = DVec3::new(
            rng.range(1.0, CHUNK - 1.0),
            rng.range(-2.0, 6.0),
            rng.range(1.0, CHUNK - 1.0),
        );
        let local = DMat4::from_scale_rotation_translation(scale, rotation, position);
        let mut parts = vec![models[rng.below(models.len())]];
        if rng.below(5) == 0 {
            parts.push(models[rng.below(models.len())]);
        }
        world.place(grid, &parts, local, rng.below(6) != 0);
    }
    world
}

#[test]
fn bvh_equals_brute_force_on_seeded_random_worlds() {
    for seed in 0..12 {
        let world = random_world(seed);
        let mut rng = Rng::new(1000 + seed);
        let centre = DVec3::new(CHUNK, 0.0, CHUNK);
        let lights = (0..3).map(|_| random_light(&mut rng, centre)).collect();
        let mut settings = config(lights);
        settings.face_culling =
            [FaceCulling::Back, FaceCulling::Front, FaceCulling::None][seed as usize % 3];
        // `run` bakes with the BVH and with brute force and asserts equality.
        let result = run(&world, &settings);
        assert!(
            result.masks.iter().any(|m| *m != 0),
            "seed {seed}: nothing useful at all"
        );
    }
}

#[test]
fn bvh_equals_brute_force_on_a_generated_world() {
    let world = generate(Preset::Small, 4);
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &world.files).unwrap();
    let scene = load_world(&dir.path().join(SETTINGS_FILE));
    let settings = shadowcull::files::read_bake_settings(&dir.path().join(SETTINGS_FILE)).unwrap();
    // Coarser grids than the file's, so the oracle stays quick.
    let lights = settings
        .lights
        .iter()
        .map(|l| {
            let mut l = l.clone();
            match &mut l.kind {
                LightKind::Directional { texel_size, .. } => *texel_size *= 4.0,
                LightKind::Spot { resolution, .. } | LightKind::Point { resolution, .. } => {
                    *resolution = 48
                }
            }
            l
        })
        .collect();
    let config = BakeConfig {
        lights,
        ..BakeConfig::from_settings(&settings)
    };
    let fast = bake::bake(&scene, &config, &Silent).unwrap();
    let oracle = bake::bake(
        &scene,
        &BakeConfig {
            brute_force: true,
            ..config
        },
        &Silent,
    )
    .unwrap();
    assert_eq!(fast.masks, oracle.masks);
    assert!(fast.masks.iter().filter(|m| **m != 0).count() > 5);
}

/// A random 2×2-chunk world of stacks of coincident placements (one model
/// list placed 2 to 40 times at one transform, each copy casting or
/// receiver-only at random) of opaque, double-sided, alpha-tested and
/// two-group models, rotated, scaled and mirrored, among single
/// placements and hilly terrain: most rays through a stack tie its copies.
fn stacked_world(seed: u64) -> World {
    let mut rng = Rng::new(seed);
    let mut world = World::new(2, 2);
    for grid in [(0, 0), (1, 1)] {
        world.terrain(grid, |x, z| 0.8 * (0.4 * x).sin() * (0.3 * z).cos());
    }
    let flags = [
        OPAQUE,
        TWO_SIDED,
        CANOPY,
        Flags {
            alpha_tested: true,
            double_sided: false,
        },
    ];
    let models: Vec<usize> = (0..5)
        .map(|k| {
            let size = Vec3::new(
                rng.range(0.5, 2.5) as f32,
                rng.range(0.5, 2.5) as f32,
                rng.range(0.5, 2.5) as f32,
            );
            let card = quad_up(-size.x, -size.z, size.x, size.z, size.y + 0.5);
            let groups = match k {
                0 => vec![(card, flags[rng.below(4)])],
                1 => vec![(cube(-size, size), OPAQUE), (card, flags[rng.below(4)])],
                _ => vec![(cube(-size, size), flags[rng.below(4)])],
            };
            world.model(Mesh { groups })
        })
        .collect();
    for k in 0..12 {
        let grid = (rng.below(2) as i32, rng.below(2) as i32);
        let rotation = DQuat::from_euler(
            glam::EulerRot::YXZ,
            rng.range(0.0, 6.3),
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
        );
        let mut scale = DVec3::splat(rng.range(0.6, 1.8));
        if rng.below(3) == 0 {
            scale.x = -scale.x;
        }
        let position = DVec3::new(
            rng.range(1.0, CHUNK - 1.0),
            rng.range(0.0, 5.0),
            rng.range(1.0, CHUNK - 1.0),
        );
        let local = DMat4::from_scale_rotation_translation(scale, rotation, position);
        let mut parts = vec![models[rng.below(models.len())]];
        if rng.below(4) == 0 {
            parts.push(models[rng.below(models.len())]);
        }
        let copies = match k % 3 {
            0 => 1,
            1 => 2 + rng.below(4),
            _ => 40,
        };
        for _ in 0..copies {
            world.place(grid, &parts, local, rng.below(4) != 0);
        }
    }
    world
}

#[test]
fn bvh_equals_brute_force_on_stacks_of_coincident_copies() {
    // A light of each kind a seed, and a sun whose texels lie closer than
    // a packet's spacing (traced as packets) and one whose lie farther
    // (ray by ray), over the culling modes.
    let mut useful = 0;
    for seed in 0..6 {
        let world = stacked_world(seed);
        let mut rng = Rng::new(2000 + seed);
        let centre = DVec3::new(CHUNK, 0.0, CHUNK);
        let mut lights: Vec<LightSettings> = Vec::new();
        while lights.len() < 3 {
            let light = random_light(&mut rng, centre);
            let kind = |l: &LightSettings| std::mem::discriminant(&l.kind);
            if !lights.iter().any(|l| kind(l) == kind(&light)) {
                lights.push(light);
            }
        }
        for light in &mut lights {
            if let LightKind::Directional { texel_size, .. } = &mut light.kind {
                *texel_size = [0.3, 0.7][seed as usize % 2];
            }
        }
        let mut settings = config(lights);
        settings.face_culling =
            [FaceCulling::Back, FaceCulling::Front, FaceCulling::None][seed as usize % 3];
        // `run` bakes with the BVH and with brute force and asserts equality.
        let result = run(&world, &settings);
        useful += result.masks.iter().filter(|m| **m != 0).count();
    }
    assert!(useful > 100, "{useful}");
}

#[test]
fn masks_are_the_same_for_any_thread_count() {
    let world = random_world(99);
    let mut rng = Rng::new(5);
    let lights: Vec<_> = (0..4)
        .map(|_| random_light(&mut rng, DVec3::new(CHUNK, 0.0, CHUNK)))
        .collect();
    let settings = config(lights);
    let masks: Vec<Vec<u32>> = [1, 2, 3, 5]
        .into_iter()
        .map(|threads| {
            on_threads(threads, || {
                bake::bake(&world.scene, &settings, &Silent).unwrap().masks
            })
        })
        .collect();
    for other in &masks[1..] {
        assert_eq!(&masks[0], other);
    }
}

/// `work` on a pool of `threads` threads.
fn on_threads<T: Send>(threads: usize, work: impl FnOnce() -> T + Send) -> T {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(work)
}

/// Refinement shares a light's casters, and a large caster's outline
/// cells, out between threads (`bake::refine`): what it proves and every
/// ray it counts must not depend on how many there are.
#[test]
fn refinement_is_the_same_for_any_thread_count() {
    for seed in [99, 7] {
        let world = random_world(seed);
        let mut rng = Rng::new(seed + 1);
        let lights: Vec<_> = (0..4)
            .map(|_| random_light(&mut rng, DVec3::new(CHUNK, 0.0, CHUNK)))
            .collect();
        let mut settings = config(lights);
        settings.refine_density = 8;
        settings.refine_samples = 16;
        let answers: Vec<(Vec<u32>, Vec<u64>)> = [1, 2, 3, 5]
            .into_iter()
            .map(|threads| {
                let result = on_threads(threads, || {
                    bake::bake(&world.scene, &settings, &Silent).unwrap()
                });
                let rays = result.lights.iter().map(|l| l.refine_rays).collect();
                (result.masks, rays)
            })
            .collect();
        assert!(
            answers[0].1.iter().any(|&rays| rays > 0),
            "seed {seed}: refinement ran"
        );
        for other in &answers[1..] {
            assert_eq!(&answers[0], other, "seed {seed}");
        }
    }
}

fn shadowcull(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn copy_fixture(preset: Preset, to: &Path) {
    write_tree(to, &generate(preset, crate::generated::FIXTURE_SEED).files).unwrap();
}

fn snapshot(dir: &Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    shadowcull::files::find_files(dir, ".chunk")
        .unwrap()
        .into_iter()
        .map(|p| {
            let bytes = std::fs::read(&p).unwrap();
            (p, bytes)
        })
        .collect()
}

#[test]
fn bake_in_place_is_idempotent_and_deterministic_across_threads() {
    let dir = tempfile::tempdir().unwrap();
    copy_fixture(Preset::Village, dir.path());
    let settings = dir.path().join(SETTINGS_FILE);
    let settings = settings.to_str().unwrap();
    let before = snapshot(dir.path());

    let dry = shadowcull(&["bake", settings, "--dry-run"]);
    assert!(
        dry.status.success(),
        "{}",
        String::from_utf8_lossy(&dry.stderr)
    );
    assert_eq!(snapshot(dir.path()), before, "--dry-run wrote nothing");
    assert!(String::from_utf8_lossy(&dry.stdout).contains("would change 9 of 9"));

    let first = shadowcull(&["bake", settings, "--threads", "1"]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let baked = snapshot(dir.path());
    assert_ne!(baked, before);
    let second = shadowcull(&["bake", settings, "--threads", "2"]);
    assert!(second.status.success());
    assert!(String::from_utf8_lossy(&second.stdout).contains("wrote 0 of 9"));
    assert_eq!(
        snapshot(dir.path()),
        baked,
        "a second bake leaves every file byte-identical"
    );

    // --out from the pristine fixture with another thread count gives the
    // same bytes as the in-place bake.
    let out = tempfile::tempdir().unwrap();
    let fixture = fixture_dir(Preset::Village).join(SETTINGS_FILE);
    let to_out = shadowcull(&[
        "bake",
        fixture.to_str().unwrap(),
        "--out",
        out.path().to_str().unwrap(),
        "--threads",
        "3",
        "--no-cache",
    ]);
    assert!(
        to_out.status.success(),
        "{}",
        String::from_utf8_lossy(&to_out.stderr)
    );
    for (path, bytes) in &baked {
        let relative = path.strip_prefix(dir.path()).unwrap();
        assert_eq!(
            &std::fs::read(out.path().join(relative)).unwrap(),
            bytes,
            "{}",
            relative.display()
        );
    }
}

#[test]
fn report_follows_the_schema() {
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("report.json");
    let fixture = fixture_dir(Preset::Small).join(SETTINGS_FILE);
    let out = shadowcull(&[
        "bake",
        fixture.to_str().unwrap(),
        "--dry-run",
        "--report",
        report.to_str().unwrap(),
        "--no-cache",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let value: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let lights = value["lights"].as_array().unwrap();
    assert_eq!(lights.len(), 3);
    for (i, light) in lights.iter().enumerate() {
        assert_eq!(light["index"], i);
        for field in ["rays", "useful_casters", "culled_casters"] {
            assert!(light[field].is_u64(), "{field}");
        }
        assert!(
            light["seconds"].is_f64() && light["name"].is_string() && light["kind"].is_string()
        );
    }
    let casters = value["casters"].as_array().unwrap();
    let keys: Vec<(String, String, u64)> = casters
        .iter()
        .map(|c| {
            (
                c["chunk"].as_str().unwrap().to_string(),
                c["kind"].as_str().unwrap().to_string(),
                c["index"].as_u64().unwrap_or(0),
            )
        })
        .collect();
    let mut sorted = keys.clone();
    sorted.sort();
    assert_eq!(keys, sorted, "casters sorted by chunk, kind, index");
    let expected = generate(Preset::Small, crate::generated::FIXTURE_SEED).expected;
    let models = casters.iter().filter(|c| c["kind"] == "model").count() as u64;
    let terrain = casters.iter().filter(|c| c["kind"] == "terrain").count() as u64;
    assert_eq!(
        (models, terrain),
        (expected.instances, expected.terrain_blocks)
    );
    for caster in casters.iter().filter(|c| c["kind"] == "model") {
        let groups = caster["groups"].as_array().unwrap();
        let or = groups.iter().fold(0, |a, g| a | g.as_u64().unwrap());
        assert_eq!(caster["mask"].as_u64().unwrap(), or);
        assert!(caster["resources"]
            .as_array()
            .is_some_and(|r| !r.is_empty()));
        if caster["receiver_only"] == true {
            assert_eq!(
                caster["mask"], 0,
                "receiver-only instances are listed with mask 0"
            );
        }
    }
    assert_eq!(
        casters
            .iter()
            .filter(|c| c["receiver_only"] == true)
            .count() as u64,
        expected.receiver_only_instances
    );
    assert!(value["skipped"].is_array());
}

#[test]
fn bake_errors_exit_1_and_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    copy_fixture(Preset::Small, dir.path());
    let settings = dir.path().join(SETTINGS_FILE);
    let text = std::fs::read_to_string(&settings).unwrap();
    let lights: String = (0..33)
        .map(|i| format!("\t\t<light>\t<name>\tl{i}\t</name>\t<type>\tdirectional\t</type>\t<direction>\t0 -1 0\t</direction>\t<texelSize>\t1\t</texelSize>\t</light>\n"))
        .collect();
    let start = text.find("<lights>").unwrap() + "<lights>".len();
    let end = text.find("</lights>").unwrap();
    std::fs::write(
        &settings,
        format!("{}\n{lights}\t{}", &text[..start], &text[end..]),
    )
    .unwrap();
    let out = shadowcull(&["bake", settings.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let message = String::from_utf8_lossy(&out.stderr);
    assert!(
        message.contains("bake.xml") && message.contains("32"),
        "{message}"
    );
    assert_eq!(
        shadowcull(&["bake", settings.to_str().unwrap(), "--threads", "0"])
            .status
            .code(),
        Some(2)
    );
}

/// The masks of a whole fixture bake, as the report's `casters` list.
fn fixture_casters(preset: Preset) -> serde_json::Value {
    let settings_file = fixture_dir(preset).join(SETTINGS_FILE);
    let scene = load_world(&settings_file);
    let settings = shadowcull::files::read_bake_settings(&settings_file).unwrap();
    let config = BakeConfig::from_settings(&settings);
    let result = bake::bake(&scene, &config, &Silent).unwrap();
    serde_json::to_value(bake::output::report(&scene, &result).casters).unwrap()
}

#[test]
fn fixture_bakes_match_the_blessed_masks() {
    // A regression guard, not a correctness proof (that is the oracle and
    // the rule tests): a change of any mask in the fixtures must be a
    // deliberate one, re-blessed with SHADOWCULL_BLESS=1.
    for preset in [Preset::Small, Preset::Village] {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("fixtures/expected")
            .join(format!("{}-casters.json", preset.name()));
        let got = fixture_casters(preset);
        if std::env::var_os("SHADOWCULL_BLESS").is_some() {
            let text = serde_json::to_string_pretty(&got).unwrap() + "\n";
            shadowcull::files::write_atomic(&path, text.as_bytes()).unwrap();
        }
        let blessed: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap_or_else(|e| {
                panic!("{}: {e}; bless with SHADOWCULL_BLESS=1", path.display())
            }))
            .unwrap();
        assert!(
            got == blessed,
            "{} differs from this bake; if the change is intended, re-bless with SHADOWCULL_BLESS=1 cargo test fixture",
            path.display()
        );
    }
}

/// The output writes a chunk at the `<shadow>` places its load found,
/// without parsing it again: the same bytes as writing it parsed, into
/// chunks without masks and into chunks a bake wrote before.
#[test]
fn chunks_written_at_the_places_the_load_found_equal_chunks_parsed_again() {
    use shadowcull::bake::output;
    use shadowcull::files::ResPaths;
    let dir = tempfile::tempdir().unwrap();
    copy_fixture(Preset::Village, dir.path());
    let settings_file = dir.path().join(SETTINGS_FILE);
    let settings = shadowcull::files::read_bake_settings(&settings_file).unwrap();
    let config = BakeConfig::from_settings(&settings);
    let res_paths = ResPaths::new(settings.res_paths.clone());
    for round in ["into chunks without masks", "into chunks baked before"] {
        let scene = load_world(&settings_file);
        let mut parsed_again = scene.clone();
        for chunk in &mut parsed_again.chunks {
            chunk.sites = None;
        }
        let mut outputs = Vec::new();
        for scene in [&scene, &parsed_again] {
            let mut result = bake::bake(scene, &config, &Silent).unwrap();
            let keep = !result.baked_bits;
            for sites in scene.chunks.iter().filter_map(|c| c.sites.as_ref()) {
                let held = sites.held();
                assert!(held.is_some_and(|h| h & keep == 0), "{round}: places used");
            }
            let out = tempfile::tempdir().unwrap();
            let made =
                output::chunk_outputs(scene, &mut result, &res_paths, Some(out.path()), &Silent)
                    .unwrap();
            output::write_outputs(&made, &Silent).unwrap();
            let files: Vec<_> = snapshot(out.path())
                .into_iter()
                .map(|(p, b)| (p.strip_prefix(out.path()).unwrap().to_path_buf(), b))
                .collect();
            outputs.push(files);
        }
        assert!(scene.chunks.iter().all(|c| c.sites.is_some()), "{round}");
        assert_eq!(outputs[0].len(), scene.chunks.len(), "{round}");
        assert!(outputs[0] == outputs[1], "{round}: the two writes differ");
        let baked = shadowcull(&["bake", settings_file.to_str().unwrap(), "--quiet"]);
        assert!(
            baked.status.success(),
            "{}",
            String::from_utf8_lossy(&baked.stderr)
        );
    }
}
