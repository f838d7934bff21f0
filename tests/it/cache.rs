//! The bake cache (docs/contract.md §5, §8): a cached bake gives the bytes
//! of a bake without cache after any edit, in every mode.
//!
//! - Micro worlds, one per input of the keys: an edit of that input
//!   changes the masks; a cached bake after it equals a fresh bake, and
//!   with that input left out of every key (`KeyInput`) it does not, so
//!   every input is needed.
//! - Generated worlds through the binary: seeded random edit sequences
//!   (instances moved, added, deleted; a model's primitives, terrain
//!   heights, `castsShadow`, a light, the options, `--light` subsets),
//!   the chunk files and report casters after each edit those of a bake
//!   without cache; bakes killed at random moments; damaged, truncated and
//!   swapped entries; two bakes on one cache at once; shards and merge.

use crate::micro::{config, cube, directional, quad_up, Mesh, World, CHUNK, OPAQUE};
use crate::support::{model_elements, moved};
use glam::{DMat4, DVec3, Vec3};
use shadowcull::bake::cache_keys::KeyInput;
use shadowcull::bake::cached::BakeCache;
use shadowcull::bake::setup::BakeWorld;
use shadowcull::bake::{self, BakeConfig, BakeResult, Silent};
use shadowcull::cache::{content_key, Cache};
use shadowcull::formats::bake_settings::FaceCulling;
use shadowcull::scene::SceneKeys;

/// Places `triangles` (world coordinates) as one model in chunk `grid`;
/// returns the instance.
fn put(world: &mut World, grid: (i32, i32), triangles: Vec<[Vec3; 3]>, casts: bool) -> usize {
    let origin = Vec3::new(
        grid.0 as f32 * CHUNK as f32,
        0.0,
        grid.1 as f32 * CHUNK as f32,
    );
    let local: Vec<[Vec3; 3]> = triangles
        .into_iter()
        .map(|t| t.map(|v| v - origin))
        .collect();
    let model = world.model(Mesh {
        groups: vec![(local, OPAQUE)],
    });
    world.place(grid, &[model], DMat4::IDENTITY, casts)
}

/// A closed box from `min` to `max` (world coordinates) in chunk `grid`.
fn block(world: &mut World, grid: (i32, i32), min: [f32; 3], max: [f32; 3]) -> usize {
    put(world, grid, cube(Vec3::from(min), Vec3::from(max)), true)
}

/// `nx` × `nz` chunks, flat terrain at 0 on each when `terrain`.
fn flat(nx: i32, nz: i32, terrain: bool) -> World {
    let mut world = World::new(nx, nz);
    if terrain {
        for x in 0..nx {
            for z in 0..nz {
                world.terrain((x, z), |_, _| 0.0);
            }
        }
    }
    world
}

/// Bakes `world` with a cache in `cache`, `left_out` left out of every key.
fn cached(
    world: &World,
    config: &BakeConfig,
    cache: &Cache,
    left_out: Option<KeyInput>,
) -> BakeResult {
    let bake_world = BakeWorld::new(&world.scene);
    let bake_cache = BakeCache::new(cache, &bake_world, SceneKeys::of(&world.scene), left_out);
    bake::bake_cached(&bake_world, config, &Silent, &bake_cache).expect("cached bake")
}

fn fresh(world: &World, config: &BakeConfig) -> BakeResult {
    bake::bake(&world.scene, config, &Silent).expect("bake")
}

/// An edit of one input of the keys: the world (and settings) before and
/// after it.
struct Scenario {
    name: &'static str,
    input: KeyInput,
    before: (World, BakeConfig),
    after: (World, BakeConfig),
}

fn sun(texel: f64) -> BakeConfig {
    config(vec![directional(DVec3::NEG_Y, texel)])
}

/// Two tall thin boxes at the corners of a `nx` × 1-chunk world, from
/// −10 m to 30 m: they hold the world's bounds (and so a sun's grid) fixed
/// while the edits move things inside it.
fn anchors(world: &mut World, nx: i32) {
    let far = nx as f32 * CHUNK as f32;
    block(world, (0, 0), [0.0, -10.0, 0.0], [0.1, 30.0, 0.1]);
    block(
        world,
        (nx - 1, 0),
        [far - 0.1, -10.0, 15.9],
        [far, 30.0, 16.0],
    );
}

/// A 1 m box over flat terrain at `y` (edited: `transform` or model).
fn box_over_terrain(y: f32) -> World {
    let mut world = flat(2, 1, true);
    anchors(&mut world, 2);
    block(&mut world, (0, 0), [5.0, y, 5.0], [6.0, y + 1.0, 6.0]);
    world
}

fn part_transform() -> Scenario {
    let build = |y: f64| {
        let mut world = flat(2, 1, true);
        anchors(&mut world, 2);
        let model = world.model(Mesh {
            groups: vec![(cube(Vec3::ZERO, Vec3::ONE), OPAQUE)],
        });
        world.place(
            (0, 0),
            &[model],
            DMat4::from_translation(DVec3::new(5.0, y, 5.0)),
            true,
        );
        world
    };
    Scenario {
        name: "a box moved under the ground",
        input: KeyInput::PartTransform,
        before: (build(2.0), sun(0.25)),
        after: (build(-3.0), sun(0.25)),
    }
}

fn part_model() -> Scenario {
    let build = |low: f32| {
        let mut world = flat(2, 1, true);
        anchors(&mut world, 2);
        let model = world.model(Mesh {
            groups: vec![(
                cube(Vec3::new(0.0, low, 0.0), Vec3::new(1.0, low + 1.0, 1.0)),
                OPAQUE,
            )],
        });
        world.place(
            (0, 0),
            &[model],
            DMat4::from_translation(DVec3::new(5.0, 2.0, 5.0)),
            true,
        );
        world
    };
    Scenario {
        name: "a model's geometry moved under the ground",
        input: KeyInput::PartModel,
        before: (build(0.0), sun(0.25)),
        after: (build(-5.0), sun(0.25)),
    }
}

fn part_casts_shadow() -> Scenario {
    let build = |casts: bool| {
        let mut world = box_over_terrain(2.0);
        put(
            &mut world,
            (0, 0),
            cube(Vec3::new(4.0, 4.0, 4.0), Vec3::new(7.0, 5.0, 7.0)),
            casts,
        );
        world
    };
    Scenario {
        name: "castsShadow of a box over another turned off",
        input: KeyInput::PartCastsShadow,
        before: (build(true), sun(0.25)),
        after: (build(false), sun(0.25)),
    }
}

fn block_content() -> Scenario {
    let build = |raised: f64| {
        let mut world = World::new(2, 1);
        world.terrain((0, 0), |x, z| {
            let under_box = (3.0..8.0).contains(&x) && (3.0..8.0).contains(&z);
            if under_box {
                raised
            } else {
                0.0
            }
        });
        world.terrain((1, 0), |_, _| 0.0);
        anchors(&mut world, 2);
        block(&mut world, (0, 0), [5.0, 2.0, 5.0], [6.0, 3.0, 6.0]);
        world
    };
    Scenario {
        name: "terrain raised over a box",
        input: KeyInput::BlockContent,
        before: (build(0.0), sun(0.25)),
        after: (build(5.0), sun(0.25)),
    }
}

fn block_origin() -> Scenario {
    let build = |terrain_at: i32| {
        let mut world = World::new(2, 1);
        world.terrain((terrain_at, 0), |_, _| 0.0);
        anchors(&mut world, 2);
        block(&mut world, (0, 0), [13.0, 2.0, 5.0], [15.5, 3.0, 6.0]);
        world
    };
    Scenario {
        name: "the same terrain block in the next chunk",
        input: KeyInput::BlockOrigin,
        before: (build(0), sun(0.25)),
        after: (build(1), sun(0.25)),
    }
}

fn ground_blocks() -> Scenario {
    // A light from −x skimming under a terrain block at 25 m: its rays meet
    // two boxes under the block without crossing it (they enter under it
    // from the world's edge), and the block's image lies more than a cell
    // (10 m) above theirs, so the block is not in their cells' reach,
    // but the below-ground test reads it for their hits. A hole over the
    // boxes makes them count.
    let build = |hole: bool| {
        let mut world = World::new(2, 1);
        let holes =
            move |x: f64, z: f64| hole && (2.0..12.0).contains(&x) && (4.0..7.0).contains(&z);
        world.terrain_with_holes((1, 0), 16, |_, _| 25.0, holes);
        block(&mut world, (1, 0), [20.0, 0.0, 5.0], [21.0, 1.0, 6.0]);
        block(&mut world, (1, 0), [25.0, 0.0, 5.0], [26.0, 1.0, 6.0]);
        world
    };
    let light = || config(vec![directional(DVec3::new(1.0, -0.05, 0.0), 0.02)]);
    Scenario {
        name: "a hole in terrain above boxes it does not cover on the light's image",
        input: KeyInput::GroundBlocks,
        before: (build(false), light()),
        after: (build(true), light()),
    }
}

fn cell_index() -> Scenario {
    // Per row of cells, a strip over a sliver that meets it at one end
    // only: both cells of the row reach both, but only one proves the
    // strip. The two rows mirror each other, so whichever cell goes first
    // one row has the wrong one's answer when cells share keys.
    let build = || {
        let mut world = World::new(2, 2);
        for (z, near) in [(1.0f32, 1.0f32), (27.0, 30.0)] {
            put(
                &mut world,
                (0, 0),
                quad_up(1.0, z, 31.0, z + 0.5, 2.0),
                true,
            );
            let far = 32.0 - near;
            let sliver = vec![[
                Vec3::new(near, 1.0, z),
                Vec3::new(near + if near < 16.0 { 2.0 } else { -2.0 }, 1.0, z + 0.5),
                Vec3::new(far, 1.0, z - 0.5 + if z < 16.0 { 11.0 } else { -11.0 }),
            ]];
            let up = sliver
                .into_iter()
                .map(|[a, b, c]| {
                    if (b - a).cross(c - a).y > 0.0 {
                        [a, b, c]
                    } else {
                        [a, c, b]
                    }
                })
                .collect();
            put(&mut world, (0, 0), up, true);
        }
        world
    };
    Scenario {
        name: "two cells that reach the same parts",
        input: KeyInput::CellIndex,
        // Texels of 5 cm: the 32 m square spans two cells a side.
        before: (World::new(2, 2), sun(0.05)),
        after: (build(), sun(0.05)),
    }
}

fn light_settings() -> Scenario {
    let build = || {
        let mut world = flat(2, 1, true);
        block(&mut world, (0, 0), [10.0, 1.0, 5.0], [11.0, 2.0, 6.0]);
        block(&mut world, (0, 0), [12.0, 0.0, 3.0], [12.5, 8.0, 8.0]);
        world
    };
    Scenario {
        name: "the sun turned so a wall shadows a box",
        input: KeyInput::LightSettings,
        before: (build(), sun(0.5)),
        after: (
            build(),
            config(vec![directional(DVec3::new(-1.0, -0.5, 0.0), 0.5)]),
        ),
    }
}

fn world_bounds() -> Scenario {
    // A pole thinner than a texel, hit by the texel centres or not as the
    // grid's origin (the world's low corner) moves by 0.1 m; the world is
    // wide enough that its cell (128 m) holds neither of the poles at the
    // edges that move the bounds.
    let build = |shift: f32| {
        let mut world = World::new(17, 1);
        let far = 17.0 * CHUNK as f32;
        block(
            &mut world,
            (0, 0),
            [shift, -1.0, 0.0],
            [shift + 0.1, 10.0, 16.0],
        );
        block(
            &mut world,
            (16, 0),
            [far - 0.1 + shift, -1.0, 0.0],
            [far + shift, 10.0, 16.0],
        );
        block(&mut world, (8, 0), [136.1, 0.5, 2.0], [136.15, 3.0, 14.0]);
        put(
            &mut world,
            (8, 0),
            quad_up(134.0, 1.0, 139.0, 15.0, 0.0),
            true,
        );
        world
    };
    Scenario {
        name: "the world's bounds moved by less than a texel",
        input: KeyInput::WorldBounds,
        before: (build(0.0), sun(0.25)),
        after: (build(-0.1), sun(0.25)),
    }
}

fn options() -> Scenario {
    let build = || {
        let mut world = World::new(1, 1);
        block(&mut world, (0, 0), [5.0, 2.0, 5.0], [6.0, 3.0, 6.0]);
        world
    };
    let none = BakeConfig {
        face_culling: FaceCulling::None,
        ..sun(0.25)
    };
    Scenario {
        name: "face culling off: a box over the void crossed twice",
        input: KeyInput::Options,
        before: (build(), sun(0.25)),
        after: (build(), none),
    }
}

/// A box of `size` metres at (5.6, 2, 5.6) (between texel centres of a
/// 1 m sun) over a receiver-only plate when `plate`.
fn small_box(size: f32, plate: bool) -> World {
    let mut world = World::new(2, 1);
    anchors(&mut world, 2);
    block(
        &mut world,
        (0, 0),
        [5.6, 2.0, 5.6],
        [5.6 + size, 2.0 + size, 5.6 + size],
    );
    if plate {
        put(&mut world, (1, 0), quad_up(4.0, 4.0, 8.0, 8.0, 1.0), false);
    }
    world
}

fn refining(samples: u32, density: u32) -> BakeConfig {
    BakeConfig {
        refine_samples: samples,
        refine_density: density,
        ..sun(1.0)
    }
}

fn refine_options() -> Scenario {
    Scenario {
        name: "refinement's lattice made dense enough to find a small box",
        input: KeyInput::RefineOptions,
        before: (small_box(0.1, true), refining(0, 1)),
        after: (small_box(0.1, true), refining(0, 4)),
    }
}

fn refine_cells() -> Scenario {
    Scenario {
        name: "a receiver put under a small box the grid misses",
        input: KeyInput::RefineCells,
        before: (small_box(0.1, false), refining(0, 4)),
        after: (small_box(0.1, true), refining(0, 4)),
    }
}

fn refine_seed() -> Scenario {
    // A quad between texel centres, over a receiver under half of it: its
    // one surface point proves it or not by its seed, which follows its
    // id. Receiver-only boxes in another cell (the world is 640 m wide,
    // cells 512 m), earlier in id order, shift its id.
    let build = |dummies: usize| {
        let mut world = World::new(40, 1);
        block(&mut world, (0, 0), [0.0, -1.0, 0.0], [0.1, 5.0, 0.1]);
        block(&mut world, (39, 0), [639.9, -1.0, 15.9], [640.0, 5.0, 16.0]);
        for n in 0..dummies {
            let x = 1.0 + n as f32 * 0.5;
            let dummy = cube(Vec3::new(x, 0.0, 1.0), Vec3::new(x + 0.1, 0.1, 1.1));
            put(&mut world, (0, 0), dummy, false);
        }
        put(
            &mut world,
            (39, 0),
            quad_up(628.62, 5.62, 629.08, 6.08, 2.0),
            true,
        );
        put(
            &mut world,
            (39, 0),
            quad_up(628.0, 5.0, 628.85, 7.0, 1.0),
            false,
        );
        world
    };
    let config = refining(1, 0);
    let proven = |world: &World| {
        let result = fresh(world, &config);
        result.masks.iter().filter(|&&m| m != 0).count()
    };
    let base = proven(&build(0));
    let dummies = (1..64)
        .find(|&n| proven(&build(n)) != base)
        .expect("some id of the quad flips its one surface point");
    Scenario {
        name: "a refined caster's id shifted by instances before it",
        input: KeyInput::RefineSeed,
        before: (build(0), config.clone()),
        after: (build(dummies), config),
    }
}

fn scenarios() -> Vec<Scenario> {
    vec![
        part_transform(),
        part_model(),
        part_casts_shadow(),
        block_content(),
        block_origin(),
        ground_blocks(),
        cell_index(),
        light_settings(),
        world_bounds(),
        options(),
        refine_options(),
        refine_cells(),
        refine_seed(),
    ]
}

/// One thread: cells are traced (and stored) in order, so a key shared by
/// two cells is met in the same order every time.
fn one_thread<T: Send>(work: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(work)
}

#[test]
fn every_input_of_the_keys_is_covered() {
    let all = scenarios();
    for input in KeyInput::ALL {
        assert!(
            all.iter().any(|s| s.input == input),
            "no scenario edits {input:?}"
        );
    }
}

#[test]
fn after_an_edit_of_any_input_a_cached_bake_equals_a_fresh_one() {
    for scenario in scenarios() {
        let (before, before_config) = &scenario.before;
        let (after, after_config) = &scenario.after;
        let fresh_before = fresh(before, before_config);
        let fresh_after = fresh(after, after_config);
        assert_ne!(
            fresh_before.masks, fresh_after.masks,
            "{}: the edit changes no mask",
            scenario.name
        );
        let dir = tempfile::tempdir().unwrap();
        let cache = Cache::open(dir.path(), u64::MAX, content_key(b"test build"));
        one_thread(|| {
            let first = cached(before, before_config, &cache, None);
            assert_eq!(first.masks, fresh_before.masks, "{}: before", scenario.name);
            for round in ["after", "after, again"] {
                let second = cached(after, after_config, &cache, None);
                assert_eq!(
                    second.masks, fresh_after.masks,
                    "{}: {round}",
                    scenario.name
                );
            }
        });
    }
}

/// Leaving an input out of every key makes the cached bake after its
/// scenario's edit go wrong: each input is needed.
#[test]
fn a_key_without_any_one_input_goes_wrong() {
    for scenario in scenarios() {
        let (before, before_config) = &scenario.before;
        let (after, after_config) = &scenario.after;
        let fresh_after = fresh(after, after_config);
        let dir = tempfile::tempdir().unwrap();
        let cache = Cache::open(dir.path(), u64::MAX, content_key(b"test build"));
        let left_out = Some(scenario.input);
        let wrong = one_thread(|| {
            cached(before, before_config, &cache, left_out);
            let after = cached(after, after_config, &cache, left_out);
            after.masks != fresh_after.masks
        });
        assert!(
            wrong,
            "{} with {:?} left out of the keys: still right",
            scenario.name, scenario.input
        );
    }
}

// ---------------------------------------------------------------------------
// Generated worlds through the binary.

use shadowcull::files::write_tree;
use shadowcull::gen::{generate, Preset};
use shadowcull::rng::Rng;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Instant;

const SPACE: &str = "spaces/small";

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn ok(output: Output, what: &str) -> Output {
    assert!(
        output.status.success(),
        "{what}: {}\n{}",
        String::from_utf8_lossy(&output.stderr),
        String::from_utf8_lossy(&output.stdout)
    );
    output
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// The `small` world written to `dir`; its settings file.
fn small_world(dir: &Path) -> PathBuf {
    write_tree(dir, &generate(Preset::Small, 1).files).unwrap();
    dir.join("bake.xml")
}

/// Every file of `dir` but its bake cache, relative path → bytes.
fn world_files(dir: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(folder) = pending.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.ends_with(".shadowcull-cache") {
                continue;
            }
            if path.is_dir() {
                pending.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                out.insert(path.strip_prefix(dir).unwrap().to_path_buf(), bytes);
            }
        }
    }
    out
}

fn report(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// What two bakes must agree on: the report's casters and each light's
/// rays.
fn masks_and_rays(report: &serde_json::Value) -> (serde_json::Value, Vec<(u64, u64)>) {
    let rays = report["lights"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| {
            (
                l["rays"].as_u64().unwrap(),
                l["refine_rays"].as_u64().unwrap(),
            )
        })
        .collect();
    (report["casters"].clone(), rays)
}

/// A world baked with a cache and its twin baked without, edited alike.
struct Twins {
    cached: tempfile::TempDir,
    fresh: tempfile::TempDir,
    /// The space folder, relative to the world's root.
    space: &'static str,
}

impl Twins {
    /// Twins of the `small` world.
    fn new() -> Twins {
        let twins = Twins::of(Preset::Small, SPACE);
        small_world(twins.cached.path());
        small_world(twins.fresh.path());
        twins
    }

    /// Twins of `preset` (seed 1), whose space is `space`.
    fn of(preset: Preset, space: &'static str) -> Twins {
        let twins = Twins {
            cached: tempfile::tempdir().unwrap(),
            fresh: tempfile::tempdir().unwrap(),
            space,
        };
        for dir in [twins.cached.path(), twins.fresh.path()] {
            write_tree(dir, &generate(preset, 1).files).unwrap();
        }
        twins
    }

    /// Writes `bytes` to `relative` in both worlds.
    fn write(&self, relative: &str, bytes: &[u8]) {
        for dir in [self.cached.path(), self.fresh.path()] {
            std::fs::write(dir.join(relative), bytes).unwrap();
        }
    }

    fn read(&self, relative: &str) -> Vec<u8> {
        std::fs::read(self.cached.path().join(relative)).unwrap()
    }

    /// Bakes both in place with `flags` (the cached one with its default
    /// cache) and checks they agree; returns the cached bake's report.
    fn bake_and_compare(&self, flags: &[&str], what: &str) -> serde_json::Value {
        let mut reports = Vec::new();
        for (dir, cache) in [
            (self.cached.path(), None),
            (self.fresh.path(), Some("--no-cache")),
        ] {
            let report_path = dir.join("report.json");
            let settings = dir.join("bake.xml");
            let mut args = vec!["bake", s(&settings), "--report", s(&report_path), "--quiet"];
            args.extend(flags);
            args.extend(cache);
            ok(run(&args), what);
            reports.push(report(&report_path));
        }
        let chunks = |dir: &Path| {
            world_files(&dir.join(self.space))
                .into_iter()
                .filter(|(p, _)| p.extension().is_some_and(|e| e == "chunk"))
                .collect::<Vec<_>>()
        };
        assert!(
            chunks(self.cached.path()) == chunks(self.fresh.path()),
            "{what}: the chunk files differ"
        );
        assert_eq!(
            masks_and_rays(&reports[0]),
            masks_and_rays(&reports[1]),
            "{what}: the reports differ"
        );
        assert!(
            reports[1].get("cache").is_none(),
            "no cache, no report of it"
        );
        reports.swap_remove(0)
    }
}

const CHUNKS: [&str; 4] = ["00000000o", "0000ffffo", "ffff0000o", "ffffffffo"];

/// One seeded edit of the world (both twins alike); says what it did.
fn edit(twins: &Twins, rng: &mut Rng, kind: usize) -> String {
    let chunk = CHUNKS[rng.below(CHUNKS.len())];
    let chunk_file = format!("{SPACE}/{chunk}.chunk");
    let text = String::from_utf8(twins.read(&chunk_file)).unwrap();
    let models = model_elements(&text);
    let pick = models[rng.below(models.len())].clone();
    let element = &text[pick.clone()];
    let with = |replacement: String| {
        let edited = format!("{}{replacement}{}", &text[..pick.start], &text[pick.end..]);
        twins.write(&chunk_file, edited.as_bytes());
    };
    match kind {
        0 => {
            let (dx, dz) = (rng.range(-5.0, 5.0), rng.range(-5.0, 5.0));
            with(moved(element, dx, dz));
            format!("moved an instance of {chunk} by ({dx:.1}, {dz:.1}) m")
        }
        1 => {
            with(format!("{element}{}", moved(element, 3.0, -2.0)));
            format!("added an instance to {chunk}")
        }
        2 if models.len() > 1 => {
            with(String::new());
            format!("deleted an instance of {chunk}")
        }
        3 => {
            let flipped = if element.contains("<castsShadow>\tfalse") {
                element.replace("<castsShadow>\tfalse", "<castsShadow>\ttrue")
            } else if element.contains("<castsShadow>\ttrue") {
                element.replace("<castsShadow>\ttrue", "<castsShadow>\tfalse")
            } else {
                element.replace(
                    "\t</model>",
                    "\t\t<castsShadow>\tfalse\t</castsShadow>\n\t</model>",
                )
            };
            with(flipped);
            format!("flipped castsShadow of an instance of {chunk}")
        }
        4 => {
            let model = [
                "props/crate",
                "props/pillar",
                "buildings/house",
                "trees/tree",
            ][rng.below(4)];
            let file = format!("sets/gen/{model}.primitives");
            let scale = rng.range(0.6, 1.6) as f32;
            twins.write(&file, &scaled_primitives(&twins.read(&file), scale));
            format!("scaled {model}'s primitives by {scale:.2} in height")
        }
        5 => {
            let file = format!("{SPACE}/{chunk}.cdata");
            let raise = rng.range(-2.0, 2.0) as f32;
            twins.write(&file, &raised_terrain(&twins.read(&file), raise));
            format!("raised the terrain of {chunk} by {raise:.2} m")
        }
        _ => {
            let settings = String::from_utf8(twins.read("bake.xml")).unwrap();
            let x = rng.range(-0.5, 0.5);
            let turned = settings.replace(
                "-0.300000 -1.000000 0.200000",
                &format!("{x:.6} -1.000000 0.200000"),
            );
            twins.write("bake.xml", turned.as_bytes());
            format!("turned the sun (x {x:.2})")
        }
    }
}

/// A `.primitives` file's vertices scaled by `scale` in height.
fn scaled_primitives(bytes: &[u8], scale: f32) -> Vec<u8> {
    use shadowcull::formats::{binsection, primitives};
    let container = binsection::parse(bytes).unwrap();
    let sections: Vec<(String, Vec<u8>)> = container
        .entries
        .iter()
        .map(|entry| {
            let data = &bytes[entry.data.clone()];
            let data = match primitives::read_vertices(data) {
                Ok(vertices) if entry.name.contains("vertices") => {
                    let positions: Vec<[f32; 3]> = vertices
                        .positions
                        .iter()
                        .map(|&[x, y, z]| [x, y * scale, z])
                        .collect();
                    primitives::write_vertices(&positions, &vec![[0.0, 1.0, 0.0]; positions.len()])
                }
                _ => data.to_vec(),
            };
            (entry.name.clone(), data)
        })
        .collect();
    let refs: Vec<(&str, &[u8])> = sections
        .iter()
        .map(|(n, d)| (n.as_str(), d.as_slice()))
        .collect();
    binsection::write(&refs)
}

/// A terrain2 `.cdata`'s heights raised by `raise` metres.
fn raised_terrain(bytes: &[u8], raise: f32) -> Vec<u8> {
    use shadowcull::formats::terrain;
    let mut data = terrain::read_terrain(bytes, "terrain2").unwrap();
    for h in &mut data.heights.heights {
        *h += raise;
    }
    terrain::write_terrain2_cdata(&data.heights, data.holes.as_ref())
}

/// The options a step bakes with: each a way to change the answer.
const OPTIONS: &[&[&str]] = &[
    &[],
    &["--filter-radius", "1"],
    &["--supersample", "2"],
    &["--conservative"],
    &["--refine", "--refine-samples", "8", "--refine-density", "2"],
    &["--light", "spot"],
    &["--light", "sun", "--light", "point"],
    &["--height-bias", "0.3"],
];

fn edit_sequence(seed: u64, steps: usize) {
    let twins = Twins::new();
    twins.bake_and_compare(&[], "the first bake");
    let again = twins.bake_and_compare(&[], "nothing changed");
    let cells = &again["cache"]["cells"];
    assert_eq!(cells["computed"], 0, "nothing changed: {cells}");
    assert!(cells["reused"].as_u64().unwrap() > 10, "{cells}");
    assert_eq!(
        again["cache"]["output"]["computed"], 0,
        "{}",
        again["cache"]
    );
    let mut rng = Rng::new(seed);
    for step in 0..steps {
        let kind = rng.below(8);
        let what = match kind {
            7 => "the options changed".to_string(),
            _ => edit(&twins, &mut rng, kind),
        };
        let options = OPTIONS[if kind == 7 {
            1 + rng.below(OPTIONS.len() - 1)
        } else {
            0
        }];
        twins.bake_and_compare(options, &format!("seed {seed} step {step}: {what}"));
    }
}

/// `text` with the first occurrence of `from` replaced by `to` (which must
/// be there: an edit that does nothing tests nothing).
fn replaced_once(text: &str, from: &str, to: &str) -> String {
    assert!(text.contains(from), "`{from}` not found");
    text.replacen(from, to, 1)
}

#[test]
fn a_forest_rebaked_after_tree_edits_equals_a_bake_without_cache() {
    let twins = Twins::of(Preset::Forest, "spaces/forest");
    twins.bake_and_compare(&[], "the first bake");
    let chunk = "spaces/forest/00000000o.chunk";
    let text = String::from_utf8(twins.read(chunk)).unwrap();
    // A tree moved: the 12-float transform's translation, then a row form.
    let at = text.find("<speedtree>").unwrap();
    let moved = replaced_once(
        &text[at..],
        " 4.000000 -1.008000 4.000000\t",
        " 9.000000 -1.008000 6.000000\t",
    );
    twins.write(chunk, format!("{}{moved}", &text[..at]).as_bytes());
    twins.bake_and_compare(&[], "a tree moved");
    let text = String::from_utf8(twins.read(chunk)).unwrap();
    let moved = replaced_once(&text, "<row3>\t46.000000", "<row3>\t40.000000");
    twins.write(chunk, moved.as_bytes());
    twins.bake_and_compare(&[], "a tree's row transform moved");
    // A tree turned into another species (another proxy rule).
    let text = String::from_utf8(twins.read(chunk)).unwrap();
    let species = replaced_once(
        &text,
        "speedtree/forest/Oak1.spt",
        "speedtree/forest/Pine_a.spt",
    );
    twins.write(chunk, species.as_bytes());
    twins.bake_and_compare(&[], "a tree's species changed");
    // The parametric proxies resized in the settings file.
    let settings = String::from_utf8(twins.read("bake.xml")).unwrap();
    let taller = replaced_once(
        &settings,
        "<height>\t6.000000\t</height>",
        "<height>\t9.000000\t</height>",
    );
    twins.write("bake.xml", taller.as_bytes());
    let again = twins.bake_and_compare(&[], "the pines' crowns taller");
    assert!(
        again["cache"]["cells"]["computed"].as_u64().unwrap() > 0,
        "a proxy resized must trace again: {}",
        again["cache"]
    );
}

#[test]
fn seeded_edit_sequences_on_a_generated_world_equal_fresh_bakes() {
    edit_sequence(7, 10);
}

#[test]
#[cfg_attr(
    not(shadowcull_slow),
    ignore = "longer edit sequences: set SHADOWCULL_SLOW=1"
)]
fn long_seeded_edit_sequences_equal_fresh_bakes() {
    for seed in 1..=4 {
        edit_sequence(seed, 25);
    }
}

#[test]
fn a_recomputed_cell_says_which_input_changed() {
    let twins = Twins::new();
    twins.bake_and_compare(&[], "the first bake");
    let becauses = |report: &serde_json::Value| -> Vec<(String, String)> {
        report["cache"]["lights"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|l| l["traced_because"].as_array().unwrap().clone())
            .map(|b| {
                (
                    b["input"].as_str().unwrap().to_string(),
                    b["name"].as_str().unwrap_or_default().to_string(),
                )
            })
            .collect()
    };
    let chunk_file = format!("{SPACE}/ffffffffo.chunk");
    let text = String::from_utf8(twins.read(&chunk_file)).unwrap();
    let first = model_elements(&text)[0].clone();
    let edited = format!(
        "{}{}{}",
        &text[..first.start],
        moved(&text[first.clone()], 0.5, 0.0),
        &text[first.end..]
    );
    twins.write(&chunk_file, edited.as_bytes());
    let why = becauses(&twins.bake_and_compare(&[], "moved"));
    assert!(
        why.contains(&("chunk".into(), "ffffffffo".into())),
        "{why:?}"
    );
    let cdata = format!("{SPACE}/0000ffffo.cdata");
    twins.write(&cdata, &raised_terrain(&twins.read(&cdata), 0.5));
    let why = becauses(&twins.bake_and_compare(&[], "raised"));
    assert!(
        why.contains(&("terrain".into(), "0000ffffo".into())),
        "{why:?}"
    );
    let file = "sets/gen/trees/tree.primitives";
    twins.write(file, &scaled_primitives(&twins.read(file), 1.2));
    let why = becauses(&twins.bake_and_compare(&[], "scaled"));
    assert!(
        why.contains(&("model".into(), "sets/gen/trees/tree.model".into())),
        "{why:?}"
    );
    let why = becauses(&twins.bake_and_compare(&["--filter-radius", "1"], "options"));
    assert!(why.contains(&("options".into(), String::new())), "{why:?}");
}

#[test]
fn a_light_whose_cells_the_cache_holds_is_set_up_once() {
    // The plan sets every light up to read its cells' entries; a light
    // whose top level is small (here empty: only the sun changed) is kept
    // for the bake instead of being set up again.
    let dir = tempfile::tempdir().unwrap();
    let settings = small_world(dir.path());
    ok(run(&["bake", s(&settings), "--quiet"]), "the first bake");
    let text = std::fs::read_to_string(&settings).unwrap();
    let turned = replaced_once(
        &text,
        "-0.300000 -1.000000 0.200000",
        "-0.200000 -1.000000 0.300000",
    );
    std::fs::write(&settings, turned).unwrap();
    let out = ok(
        run(&[
            "bake",
            s(&settings),
            "--progress",
            "json",
            "--progress-interval",
            "0",
        ]),
        "the sun turned",
    );
    let stderr = String::from_utf8(out.stderr).unwrap();
    for light in ["sun", "spot", "point"] {
        let set_up = stderr
            .lines()
            .filter_map(|line| serde_json::from_str::<serde_json::Value>(line).ok())
            .filter(|e| e["phase"] == "top-level" && e["light"] == light && e["done"] == 0)
            .count();
        assert_eq!(set_up, 1, "{light}: {stderr}");
    }
    assert!(
        stderr.contains("light spot: 1 cells, 1 reused")
            && stderr.contains("light point: 6 cells, 6 reused"),
        "{stderr}"
    );
}

/// The cache folder of `dir`'s default cache.
fn cache_of(dir: &Path) -> PathBuf {
    dir.join(".shadowcull-cache")
}

/// Every entry file of the cache folder `dir` of kind `kind`.
fn entries(dir: &Path, kind: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let Ok(folders) = std::fs::read_dir(dir.join(kind)) else {
        return out;
    };
    for folder in folders {
        for entry in std::fs::read_dir(folder.unwrap().path()).unwrap() {
            let path = entry.unwrap().path();
            if !path.to_string_lossy().ends_with(".tmp") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn damaged_entries_are_warned_about_recomputed_and_the_result_is_the_same() {
    let twins = Twins::new();
    let flags = ["--refine", "--refine-samples", "8", "--refine-density", "2"];
    twins.bake_and_compare(&flags, "the first bake");
    let cache = cache_of(twins.cached.path());
    let cells = entries(&cache, "cell");
    let refine = entries(&cache, "refine");
    let output = entries(&cache, "output");
    assert!(cells.len() >= 4 && refine.len() >= 2 && !output.is_empty());
    // Truncated, a bit flipped, another entry's bytes, emptied.
    let bytes = std::fs::read(&cells[0]).unwrap();
    std::fs::write(&cells[0], &bytes[..bytes.len() / 2]).unwrap();
    let mut flipped = std::fs::read(&cells[1]).unwrap();
    flipped[60] ^= 0x10;
    std::fs::write(&cells[1], flipped).unwrap();
    std::fs::copy(&refine[0], &refine[1]).unwrap();
    std::fs::copy(&cells[3], &cells[2]).unwrap();
    std::fs::write(&output[0], b"").unwrap();
    // Every chunk's parsed items: truncated.
    let chunks = entries(&cache, "chunk");
    assert!(chunks.len() >= CHUNKS.len());
    for entry in &chunks {
        let bytes = std::fs::read(entry).unwrap();
        std::fs::write(entry, &bytes[..bytes.len() - 1]).unwrap();
    }
    let touched = [&cells[0], &cells[1], &refine[1], &cells[2], &output[0]];
    let settings = twins.cached.path().join("bake.xml");
    let report_path = twins.cached.path().join("report.json");
    let mut args = vec!["bake", s(&settings), "--report", s(&report_path)];
    args.extend(flags);
    let out = ok(run(&args), "the bake over damaged entries");
    let stderr = String::from_utf8_lossy(&out.stderr);
    let warned = stderr.lines().filter(|l| l.contains("cache entry")).count();
    assert!(warned >= 4, "a line per damaged entry read: {stderr}");
    for path in touched.iter().take(3) {
        assert!(
            stderr.contains(&*path.to_string_lossy()),
            "{} named: {stderr}",
            path.display()
        );
    }
    let cached = report(&report_path);
    assert!(
        cached["cache"]["cells"]["damaged"].as_u64().unwrap() >= 3,
        "{}",
        cached["cache"]
    );
    assert_eq!(
        cached["cache"]["chunks"]["damaged"],
        CHUNKS.len(),
        "every chunk parsed again: {}",
        cached["cache"]
    );
    // The twin without cache baked the same world: the same result.
    twins.bake_and_compare(&flags, "after the damage");
    for path in touched {
        let bytes = std::fs::read(path).unwrap_or_default();
        assert!(bytes.len() > 60, "{} rewritten whole", path.display());
    }
}

#[test]
fn a_bake_killed_at_any_moment_leaves_a_cache_the_next_bake_can_trust() {
    let twins = Twins::new();
    let settings = twins.cached.path().join("bake.xml");
    let flags = ["--refine", "--refine-samples", "8", "--refine-density", "2"];
    let mut args = vec!["bake", s(&settings), "--quiet"];
    args.extend(flags);
    // How long a whole bake takes here, to kill the others within it.
    let started = Instant::now();
    ok(run(&args), "a whole bake");
    let whole = started.elapsed();
    let mut rng = Rng::new(3);
    for _ in 0..6 {
        // Something to recompute each time: a moved instance.
        edit(&twins, &mut rng, 0);
        let mut child = Command::new(env!("CARGO_BIN_EXE_shadowcull"))
            .args(&args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let after = whole.mul_f64(rng.range(0.05, 1.0));
        std::thread::sleep(after);
        let _ = child.kill();
        let _ = child.wait();
    }
    twins.bake_and_compare(&flags, "after the killed bakes");
    let stats = ok(
        run(&[
            "cache",
            s(&cache_of(twins.cached.path())),
            "stats",
            "--json",
        ]),
        "stats",
    );
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert!(stats["entries"].as_u64().unwrap() > 0, "{stats}");
}

#[test]
fn two_bakes_sharing_one_cache_are_both_right_and_leave_it_sound() {
    let dirs = [tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap()];
    let fresh = tempfile::tempdir().unwrap();
    let shared = tempfile::tempdir().unwrap();
    let cache = shared.path().join("cache");
    for dir in dirs.iter().chain([&fresh]) {
        small_world(dir.path());
    }
    let bake = |dir: &Path| -> Command {
        let mut command = Command::new(env!("CARGO_BIN_EXE_shadowcull"));
        command
            .args([
                "bake",
                s(&dir.join("bake.xml")),
                "--cache",
                s(&cache),
                "--quiet",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        command
    };
    let children: Vec<_> = dirs
        .iter()
        .map(|d| bake(d.path()).spawn().unwrap())
        .collect();
    for child in children {
        let out = child.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    ok(
        run(&[
            "bake",
            s(&fresh.path().join("bake.xml")),
            "--no-cache",
            "--quiet",
        ]),
        "fresh",
    );
    let expected = world_files(&fresh.path().join(SPACE));
    for dir in &dirs {
        assert!(
            world_files(&dir.path().join(SPACE)) == expected,
            "a concurrent bake differs"
        );
    }
    let stats = ok(run(&["cache", s(&cache), "stats", "--json"]), "stats");
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats["temporaries"], 0, "{stats}");
    // Every entry they left passes its check: a third bake reuses them all
    // without a warning.
    let third = tempfile::tempdir().unwrap();
    small_world(third.path());
    let report_path = third.path().join("report.json");
    let out = ok(
        run(&[
            "bake",
            s(&third.path().join("bake.xml")),
            "--cache",
            s(&cache),
            "--report",
            s(&report_path),
        ]),
        "a third bake",
    );
    assert!(!String::from_utf8_lossy(&out.stderr).contains("cache entry"));
    let cells = &report(&report_path)["cache"]["cells"];
    assert_eq!(
        (cells["computed"].as_u64(), cells["damaged"].as_u64()),
        (Some(0), Some(0)),
        "{cells}"
    );
    assert!(world_files(&third.path().join(SPACE)) == expected);
}

#[test]
fn shards_and_merge_with_a_cache_write_what_one_bake_writes() {
    let dir = tempfile::tempdir().unwrap();
    let settings = small_world(dir.path());
    let work = tempfile::tempdir().unwrap();
    let cache = work.path().join("cache");
    let one = work.path().join("one");
    ok(
        run(&[
            "bake",
            s(&settings),
            "--out",
            s(&one),
            "--no-cache",
            "--refine",
            "--quiet",
        ]),
        "one bake",
    );
    for round in ["an empty cache", "the cache the first round filled"] {
        let merged = work.path().join(format!("merged {round}"));
        let mut partials = Vec::new();
        for index in 0..3 {
            let partial = work.path().join(format!("p{index}.part"));
            let shard = format!("{index}/3");
            let out = ok(
                run(&[
                    "bake",
                    s(&settings),
                    "--shard",
                    &shard,
                    "--partial",
                    s(&partial),
                    "--cache",
                    s(&cache),
                ]),
                &format!("shard {shard} with {round}"),
            );
            let stdout = String::from_utf8_lossy(&out.stderr);
            if round.starts_with("the cache") {
                assert!(stdout.contains(" 0 traced"), "{stdout}");
            }
            partials.push(partial);
        }
        let mut args = vec!["merge", s(&settings)];
        args.extend(partials.iter().map(|p| s(p)));
        args.extend([
            "--out",
            s(&merged),
            "--cache",
            s(&cache),
            "--refine",
            "--quiet",
        ]);
        ok(run(&args), &format!("merge with {round}"));
        assert!(
            world_files(&one) == world_files(&merged),
            "{round}: the merge differs"
        );
    }
}

#[test]
fn plan_and_the_cache_command_say_what_the_cache_holds() {
    let dir = tempfile::tempdir().unwrap();
    let settings = small_world(dir.path());
    let cache = cache_of(dir.path());
    let plan = |expect: &str| {
        let out = ok(run(&["plan", s(&settings)]), "plan");
        let stdout = String::from_utf8_lossy(&out.stdout).to_string();
        assert!(stdout.contains(expect), "`{expect}` in: {stdout}");
    };
    plan("cache: 0 of ");
    ok(run(&["bake", s(&settings), "--quiet"]), "bake");
    plan("cells stored, a cached bake traces 0");
    let stats = ok(run(&["cache", s(&cache), "stats"]), "stats");
    let text = String::from_utf8_lossy(&stats.stdout).to_string();
    for kind in ["cell", "manifest", "output"] {
        assert!(text.contains(kind), "{text}");
    }
    ok(run(&["cache", s(&cache), "clear"]), "clear");
    let stats = ok(run(&["cache", s(&cache), "stats", "--json"]), "stats");
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats["entries"], 0, "{stats}");
    // A cache limit evicts the least recently used entries after a bake.
    ok(
        run(&["bake", s(&settings), "--quiet", "--cache-max", "5k"]),
        "a bake under a limit",
    );
    let stats = ok(run(&["cache", s(&cache), "stats", "--json"]), "stats");
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert!(stats["bytes"].as_u64().unwrap() <= 5000, "{stats}");
}

// ---------------------------------------------------------------------------
// The world's record: an unchanged world is not loaded again.

const UP_TO_DATE: &str = "cache: up to date";

/// Bakes `dir`'s settings in place (`flags` added); says whether the bake
/// found the world as its record left it.
fn bake_in_place(dir: &Path, flags: &[&str], what: &str) -> bool {
    let settings = dir.join("bake.xml");
    let mut args = vec!["bake", s(&settings)];
    args.extend(flags);
    let output = ok(run(&args), what);
    String::from_utf8_lossy(&output.stderr).contains(UP_TO_DATE)
}

/// The chunk files of `dir`'s space `space`, path → bytes.
fn chunk_files(dir: &Path, space: &str) -> Vec<(PathBuf, Vec<u8>)> {
    world_files(&dir.join(space))
        .into_iter()
        .filter(|(p, _)| p.extension().is_some_and(|e| e == "chunk"))
        .collect()
}

/// After `edit` of both twins: the cached twin's bake must not take the
/// world for unchanged, must write what a bake without cache writes, and
/// the bake after it finds the world as it left it.
fn edited_and_rebaked(twins: &Twins, what: &str, edit: impl Fn(&Path)) {
    edit(twins.cached.path());
    edit(twins.fresh.path());
    assert!(
        !bake_in_place(twins.cached.path(), &[], what),
        "{what}: taken for unchanged"
    );
    bake_in_place(twins.fresh.path(), &["--no-cache"], what);
    assert!(
        chunk_files(twins.cached.path(), SPACE) == chunk_files(twins.fresh.path(), SPACE),
        "{what}: the chunk files differ from a bake without cache"
    );
    assert!(
        bake_in_place(twins.cached.path(), &[], what),
        "{what}: the bake after it should find the world as it left it"
    );
}

#[test]
fn a_world_as_its_last_bake_left_it_is_known_and_no_edit_is_missed() {
    let twins = Twins::new();
    // An earlier res path that holds nothing yet: a model put there later
    // is found before the one the bake read.
    let settings = String::from_utf8(twins.read("bake.xml")).unwrap();
    let two_roots = replaced_once(
        &settings,
        "<path>\t.\t</path>",
        "<path>\toverride\t</path>\n\t\t<path>\t.\t</path>",
    );
    twins.write("bake.xml", two_roots.as_bytes());
    for dir in [twins.cached.path(), twins.fresh.path()] {
        std::fs::create_dir_all(dir.join("override/sets")).unwrap();
    }
    assert!(!bake_in_place(twins.cached.path(), &[], "the first bake"));
    bake_in_place(twins.fresh.path(), &["--no-cache"], "the first bake");
    let baked = chunk_files(twins.cached.path(), SPACE);
    assert!(bake_in_place(twins.cached.path(), &[], "nothing changed"));
    assert!(
        bake_in_place(twins.cached.path(), &["--check"], "--check"),
        "--check on an unchanged world exits 0 without loading it"
    );
    assert!(baked == chunk_files(twins.cached.path(), SPACE));
    // Other options, another record: loaded and baked.
    assert!(!bake_in_place(
        twins.cached.path(),
        &["--dry-run", "--height-bias", "0.2"],
        "other options"
    ));
    let chunk = format!("{SPACE}/{}.chunk", CHUNKS[0]);
    edited_and_rebaked(&twins, "a chunk edited, its size and time kept", |dir| {
        let path = dir.join(&chunk);
        let modified = std::fs::metadata(&path).unwrap().modified().unwrap();
        let text = String::from_utf8(std::fs::read(&path).unwrap()).unwrap();
        let models = model_elements(&text);
        let element = &text[models[0].clone()];
        let row = element.find("<row3>\t").unwrap() + "<row3>\t".len();
        // One digit of the translation changed: the same length.
        let at = models[0].start + row;
        let digit = text.as_bytes()[at];
        let other = if digit == b'1' { b'2' } else { b'1' };
        let mut bytes = text.into_bytes();
        bytes[at] = other;
        std::fs::write(&path, &bytes).unwrap();
        let file = std::fs::File::options().write(true).open(&path).unwrap();
        file.set_modified(modified).unwrap();
    });
    edited_and_rebaked(&twins, "a model put in an earlier res path", |dir| {
        let from = dir.join("sets/gen/props/pillar.model");
        let to = dir.join("override/sets/gen/props/crate.model");
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        std::fs::copy(from, to).unwrap();
    });
    edited_and_rebaked(&twins, "a chunk deleted", |dir| {
        std::fs::remove_file(dir.join(format!("{SPACE}/{}.chunk", CHUNKS[3]))).unwrap();
    });
    edited_and_rebaked(&twins, "a terrain block raised", |dir| {
        let cdata = dir.join(format!("{SPACE}/{}.cdata", CHUNKS[1]));
        let raised = raised_terrain(&std::fs::read(&cdata).unwrap(), 1.5);
        std::fs::write(&cdata, raised).unwrap();
    });
}

// ---------------------------------------------------------------------------
// Chunks read back from the cache instead of parsed.

/// The scene as the bake uses it, without the keys of the files' bytes
/// (which writing masks changes).
fn scene_text(scene: &shadowcull::scene::Scene) -> String {
    let mut chunks = scene.chunks.clone();
    for chunk in &mut chunks {
        chunk.file_key = None;
    }
    format!(
        "{chunks:?}\n{:?}\n{:?}\n{:?}\n{:?}",
        scene.instances, scene.items, scene.problems, scene.inputs
    )
}

#[test]
fn chunks_read_back_from_the_cache_load_the_scene_parsing_loads_before_and_after_a_bake() {
    use shadowcull::bake::output;
    use shadowcull::cache::{Kind, KindCounts};
    use shadowcull::files::ResPaths;
    use shadowcull::scene::LoadConfig;
    let dir = tempfile::tempdir().unwrap();
    let settings = small_settings(dir.path());
    let load = LoadConfig::from_settings(&settings);
    let chunk_counts = |cache: &Cache| -> KindCounts {
        let counts = cache.counts().into_iter().find(|(k, _)| *k == Kind::Chunk);
        counts.unwrap().1
    };
    let open = || Cache::open(dir.path().join("cache"), u64::MAX, content_key(b"a build"));
    let first = open();
    let parsed = load_unvouched(&load, Some(&first)).unwrap();
    let chunks = parsed.chunks.len() as u64;
    assert_eq!(chunk_counts(&first).written, chunks);
    let uncached = load_unvouched(&load, None).unwrap();
    assert_eq!(scene_text(&parsed), scene_text(&uncached));

    // Read back: the same scene, and nothing parsed.
    let second = open();
    let read_back = load_unvouched(&load, Some(&second)).unwrap();
    assert_eq!(chunk_counts(&second).reused, chunks);
    assert_eq!(scene_text(&read_back), scene_text(&parsed));

    // A dry run writes nothing: it stores no entry for bytes no file
    // holds.
    let config = BakeConfig::from_settings(&settings);
    let res_paths = ResPaths::new(settings.res_paths.clone());
    let mut dry = bake::bake(&read_back, &config, &Silent).unwrap();
    let to = output::Destination {
        out_dir: None,
        bytes: output::OutputBytes::Dropped,
    };
    let (outputs, _) =
        output::chunk_outputs_cached(&read_back, &mut dry, &res_paths, to, &Silent, Some(&second))
            .unwrap();
    assert!(outputs.iter().all(|o| o.changed), "every chunk gains masks");
    let cache_dir = dir.path().join("cache");
    assert_eq!(entries(&cache_dir, "chunk").len() as u64, chunks);
    assert!(entries(&cache_dir, "output").is_empty());

    // A bake in place writes masks into every chunk; the entries it stores
    // for the bytes it wrote load the scene a parse of them loads.
    let mut result = bake::bake(&read_back, &config, &Silent).unwrap();
    let to = output::Destination {
        out_dir: None,
        bytes: output::OutputBytes::Kept,
    };
    let (outputs, _) = output::chunk_outputs_cached(
        &read_back,
        &mut result,
        &res_paths,
        to,
        &Silent,
        Some(&second),
    )
    .unwrap();
    assert!(outputs.iter().any(|o| o.changed), "masks written");
    output::write_outputs(&outputs, &Silent).unwrap();
    let changed = outputs.iter().filter(|o| o.changed).count() as u64;
    assert_eq!(
        entries(&dir.path().join("cache"), "chunk").len() as u64,
        chunks,
        "the entries of the {changed} chunks' replaced bytes are gone"
    );
    let third = open();
    let after = load_unvouched(&load, Some(&third)).unwrap();
    assert_eq!(chunk_counts(&third).reused, chunks, "nothing parsed again");
    let parsed_after = load_unvouched(&load, None).unwrap();
    assert_eq!(scene_text(&after), scene_text(&parsed_after));
    for (chunk, output) in after.chunks.iter().zip(&outputs) {
        assert_eq!(chunk.file_key, output.key, "{}", chunk.name);
    }
}

/// The `small` world written to `dir`, its settings read.
fn small_settings(dir: &Path) -> shadowcull::formats::bake_settings::BakeSettings {
    let settings_path = small_world(dir);
    let bytes = std::fs::read(&settings_path).unwrap();
    shadowcull::formats::bake_settings::from_bytes(&bytes, &settings_path).unwrap()
}

/// A load that no record vouches for.
fn load_unvouched(
    load: &shadowcull::scene::LoadConfig,
    cache: Option<&Cache>,
) -> shadowcull::Result<shadowcull::scene::Scene> {
    let known = shadowcull::cache::KnownFiles::default();
    shadowcull::scene::load_scene_cached(load, &Silent, cache, &known)
}

#[test]
fn a_chunk_file_whose_stamp_a_record_vouches_for_is_not_read() {
    use shadowcull::cache::{KnownFiles, RACY_NANOSECONDS};
    use shadowcull::files::stamp;
    use shadowcull::scene::{load_scene_cached, LoadConfig};
    let dir = tempfile::tempdir().unwrap();
    let load = LoadConfig::from_settings(&small_settings(dir.path()));
    let cache = Cache::open(dir.path().join("cache"), u64::MAX, content_key(b"a build"));
    let parsed = load_unvouched(&load, Some(&cache)).unwrap();
    // A record that says chunk `a` holds chunk `b`'s bytes: believed only
    // if `a` is not read.
    let (a, b) = (&parsed.chunks[0], &parsed.chunks[1]);
    assert_ne!(a.instances.len(), b.instances.len(), "chunks told apart");
    let a_stamp = stamp(&a.file).unwrap();
    let b_key = content_key(&std::fs::read(&b.file).unwrap());
    let vouch = |at: u64| KnownFiles::new([(a.file.as_path(), a_stamp, b_key)].into_iter(), at);
    let after_the_margin = a_stamp.latest_ns() + RACY_NANOSECONDS + 1;
    let trusting = load_scene_cached(&load, &Silent, Some(&cache), &vouch(after_the_margin));
    let trusting = trusting.unwrap();
    assert_eq!(trusting.chunks[0].instances.len(), b.instances.len());
    assert_eq!(trusting.chunks[0].file_key, Some(b_key));

    // Stamped too close to the record, or written since: read.
    let racy = load_scene_cached(&load, &Silent, Some(&cache), &vouch(after_the_margin - 2));
    assert_eq!(scene_text(&racy.unwrap()), scene_text(&parsed));
    std::fs::write(&a.file, std::fs::read(&a.file).unwrap()).unwrap();
    let rewritten = load_scene_cached(&load, &Silent, Some(&cache), &vouch(after_the_margin));
    assert_eq!(scene_text(&rewritten.unwrap()), scene_text(&parsed));
}

#[test]
fn terrain_read_back_is_decoded_where_read_and_bakes_as_decoded_terrain() {
    use shadowcull::bake::ground::Ground;
    use shadowcull::cache::{Kind, KindCounts};
    use shadowcull::scene::{keys, LoadConfig};
    let dir = tempfile::tempdir().unwrap();
    let settings = small_settings(dir.path());
    let load = LoadConfig::from_settings(&settings);
    let open = || Cache::open(dir.path().join("cache"), u64::MAX, content_key(b"a build"));
    let terrain_counts = |cache: &Cache| -> KindCounts {
        let counts = cache
            .counts()
            .into_iter()
            .find(|(k, _)| *k == Kind::Terrain);
        counts.unwrap().1
    };
    let first = open();
    let decoded = load_unvouched(&load, Some(&first)).unwrap();
    let blocks = decoded.terrain.len();
    assert!(blocks >= 4, "{blocks} blocks");
    // One entry holds the space's ranges.
    assert_eq!(terrain_counts(&first).written, 1);
    assert!(decoded.terrain.iter().all(|b| b.is_decoded()));

    // Read back: every block's range from the cache, no sample decoded,
    // and the entry, still true, not written again.
    let second = open();
    let read_back = load_unvouched(&load, Some(&second)).unwrap();
    assert_eq!(terrain_counts(&second).reused, 1);
    assert_eq!(terrain_counts(&second).written, 0);
    assert!(read_back.terrain.iter().all(|b| !b.is_decoded()));
    assert_eq!(scene_text(&read_back), scene_text(&decoded));
    for (a, b) in decoded.terrain.iter().zip(&read_back.terrain) {
        assert_eq!((a.bounds(), a.cells()), (b.bounds(), b.cells()));
        assert_eq!(keys::block_key(a), keys::block_key(b));
    }

    // The below-ground test over one block decodes the blocks near the
    // point (the ceilings' squares reach a neighbour's edge), no other.
    let ground = Ground::new(&read_back).unwrap();
    let (lo, hi) = read_back.terrain[0].bounds();
    let centre = (lo + hi) / 2.0;
    let probe = DVec3::new(centre.x, lo.y - 1.0, centre.z);
    let expected = Ground::new(&decoded).unwrap().is_below(probe, 0.0);
    assert_eq!(ground.is_below(probe, 0.0), expected);
    assert!(read_back.terrain[0].is_decoded());
    let others = read_back.terrain[1..]
        .iter()
        .filter(|b| b.is_decoded())
        .count();
    assert_eq!(
        others, 0,
        "a point in the middle of block 0 decodes it alone"
    );

    // A bake of the read-back terrain decides what one of decoded terrain
    // does, and reads the same samples.
    let config = BakeConfig::from_settings(&settings);
    let baked = bake::bake(&decoded, &config, &Silent).unwrap();
    let read_back_baked = bake::bake(&read_back, &config, &Silent).unwrap();
    assert_eq!(baked.masks, read_back_baked.masks);
    for (a, b) in decoded.terrain.iter().zip(&read_back.terrain) {
        if b.is_decoded() {
            assert_eq!(a.grid().heights.get(), b.grid().heights.get());
        }
    }
}
