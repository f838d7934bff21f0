//! Issue 17: no missing shadow at any shadow-map offset. Designed worlds
//! for the filter margin, refinement and the conservative mode (expected
//! masks from each world's design, explained beside it; `micro::run` also
//! checks the brute-force oracle), and seeded random worlds against the
//! union of many randomly offset dense bakes.

use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};

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
