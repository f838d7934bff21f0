//! One micro world per rule of docs/contract.md §4. Expected masks come from the design
//! of each world (explained beside it); `micro::run` also checks every world
//! against the brute-force oracle.

use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::formats::bake_settings::{FaceCulling, LightKind, LightSettings};

const DOWN: DVec3 = DVec3::new(0.0, -1.0, 0.0);

fn flat(world: &mut World, grid: (i32, i32)) {
    world.terrain(grid, |_, _| 0.0);
}

fn one(world: &mut World, triangles: Vec<[Vec3; 3]>, flags: Flags) -> usize {
    world.model(Mesh {
        groups: vec![(triangles, flags)],
    })
}

fn place(world: &mut World, model: usize) -> usize {
    world.place((0, 0), &[model], DMat4::IDENTITY, true)
}

#[test]
fn occluded_caster_is_culled_and_its_occluder_kept() {
    // Box A (4..8 at y 2..3) hides box B (5..7 at y 0.5..1) completely from a
    // light straight down; flat terrain below both. A: first hit, terrain
    // behind → useful. B: never a first hit → culled. Terrain: first hit
    // only where nothing is above it, and nothing is behind it → culled.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let a = one(
        &mut world,
        cube(Vec3::new(4.0, 2.0, 4.0), Vec3::new(8.0, 3.0, 8.0)),
        OPAQUE,
    );
    let b = one(
        &mut world,
        cube(Vec3::new(5.0, 0.5, 5.0), Vec3::new(7.0, 1.0, 7.0)),
        OPAQUE,
    );
    let a = place(&mut world, a);
    let b = place(&mut world, b);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, a), vec![1]);
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
}

#[test]
fn caster_with_nothing_behind_is_culled_unless_faces_are_kept() {
    // A box over the void: the top face is hit, the bottom face is a back
    // face for a light from above. With back-face culling one crossing →
    // culled; with `none` both faces count → useful.
    let mut world = World::new(1, 1);
    let m = one(
        &mut world,
        cube(Vec3::new(4.0, 2.0, 4.0), Vec3::new(8.0, 3.0, 8.0)),
        OPAQUE,
    );
    let i = place(&mut world, m);
    let mut settings = config(vec![directional(DOWN, 0.25)]);
    assert_eq!(instance_masks(&run(&world, &settings), &world, i), vec![0]);
    settings.face_culling = FaceCulling::None;
    assert_eq!(instance_masks(&run(&world, &settings), &world, i), vec![1]);
}

#[test]
fn alpha_tested_canopy_does_not_cull_what_is_below() {
    // Canopy card (alpha-tested, double-sided) at y 5 over 2..10 covers a box
    // (4..6, y 1..2) entirely; flat terrain. All pass: canopy first, box or
    // terrain behind → canopy useful. Opaque pass: canopy gone, box first,
    // terrain behind → box useful too. Terrain never has anything behind.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let canopy = one(&mut world, quad_up(2.0, 2.0, 10.0, 10.0, 5.0), CANOPY);
    let bush = one(
        &mut world,
        cube(Vec3::new(4.0, 1.0, 4.0), Vec3::new(6.0, 2.0, 6.0)),
        OPAQUE,
    );
    let canopy = place(&mut world, canopy);
    let bush = place(&mut world, bush);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, canopy), vec![1]);
    assert_eq!(instance_masks(&result, &world, bush), vec![1]);
    assert_eq!(terrain_mask(&result, 0), 0);
    assert_eq!(result.lights[0].passes, 2);
}

#[test]
fn object_sunk_into_terrain_does_not_make_the_terrain_useful() {
    // A box 1..3 m below flat terrain: its hits are below H − heightBias and
    // ignored, so the terrain has nothing behind it. With a height bias
    // larger than the depth the box counts again and the terrain becomes
    // useful (the box stays culled: the terrain is in front of it).
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let m = one(
        &mut world,
        cube(Vec3::new(4.0, -3.0, 4.0), Vec3::new(8.0, -1.0, 8.0)),
        OPAQUE,
    );
    let sunk = place(&mut world, m);
    let mut settings = config(vec![directional(DOWN, 0.25)]);
    let result = run(&world, &settings);
    assert_eq!(terrain_mask(&result, 0), 0);
    assert_eq!(instance_masks(&result, &world, sunk), vec![0]);
    settings.height_bias = 5.0;
    let result = run(&world, &settings);
    assert_eq!(terrain_mask(&result, 0), 1);
    assert_eq!(instance_masks(&result, &world, sunk), vec![0]);
}

#[test]
fn single_sided_quad_seen_from_behind_versus_double_sided() {
    // A quad at y 3 facing down, terrain below, light from above: its only
    // face is a back face → ignored → culled. Double-sided: hit, terrain
    // behind → useful.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let down = one(
        &mut world,
        flipped(quad_up(4.0, 4.0, 8.0, 8.0, 3.0)),
        OPAQUE,
    );
    let two = one(
        &mut world,
        flipped(quad_up(10.0, 10.0, 14.0, 14.0, 3.0)),
        TWO_SIDED,
    );
    let down = place(&mut world, down);
    let two = place(&mut world, two);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, down), vec![0]);
    assert_eq!(instance_masks(&result, &world, two), vec![1]);
}

#[test]
fn mirrored_instance_keeps_its_facing() {
    // An up-facing quad placed with a mirror (x → −x) over terrain. Its
    // transformed winding points down, but the engine flips the cull mode of
    // mirrored models, so it still faces the light: useful. The same quad
    // mirrored twice (x and z: determinant +1) is not flipped and useful too.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let q = one(&mut world, quad_up(-2.0, -2.0, 2.0, 2.0, 3.0), OPAQUE);
    let mirror = DMat4::from_translation(DVec3::new(5.0, 0.0, 5.0))
        * DMat4::from_scale(DVec3::new(-1.0, 1.0, 1.0));
    let twice = DMat4::from_translation(DVec3::new(11.0, 0.0, 11.0))
        * DMat4::from_scale(DVec3::new(-1.0, 1.0, -1.0));
    let mirrored = world.place((0, 0), &[q], mirror, true);
    let rotated = world.place((0, 0), &[q], twice, true);
    assert!(world.scene.instances[mirrored].mirrored);
    assert!(!world.scene.instances[rotated].mirrored);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, mirrored), vec![1]);
    assert_eq!(instance_masks(&result, &world, rotated), vec![1]);
}

#[test]
fn coplanar_casters_tie() {
    // Two coplanar quads (separate instances) over the void: each ray hits
    // both at the same depth: two fragments under LEQUAL → both useful, as
    // the rasterized method would say. A decal on a box top (void below):
    // the box alone is one crossing, with the decal tied in front both are
    // useful where the decal lies.
    let mut world = World::new(1, 1);
    let q1 = one(&mut world, quad_up(1.0, 1.0, 5.0, 5.0, 3.0), OPAQUE);
    let q2 = one(&mut world, quad_up(1.0, 1.0, 5.0, 5.0, 3.0), OPAQUE);
    let wall = one(
        &mut world,
        cube(Vec3::new(8.0, 1.0, 8.0), Vec3::new(14.0, 3.0, 14.0)),
        OPAQUE,
    );
    let decal = one(&mut world, quad_up(10.0, 10.0, 12.0, 12.0, 3.0), OPAQUE);
    let q1 = place(&mut world, q1);
    let q2 = place(&mut world, q2);
    let wall = place(&mut world, wall);
    let decal = place(&mut world, decal);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, q1), vec![1]);
    assert_eq!(instance_masks(&result, &world, q2), vec![1]);
    assert_eq!(instance_masks(&result, &world, wall), vec![1]);
    assert_eq!(instance_masks(&result, &world, decal), vec![1]);
}

#[test]
fn receiver_only_instance_receives_but_never_casts() {
    // A receiver-only box R (castsShadow false) on the void, a quad Q above
    // part of it. Q: first hit with R behind → useful. R: mask 0 always.
    // Without R, Q has nothing behind it → culled.
    let mut world = World::new(1, 1);
    let r = one(
        &mut world,
        cube(Vec3::new(4.0, 0.0, 4.0), Vec3::new(8.0, 1.0, 8.0)),
        OPAQUE,
    );
    let q = one(&mut world, quad_up(5.0, 5.0, 7.0, 7.0, 3.0), OPAQUE);
    let receiver = world.place((0, 0), &[r], DMat4::IDENTITY, false);
    let quad = place(&mut world, q);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, receiver), vec![0]);
    assert_eq!(instance_masks(&result, &world, quad), vec![1]);

    let mut alone = World::new(1, 1);
    let q = one(&mut alone, quad_up(5.0, 5.0, 7.0, 7.0, 3.0), OPAQUE);
    let quad = place(&mut alone, q);
    let result = run(&alone, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &alone, quad), vec![0]);
}

#[test]
fn receiver_in_the_neighbouring_chunk() {
    // A box at the +x edge of chunk (0,0), y 3..4, no terrain under it; the
    // only terrain is chunk (1,0). Light travelling +x and down at 45°: rays
    // through the box land on chunk (1,0)'s terrain → useful.
    let mut world = World::new(2, 1);
    flat(&mut world, (1, 0));
    let m = one(
        &mut world,
        cube(Vec3::new(14.0, 3.0, 6.0), Vec3::new(15.0, 4.0, 10.0)),
        OPAQUE,
    );
    let b = place(&mut world, m);
    let result = run(
        &world,
        &config(vec![directional(DVec3::new(1.0, -1.0, 0.0), 0.25)]),
    );
    assert_eq!(instance_masks(&result, &world, b), vec![1]);
    // Straight down, nothing is under it in its own chunk: culled.
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
}

#[test]
fn terrain_shadowing_itself() {
    // A 4 m hill in the middle of the block, light grazing from −x at about
    // 17° below the horizon: rays hit the hill's lit slope and, further on,
    // the ground beyond it → the block is useful. A flat block under the
    // same light never has anything behind its one crossing → culled.
    let hill = |x: f64, z: f64| 4.0 * (-((x - 8.0).powi(2) + (z - 8.0).powi(2)) / 6.0).exp();
    let light = directional(DVec3::new(1.0, -0.3, 0.0), 0.25);
    let mut world = World::new(1, 1);
    world.terrain((0, 0), hill);
    assert_eq!(
        terrain_mask(&run(&world, &config(vec![light.clone()])), 0),
        1
    );
    let mut flat_world = World::new(1, 1);
    flat(&mut flat_world, (0, 0));
    assert_eq!(terrain_mask(&run(&flat_world, &config(vec![light])), 0), 0);
}

#[test]
fn multi_group_model_masks_each_group() {
    // One model: group 0 a quad at y 3 over 4..8, group 1 a box (5..7, y
    // 1..2) under it; terrain. Group 0 useful, group 1 never first → culled.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let m = world.model(Mesh {
        groups: vec![
            (quad_up(4.0, 4.0, 8.0, 8.0, 3.0), OPAQUE),
            (
                cube(Vec3::new(5.0, 1.0, 5.0), Vec3::new(7.0, 2.0, 7.0)),
                OPAQUE,
            ),
        ],
    });
    let i = place(&mut world, m);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, i), vec![1, 0]);
}

#[test]
fn two_resource_instance_masks_parts_in_order() {
    // One instance with two <resource> parts: a quad (part 0) over a box
    // (part 1), terrain below: [1, 0], the instance mask is their OR = 1.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let top = one(&mut world, quad_up(4.0, 4.0, 8.0, 8.0, 3.0), OPAQUE);
    let under = one(
        &mut world,
        cube(Vec3::new(5.0, 1.0, 5.0), Vec3::new(7.0, 2.0, 7.0)),
        OPAQUE,
    );
    let i = world.place((0, 0), &[top, under], DMat4::IDENTITY, true);
    let result = run(&world, &config(vec![directional(DOWN, 0.25)]));
    assert_eq!(instance_masks(&result, &world, i), vec![1, 0]);
}

fn spot(name: &str, position: DVec3, direction: DVec3) -> LightSettings {
    LightSettings {
        name: name.into(),
        kind: LightKind::Spot {
            position,
            direction: direction.normalize(),
            fov_degrees: 60.0,
            near: 0.1,
            far: 50.0,
            resolution: 64,
        },
    }
}

#[test]
fn spot_and_point_lights_see_only_what_they_reach() {
    // Box A under both lights on terrain; box B (chunk (1,1), far corner) is
    // outside the spot's 60° cone and beyond the point light's far = 30 m.
    let mut world = World::new(2, 2);
    flat(&mut world, (0, 0));
    flat(&mut world, (1, 1));
    let a = one(
        &mut world,
        cube(Vec3::new(6.0, 1.0, 6.0), Vec3::new(10.0, 2.0, 10.0)),
        OPAQUE,
    );
    let b = one(
        &mut world,
        cube(Vec3::new(12.0, 1.0, 12.0), Vec3::new(14.0, 2.0, 14.0)),
        OPAQUE,
    );
    let a = place(&mut world, a);
    let b = world.place((1, 1), &[b], DMat4::IDENTITY, true);
    let point = LightSettings {
        name: "point".into(),
        kind: LightKind::Point {
            position: DVec3::new(8.0, 6.0, 8.0),
            near: 0.1,
            far: 30.0,
            resolution: 32,
        },
    };
    let result = run(
        &world,
        &config(vec![spot("spot", DVec3::new(8.0, 10.0, 8.0), DOWN), point]),
    );
    assert_eq!(instance_masks(&result, &world, a), vec![0b11]);
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
}

#[test]
fn light_bits_follow_light_order() {
    // Three boxes on terrain, three spots, spot i straight above box i only:
    // box i's mask is exactly bit i.
    let mut world = World::new(3, 1);
    let mut boxes = Vec::new();
    let mut lights = Vec::new();
    for i in 0..3 {
        flat(&mut world, (i, 0));
        let m = one(
            &mut world,
            cube(Vec3::new(6.0, 1.0, 6.0), Vec3::new(10.0, 2.0, 10.0)),
            OPAQUE,
        );
        boxes.push(world.place((i, 0), &[m], DMat4::IDENTITY, true));
        let x = i as f64 * CHUNK + 8.0;
        lights.push(LightSettings {
            name: format!("spot{i}"),
            kind: LightKind::Spot {
                position: DVec3::new(x, 6.0, 8.0),
                direction: DOWN,
                fov_degrees: 40.0,
                near: 0.1,
                far: 20.0,
                resolution: 32,
            },
        });
    }
    let result = run(&world, &config(lights));
    for (i, b) in boxes.iter().enumerate() {
        assert_eq!(instance_masks(&result, &world, *b), vec![1 << i], "box {i}");
    }
}

#[test]
fn light_whose_frustum_holds_nothing_is_skipped_and_reported() {
    // A spot light pointing up, away from the only box: nothing in reach,
    // no rays traced, the box keeps mask 0, `skipped` says why.
    let mut world = World::new(1, 1);
    let m = one(
        &mut world,
        cube(Vec3::new(4.0, 0.0, 4.0), Vec3::new(8.0, 1.0, 8.0)),
        OPAQUE,
    );
    let b = place(&mut world, m);
    let up = spot("up", DVec3::new(6.0, 5.0, 6.0), DVec3::Y);
    let result = run(&world, &config(vec![up]));
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
    assert_eq!(result.lights[0].rays, 0);
    assert!(
        result
            .skipped
            .iter()
            .any(|s| s.why.contains("holds no geometry")),
        "{:?}",
        result.skipped
    );
}

#[test]
fn empty_world_skips_directional_lights_and_33_lights_are_refused() {
    let world = World::new(1, 1);
    let result = run(&world, &config(vec![directional(DOWN, 1.0)]));
    assert!(result.lights.is_empty());
    assert!(
        result.skipped.iter().any(|s| s.what.contains("sun")),
        "{:?}",
        result.skipped
    );
    let lights = (0..33).map(|_| directional(DOWN, 1.0)).collect();
    let err = shadowcull::bake::bake(&world.scene, &config(lights), &shadowcull::bake::Silent)
        .unwrap_err();
    assert!(err.to_string().contains("at most 32"), "{err}");
}

#[test]
fn casters_smaller_than_a_texel_need_supersampling_or_refinement() {
    // 1 m texels over a 16 m block straight down: centres at x, z = k + 0.5.
    // A 15 cm box spanning 0.80..0.95 lies between centres: the plain grid
    // misses it (culled). 2×2 sub-centres (k + 0.25, k + 0.75) miss it too;
    // 4×4 (k + 0.125 … k + 0.875) hit it at 0.875 → useful (terrain
    // behind). Refinement aims rays at its own faces → useful as well.
    let mut world = World::new(1, 1);
    flat(&mut world, (0, 0));
    let m = one(
        &mut world,
        cube(Vec3::new(0.8, 1.0, 0.8), Vec3::new(0.95, 1.2, 0.95)),
        OPAQUE,
    );
    let small = place(&mut world, m);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, small),
        vec![0]
    );
    settings.supersample = 2;
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, small),
        vec![0]
    );
    settings.supersample = 4;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, small), vec![1]);
    assert_eq!(result.lights[0].rays, 16 * 16 * 16);
    settings.supersample = 1;
    settings.refine_samples = 8;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, small), vec![1]);
    // Refinement rays go only to casters the grid did not prove useful:
    // the box (8 samples) and the terrain block (8 samples), never useful.
    assert_eq!(result.lights[0].refine_rays, 16);
    assert_eq!(terrain_mask(&result, 0), 0);
}
