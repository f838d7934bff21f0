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
    let session = BakeCache::new(cache, &bake_world, SceneKeys::of(&world.scene), left_out);
    bake::bake_cached(&bake_world, config, &Silent, &session).expect("cached bake")
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
    // A light from −x skimming under a terrain block at 10 m: its rays meet
    // two boxes under the block without crossing it (they enter under it
    // from the world's edge), so the block is not in their cells' reach,
    // but the below-ground test reads it for their hits. A hole over the
    // boxes makes them count.
    let build = |hole: bool| {
        let mut world = World::new(2, 1);
        let holes =
            move |x: f64, z: f64| hole && (2.0..12.0).contains(&x) && (4.0..7.0).contains(&z);
        world.terrain_with_holes((1, 0), 16, |_, _| 10.0, holes);
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
        before: (World::new(2, 2), sun(0.1)),
        after: (build(), sun(0.1)),
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
    // grid's origin (the world's low corner) moves by 0.1 m.
    let build = |shift: f32| {
        let mut world = World::new(9, 1);
        let far = 9.0 * CHUNK as f32;
        block(
            &mut world,
            (0, 0),
            [shift, -1.0, 0.0],
            [shift + 0.1, 10.0, 16.0],
        );
        block(
            &mut world,
            (8, 0),
            [far - 0.1 + shift, -1.0, 0.0],
            [far + shift, 10.0, 16.0],
        );
        block(&mut world, (4, 0), [72.1, 0.5, 2.0], [72.15, 3.0, 14.0]);
        put(
            &mut world,
            (4, 0),
            quad_up(70.0, 1.0, 75.0, 15.0, 0.0),
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
    // id. Receiver-only boxes in another cell, earlier in id order, shift
    // its id.
    let build = |dummies: usize| {
        let mut world = World::new(17, 1);
        block(&mut world, (0, 0), [0.0, -1.0, 0.0], [0.1, 5.0, 0.1]);
        block(&mut world, (16, 0), [271.9, -1.0, 15.9], [272.0, 5.0, 16.0]);
        for n in 0..dummies {
            let x = 1.0 + n as f32 * 0.5;
            let dummy = cube(Vec3::new(x, 0.0, 1.0), Vec3::new(x + 0.1, 0.1, 1.1));
            put(&mut world, (0, 0), dummy, false);
        }
        put(
            &mut world,
            (16, 0),
            quad_up(260.62, 5.62, 261.08, 6.08, 2.0),
            true,
        );
        put(
            &mut world,
            (16, 0),
            quad_up(260.0, 5.0, 260.85, 7.0, 1.0),
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
