//! No missing shadow at any shadow-map offset. Designed worlds
//! for the filter margin, refinement and the conservative mode (expected
//! masks from each world's design, explained beside it; `micro::run` also
//! checks the brute-force oracle), and seeded random worlds against the
//! union of many randomly offset dense bakes.

use crate::bake_world::{random_light, random_world};
use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::bake::{self, BakeConfig, GridMode, Silent};
use shadowcull::formats::bake_settings::{FaceCulling, LightKind, LightSettings};
use shadowcull::rng::Rng;

const DOWN: DVec3 = DVec3::new(0.0, -1.0, 0.0);

fn one(world: &mut World, triangles: Vec<[Vec3; 3]>, flags: Flags) -> usize {
    world.model(Mesh {
        groups: vec![(triangles, flags)],
    })
}

/// A box caster at x, z 2.1..2.9 (y 2..3) and a receiver-only box whose x
/// starts `gap` texels further (1 m texels, light straight down, no
/// terrain). The world's bounds start at a box edge, so each box lies
/// inside one texel column: the caster's texel has nothing behind it.
fn caster_beside_receiver(gap: f32) -> (World, usize) {
    let mut world = World::new(1, 1);
    let caster = one(
        &mut world,
        cube(Vec3::new(2.1, 2.0, 2.1), Vec3::new(2.9, 3.0, 2.9)),
        OPAQUE,
    );
    let receiver = one(
        &mut world,
        cube(
            Vec3::new(2.1 + gap, 0.0, 2.1),
            Vec3::new(2.9 + gap, 1.0, 2.9),
        ),
        OPAQUE,
    );
    let c = world.place((0, 0), &[caster], DMat4::IDENTITY, true);
    world.place((0, 0), &[receiver], DMat4::IDENTITY, false);
    (world, c)
}

#[test]
fn filter_margin_keeps_a_caster_whose_receiver_is_one_texel_beside_it() {
    let (world, caster) = caster_beside_receiver(1.0);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    // K = 0: the caster's texel holds one crossing (its top face; the
    // bottom is a back face): nothing behind, culled.
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, caster),
        vec![0]
    );
    // K = 1: the receiver's texel is in the caster's neighbourhood and its
    // top (y 1) lies behind the caster's depth (y 3): kept.
    settings.filter_radius = 1;
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, caster),
        vec![1]
    );
    // With 2×2 supersampling the neighbourhood is still one texel wide.
    settings.supersample = 2;
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, caster),
        vec![1]
    );
}

#[test]
fn filter_margin_reaches_k_texels_and_no_further() {
    let (world, caster) = caster_beside_receiver(2.0);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    settings.filter_radius = 1;
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, caster),
        vec![0]
    );
    settings.filter_radius = 2;
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, caster),
        vec![1]
    );
}

#[test]
fn filter_margin_needs_the_receiver_behind_not_in_front() {
    // The receiver-only box beside the caster is now above it (y 4..5):
    // at its texel it is in front of the caster's depth, so it does not
    // receive the caster's shadow; culled at any K.
    let mut world = World::new(1, 1);
    let caster = one(
        &mut world,
        cube(Vec3::new(2.1, 2.0, 2.1), Vec3::new(2.9, 3.0, 2.9)),
        OPAQUE,
    );
    let above = one(
        &mut world,
        cube(Vec3::new(3.1, 4.0, 2.1), Vec3::new(3.9, 5.0, 2.9)),
        OPAQUE,
    );
    let c = world.place((0, 0), &[caster], DMat4::IDENTITY, true);
    world.place((0, 0), &[above], DMat4::IDENTITY, false);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    settings.filter_radius = 2;
    assert_eq!(instance_masks(&run(&world, &settings), &world, c), vec![0]);
}

/// The 15 cm box of `bake_rules::casters_smaller_than_a_texel_need_…`:
/// 1 m texels straight down over a flat 16 m block; the box spans
/// 0.80..0.95 in x and z, between the texel centres 0.5 and 1.5.
fn sliver_world() -> (World, usize) {
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let m = one(
        &mut world,
        cube(Vec3::new(0.8, 1.0, 0.8), Vec3::new(0.95, 1.2, 0.95)),
        OPAQUE,
    );
    let small = world.place((0, 0), &[m], DMat4::IDENTITY, true);
    (world, small)
}

#[test]
fn a_caster_between_texel_centres_is_kept_by_conservative_and_refine() {
    let (world, small) = sliver_world();
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    // The plain grid misses it: no centre lands on it.
    assert_eq!(
        instance_masks(&run(&world, &settings), &world, small),
        vec![0]
    );
    // Its beam (texel 0..1) meets it, terrain lies behind, nothing nearer.
    settings.grid_mode = GridMode::Conservative;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, small), vec![1]);
    // The flat terrain has nothing behind it anywhere: still culled (the
    // conservative mode is not "keep everything").
    assert_eq!(terrain_mask(&result, 0), 0);
    // Refinement's footprint lattice alone (no surface points) finds it:
    // ×8 lattice points at k + 0.8125 and 0.9375 lie on the box.
    settings.grid_mode = GridMode::Centres;
    settings.refine_density = 8;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, small), vec![1]);
    let light = &result.lights[0];
    assert!(light.refine_rays > 0);
    // The report says how much of the tracing was refinement's.
    assert!(light.refine_seconds > 0.0 && light.refine_seconds <= light.trace_seconds);
    assert_eq!(terrain_mask(&result, 0), 0);
}

#[test]
fn a_card_between_texel_centres_under_spot_and_point_lights_is_kept_by_the_outline_lattice() {
    // A 15 cm card facing up (x, z 0.80..0.95 at y 1.2, centre 0.875) over
    // flat terrain, under a spot light and a point light 10 m above and
    // 0.55 m short of its centre in x and z, looking straight down (90°, 64
    // texels a side; the point light's −y face is the same view; both
    // image axes lie along world x and z). 8.8 m down, the view's texel
    // edges lie 8.8 / 32 m apart, and the card's centre sits 0.55 m =
    // 2 texels off the axis in both: on a texel corner, so the nearest
    // centre rays cross its plane half a texel (0.14 m) off in both axes,
    // beyond the card (0.075 m): the plain grid misses it. Refinement
    // (lattice only) takes the outline way here: the card's edges cross
    // every cell that meets it (a texel is larger than the card), so no
    // probe of an uncrossed cell can find it (top cells' corners lie 2
    // texels away); only the outline cells' points can, ×8 points 1/16
    // texel (1.7 cm) either side of its centre lie on it, with terrain
    // behind: useful. The flat terrain has nothing behind it: culled.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let m = one(&mut world, quad_up(0.8, 0.8, 0.95, 0.95, 1.2), OPAQUE);
    let card = world.place((0, 0), &[m], DMat4::IDENTITY, true);
    let above = DVec3::new(0.875 - 0.55, 10.0, 0.875 - 0.55);
    let lights = vec![
        LightSettings {
            name: "spot".into(),
            kind: LightKind::Spot {
                position: above,
                direction: DOWN,
                fov_degrees: 90.0,
                near: 0.1,
                far: 50.0,
                resolution: 64,
            },
        },
        LightSettings {
            name: "point".into(),
            kind: LightKind::Point {
                position: above,
                near: 0.1,
                far: 50.0,
                resolution: 64,
            },
        },
    ];
    let mut settings = config(lights);
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, card), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
    settings.refine_density = 8;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, card), vec![0b11]);
    assert!(result.lights.iter().all(|l| l.refine_rays > 0));
    assert_eq!(terrain_mask(&result, 0), 0);
}

#[test]
fn probes_that_disagree_split_their_cell_down_to_a_receiver_between_centres() {
    // A closed slab C (y 0.9..1.0) whose +x edge runs 2.5 cm past a 15 cm
    // receiver-only card R (x, z 0.80..0.95 at y 0.5, facing up) under it;
    // no terrain, so C has something behind it only over R. A spot light
    // (90°, 64 texels) looks straight down from 9.5 m above R, 0.59375 m =
    // 2 texels (at R's depth) short of R's centre in x and z: R's centre
    // is on a texel corner, the nearest centre rays pass half a texel
    // (0.15 m) off in both axes, beyond R (0.075 m). The plain grid sees C
    // in front with nothing behind: culled. C is closed (every edge of its
    // hittable triangles is shared), so its footprint has no outline:
    // refinement probes cells at their corners and splits a cell only
    // where the probes disagree on C being in front. Along C's +x edge
    // they do (on C and off it), down to single lattice points, and that
    // edge runs within a lattice step (3.7 cm) of R: a point on R sees C
    // in front with R behind, so C is useful.
    let mut world = World::new(1, 1);
    let c = one(
        &mut world,
        cube(Vec3::new(-0.125, 0.9, -0.125), Vec3::new(0.975, 1.0, 1.875)),
        OPAQUE,
    );
    let r = one(&mut world, quad_up(0.8, 0.8, 0.95, 0.95, 0.5), OPAQUE);
    let c = world.place((0, 0), &[c], DMat4::IDENTITY, true);
    world.place((0, 0), &[r], DMat4::IDENTITY, false);
    let short = 0.59375;
    let spot = LightSettings {
        name: "spot".into(),
        kind: LightKind::Spot {
            position: DVec3::new(0.875 - short, 10.0, 0.875 - short),
            direction: DOWN,
            fov_degrees: 90.0,
            near: 0.1,
            far: 50.0,
            resolution: 64,
        },
    };
    let mut settings = config(vec![spot]);
    assert_eq!(instance_masks(&run(&world, &settings), &world, c), vec![0]);
    settings.refine_density = 8;
    assert_eq!(instance_masks(&run(&world, &settings), &world, c), vec![1]);
}

#[test]
fn a_caster_hidden_behind_a_larger_occluder_is_culled_by_conservative() {
    // Box A (4..8 at y 2..3) covers box B (5..7 at y 0.5..1) from a light
    // straight down, over flat terrain; 0.7 m texels so texel edges cut
    // across both and A's top diagonal crosses texels over B. Every beam
    // over B meets A's top face (two triangles whose union covers B's part
    // of the beam) 2 m nearer: B is hidden in every beam. A is front with
    // terrain behind: kept.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
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
    let a = world.place((0, 0), &[a], DMat4::IDENTITY, true);
    let b = world.place((0, 0), &[b], DMat4::IDENTITY, true);
    let mut settings = config(vec![directional(DOWN, 0.7)]);
    settings.grid_mode = GridMode::Conservative;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, a), vec![1]);
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
    // An alpha-tested occluder hides nothing in the Opaque pass: B kept.
    let mut world2 = World::new(1, 1);
    world2.terrain((0, 0), |_, _| 0.0);
    let canopy = one(
        &mut world2,
        cube(Vec3::new(4.0, 2.0, 4.0), Vec3::new(8.0, 3.0, 8.0)),
        Flags {
            alpha_tested: true,
            double_sided: false,
        },
    );
    let b2 = one(
        &mut world2,
        cube(Vec3::new(5.0, 0.5, 5.0), Vec3::new(7.0, 1.0, 7.0)),
        OPAQUE,
    );
    world2.place((0, 0), &[canopy], DMat4::IDENTITY, true);
    let b2 = world2.place((0, 0), &[b2], DMat4::IDENTITY, true);
    assert_eq!(
        instance_masks(&run(&world2, &settings), &world2, b2),
        vec![1]
    );
    // A receiver-only occluder is not in the shadow map: B kept.
    let mut world3 = World::new(1, 1);
    world3.terrain((0, 0), |_, _| 0.0);
    let roof = one(
        &mut world3,
        cube(Vec3::new(4.0, 2.0, 4.0), Vec3::new(8.0, 3.0, 8.0)),
        OPAQUE,
    );
    let b3 = one(
        &mut world3,
        cube(Vec3::new(5.0, 0.5, 5.0), Vec3::new(7.0, 1.0, 7.0)),
        OPAQUE,
    );
    world3.place((0, 0), &[roof], DMat4::IDENTITY, false);
    let b3 = world3.place((0, 0), &[b3], DMat4::IDENTITY, true);
    assert_eq!(
        instance_masks(&run(&world3, &settings), &world3, b3),
        vec![1]
    );
}

/// `light` with its grid `k` times denser per side.
fn denser(light: &LightSettings, k: f64) -> LightSettings {
    shadowcull::sweep::scale_light(light, k)
}

#[test]
fn conservative_keeps_a_superset_of_randomly_offset_dense_bakes() {
    // Seeded random worlds (terrain, boxes and cards with random flags,
    // receiver-only and sunk placements) under random lights of every kind;
    // the union of ×3 bakes at 6 random sub-texel grid offsets must be kept
    // by the conservative ×1 bake, light by light.
    let mut kinds = [false; 3];
    // (caster, light) pairs the offset bakes need beyond the centre rays:
    // the test has teeth only if some exist.
    let mut beyond_centres = 0;
    for seed in 0..6u64 {
        let world = random_world(seed);
        let mut rng = Rng::new(2000 + seed);
        let centre = DVec3::new(CHUNK, 0.0, CHUNK);
        let lights: Vec<LightSettings> = (0..3).map(|_| random_light(&mut rng, centre)).collect();
        for light in &lights {
            kinds[match light.kind {
                LightKind::Directional { .. } => 0,
                LightKind::Spot { .. } => 1,
                LightKind::Point { .. } => 2,
            }] = true;
        }
        let mut settings = config(lights.clone());
        settings.face_culling =
            [FaceCulling::Back, FaceCulling::Front, FaceCulling::None][seed as usize % 3];
        let conservative = bake::bake(
            &world.scene,
            &BakeConfig {
                grid_mode: GridMode::Conservative,
                ..settings.clone()
            },
            &Silent,
        )
        .unwrap();
        let plain = bake::bake(&world.scene, &settings, &Silent).unwrap();
        let mut union = vec![0u32; conservative.masks.len()];
        for _ in 0..6 {
            let offset = (rng.range(-0.5, 0.5), rng.range(-0.5, 0.5));
            let dense = bake::bake(
                &world.scene,
                &BakeConfig {
                    lights: lights.iter().map(|l| denser(l, 3.0)).collect(),
                    grid_offset: offset,
                    ..settings.clone()
                },
                &Silent,
            )
            .unwrap();
            for (u, m) in union.iter_mut().zip(&dense.masks) {
                *u |= m;
            }
        }
        for (id, (&kept, &needed)) in conservative.masks.iter().zip(&union).enumerate() {
            assert_eq!(
                needed & !kept,
                0,
                "seed {seed}: caster {id} is useful at some offset (lights {needed:b}) but the conservative bake keeps only {kept:b}"
            );
        }
        beyond_centres += union
            .iter()
            .zip(&plain.masks)
            .map(|(u, p)| (u & !p).count_ones())
            .sum::<u32>();
        for (&kept, &centre) in conservative.masks.iter().zip(&plain.masks) {
            assert_eq!(
                centre & !kept,
                0,
                "seed {seed}: conservative lost a centre-ray caster"
            );
        }
        // Not "keep everything": some caster in reach is still culled.
        let real = conservative.casters.real_casters() as u32 * lights.len() as u32;
        let kept: u32 = conservative.masks.iter().map(|m| m.count_ones()).sum();
        assert!(
            kept < real,
            "seed {seed}: conservative kept all {real} pairs"
        );
    }
    assert_eq!(kinds, [true; 3], "every light kind was drawn");
    assert!(
        beyond_centres > 0,
        "no offset bake found anything beyond the centre rays"
    );
    eprintln!("offset bakes needed {beyond_centres} pairs beyond the centre rays");
}

#[test]
fn a_grid_offset_moves_sample_points_within_their_texels() {
    // The sliver box (0.80..0.95) lies in texel 0 of the 1 m grid: the
    // centre ray (0.5) misses it, an offset of +0.4 (0.9) lands on it, and
    // −0.4 (0.1) misses again.
    let (world, small) = sliver_world();
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    settings.grid_offset = (0.4, 0.4);
    let hit = run(&world, &settings);
    settings.grid_offset = (-0.4, -0.4);
    let miss = run(&world, &settings);
    // Which way the grid's u axis runs decides which offset lands on it.
    let masks = (
        instance_masks(&hit, &world, small),
        instance_masks(&miss, &world, small),
    );
    assert!(
        masks == (vec![1], vec![0]) || masks == (vec![0], vec![1]),
        "{masks:?}"
    );
}

#[test]
fn conservative_culls_what_the_terrain_covers() {
    // Box B (5..7, y −2..−1) and below it box C (y −4..−3) are buried under
    // flat terrain. The plain bake drops their hits (below ground). In
    // every beam over B, C could lie behind B, but the terrain (never
    // dropped by the below-ground rule, so a sure occluder) covers B's
    // fragment 1 m nearer: B is culled; C has nothing behind it: culled.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let b = one(
        &mut world,
        cube(Vec3::new(5.0, -2.0, 5.0), Vec3::new(7.0, -1.0, 7.0)),
        OPAQUE,
    );
    let c = one(
        &mut world,
        cube(Vec3::new(5.0, -4.0, 5.0), Vec3::new(7.0, -3.0, 7.0)),
        OPAQUE,
    );
    let b = world.place((0, 0), &[b], DMat4::IDENTITY, true);
    let c = world.place((0, 0), &[c], DMat4::IDENTITY, true);
    let mut settings = config(vec![directional(DOWN, 0.7)]);
    let plain = run(&world, &settings);
    assert_eq!(instance_masks(&plain, &world, b), vec![0]);
    settings.grid_mode = GridMode::Conservative;
    let result = run(&world, &settings);
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
    assert_eq!(instance_masks(&result, &world, c), vec![0]);
}

/// Receiver-only ground (y 0, from x, z 0, so a 1 m grid's centres lie
/// at k + 0.5), an opaque roof R (y 10, from x `roof_from` to 16), a
/// small slab A (x, z 0.6..0.95, y 2) and a group B: a 35 × 10 cm sliver
/// (x 0.6..0.95, z 0.7..0.8, at `sliver_y`) and an 84 m² triangle (y 5)
/// under the roof. A and the sliver lie between texel centres. B's own
/// area-weighted points miss the sliver (0.04 % of its area), so its rays
/// all meet the roof first; A's first two points (z 0.93 and 0.63: the
/// points are fixed per light and caster) miss the sliver, and three of
/// its later ones cross it. Returns the world and R's, A's and B's
/// instances.
fn roof_slab_sliver(roof_from: f32, sliver_y: f32) -> (World, [usize; 3]) {
    let mut world = World::new(1, 1);
    let ground = one(&mut world, quad_up(0.0, 0.0, 16.0, 16.0, 0.0), OPAQUE);
    let roof = one(
        &mut world,
        quad_up(roof_from, 0.0, 16.0, 16.0, 10.0),
        OPAQUE,
    );
    let slab = one(&mut world, quad_up(0.6, 0.6, 0.95, 0.95, 2.0), OPAQUE);
    let mut sliver = quad_up(0.6, 0.7, 0.95, 0.8, sliver_y);
    sliver.push([
        Vec3::new(3.0, 5.0, 1.0),
        Vec3::new(3.0, 5.0, 15.0),
        Vec3::new(15.0, 5.0, 15.0),
    ]);
    let sliver = one(&mut world, sliver, OPAQUE);
    world.place((0, 0), &[ground], DMat4::IDENTITY, false);
    let placed = [roof, slab, sliver].map(|m| world.place((0, 0), &[m], DMat4::IDENTITY, true));
    (world, placed)
}

/// The first masks of `instances`.
fn first_masks<const N: usize>(
    result: &bake::BakeResult,
    world: &World,
    instances: [usize; N],
) -> [u32; N] {
    instances.map(|i| instance_masks(result, world, i)[0])
}

/// A caster shown only through another's surface points: the roof stops
/// at x 2, the sliver (y 2.5) lies over the slab A in the open. A's first
/// two points prove A (ground behind); its later ones that cross the
/// sliver prove B (A and the ground behind), so refinement must go on
/// tracing them once A is proven. The lattice is off: it would find the
/// sliver by itself.
#[test]
fn a_sliver_proven_only_by_another_casters_surface_points_is_kept() {
    let (world, casters) = roof_slab_sliver(2.0, 2.5);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    // The grid: no centre lands on the slab or the sliver; the roof's
    // centres have ground behind.
    assert_eq!(
        first_masks(&run(&world, &settings), &world, casters),
        [1, 0, 0]
    );
    settings.refine_samples = 16;
    let result = run(&world, &settings);
    assert_eq!(first_masks(&result, &world, casters), [1, 1, 1]);
    // Every point of both is traced (32 rays), though the rays after the
    // slab's proof that meet only settled casters may be left out.
    assert_eq!(result.lights[0].refine_rays, 32);
}

/// The same group B with the roof over the whole chunk and the sliver
/// above it (y 12): the roof hides the slab A everywhere. A's first two
/// points meet only the roof, which then surely hides A's other points
/// from A, so they cannot prove A; but three of them cross the sliver,
/// front-most there with the roof behind: they must still be traced, for
/// B.
#[test]
fn a_sliver_proven_only_through_a_hidden_casters_surface_points_is_kept() {
    let (world, casters) = roof_slab_sliver(0.0, 12.0);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    assert_eq!(
        first_masks(&run(&world, &settings), &world, casters),
        [1, 0, 0]
    );
    settings.refine_samples = 16;
    assert_eq!(
        first_masks(&run(&world, &settings), &world, casters),
        [1, 0, 1]
    );
}

/// A caster in two steps, as one group: a low quad (x 2.1..2.9, z
/// 5.1..5.9, y 2) under an opaque shelf S (y 4, the whole chunk; its
/// diagonal x = z, where no point is surely inside, lies away) and a high
/// quad (x 2.6..2.95, z 5.6..5.95, y 6) above it, between texel centres.
/// Its first two points fall on the low step and meet the shelf first;
/// its later points on the high step are front-most with the shelf
/// behind. The shelf lies nearer than the low step but deeper than the
/// high one, so it does not hide those points: the occlusion test must
/// take the caster's nearest depth (its top), not the depth of the step a
/// point lies on, or the caster is lost; so must the check of its whole
/// footprint's lattice.
#[test]
fn a_caster_poking_out_above_its_occluder_is_kept() {
    let mut world = World::new(1, 1);
    let ground = one(&mut world, quad_up(0.0, 0.0, 16.0, 16.0, 0.0), OPAQUE);
    let shelf = one(&mut world, quad_up(0.0, 0.0, 16.0, 16.0, 4.0), OPAQUE);
    let mut steps = quad_up(2.1, 5.1, 2.9, 5.9, 2.0);
    steps.extend(quad_up(2.6, 5.6, 2.95, 5.95, 6.0));
    let steps = one(&mut world, steps, OPAQUE);
    world.place((0, 0), &[ground], DMat4::IDENTITY, false);
    let shelf = world.place((0, 0), &[shelf], DMat4::IDENTITY, true);
    let steps = world.place((0, 0), &[steps], DMat4::IDENTITY, true);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    let masks = |result: &bake::BakeResult| first_masks(result, &world, [shelf, steps]);
    assert_eq!(masks(&run(&world, &settings)), [1, 0]);
    settings.refine_samples = 16;
    assert_eq!(masks(&run(&world, &settings)), [1, 1]);
    // Two surface points (both on the low step) and the footprint
    // lattice, which finds the high step: the shelf the points met must
    // not count as hiding the whole footprint either.
    settings.refine_samples = 2;
    settings.refine_density = 8;
    assert_eq!(masks(&run(&world, &settings)), [1, 1]);
}

/// Refinement's deferred surface points go a chunk of candidates at a time
/// (65 536 points over `refine_samples` casters: 32 at 2 048), each chunk's
/// after its casters' own rays, where they may meet a caster not proven by
/// then. The sliver world of [`roof_slab_sliver`] (roof from x 2), with B's
/// strip 2 cm wide over A and its big part eight 12 × 14 m layers under
/// the roof, so B's own 2 048 points miss the strip while a hundred of A's
/// cross it (A's first two do not: the points are fixed per light and
/// caster); 100 crates under the roof, which stay culled, are refined too.
/// B comes first, A is the 43rd candidate: in the second chunk of four,
/// so A's points that prove B go in a later chunk than B's own.
#[test]
fn a_sliver_proven_by_a_later_chunks_surface_points_is_kept() {
    let mut world = World::new(1, 1);
    let ground = one(&mut world, quad_up(0.0, 0.0, 16.0, 16.0, 0.0), OPAQUE);
    let roof = one(&mut world, quad_up(2.0, 0.0, 16.0, 16.0, 10.0), OPAQUE);
    let slab = one(&mut world, quad_up(0.6, 0.6, 0.95, 0.95, 2.0), OPAQUE);
    let mut sliver = quad_up(0.6, 0.75, 0.95, 0.77, 2.5);
    for layer in 0..8 {
        sliver.extend(quad_up(3.0, 1.0, 15.0, 15.0, 4.0 + 0.5 * layer as f32));
    }
    let sliver = one(&mut world, sliver, OPAQUE);
    world.place((0, 0), &[ground], DMat4::IDENTITY, false);
    let roof = world.place((0, 0), &[roof], DMat4::IDENTITY, true);
    let b = world.place((0, 0), &[sliver], DMat4::IDENTITY, true);
    let crates = |world: &mut World, ks: std::ops::Range<usize>| {
        for k in ks {
            let min = Vec3::new(
                3.5 + (k % 10) as f32 * 1.1,
                1.0,
                1.5 + (k / 10 % 10) as f32 * 1.3,
            );
            let model = one(world, cube(min, min + 0.5), OPAQUE);
            world.place((0, 0), &[model], DMat4::IDENTITY, true);
        }
    };
    crates(&mut world, 0..41);
    let a = world.place((0, 0), &[slab], DMat4::IDENTITY, true);
    crates(&mut world, 41..100);
    let mut settings = config(vec![directional(DOWN, 1.0)]);
    assert_eq!(
        first_masks(&run(&world, &settings), &world, [roof, a, b]),
        [1, 0, 0]
    );
    settings.refine_samples = 2048;
    settings.refine_density = 0;
    let result = run(&world, &settings);
    assert_eq!(first_masks(&result, &world, [roof, a, b]), [1, 1, 1]);
    let refined = result.lights[0].refine_rays;
    assert!(
        refined > 3 * 65536,
        "{refined} refinement rays: fewer than four chunks"
    );
}
