//! Stiff and extreme cases of the bake (docs/contract.md §6 and §7
//! "Numerical robustness"): worlds far from the origin, axis-aligned and grazing light,
//! coplanar casters on walls, rays exactly on shared edges and vertices,
//! degenerate and non-finite triangles, huge next to tiny triangles, bad
//! transforms, grid sizes from 1×1 up, and the 32-light limit. Each test says
//! what the contract asks for and the masks worked out from its world's design;
//! `micro::run` also bakes every micro world by brute force and asserts the
//! same masks.

use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::formats::bake_settings::{LightKind, LightSettings};

const DOWN: DVec3 = DVec3::new(0.0, -1.0, 0.0);

fn one(world: &mut World, triangles: Vec<[Vec3; 3]>, flags: Flags) -> usize {
    world.model(Mesh {
        groups: vec![(triangles, flags)],
    })
}

fn at(x: f64, y: f64, z: f64) -> DMat4 {
    DMat4::from_translation(DVec3::new(x, y, z))
}

fn spot(
    position: DVec3,
    direction: DVec3,
    fov: f64,
    near: f64,
    far: f64,
    res: u32,
) -> LightSettings {
    LightSettings {
        name: "spot".into(),
        kind: LightKind::Spot {
            position,
            direction: direction.normalize(),
            fov_degrees: fov,
            near,
            far,
            resolution: res,
        },
    }
}

fn skipped_why(result: &bake::BakeResult) -> Vec<String> {
    result.skipped.iter().map(|s| s.why.clone()).collect()
}

/// Quad in the plane x = `x`, facing −x, over y0..y1 × z0..z1.
fn quad_neg_x(x: f32, y0: f32, z0: f32, y1: f32, z1: f32) -> Vec<[Vec3; 3]> {
    let a = Vec3::new(x, y0, z0);
    let b = Vec3::new(x, y0, z1);
    let c = Vec3::new(x, y1, z1);
    let d = Vec3::new(x, y1, z0);
    // (b − a) × (c − a) = (−Δy·Δz, 0, 0): facing −x.
    vec![[a, b, c], [a, c, d]]
}

// ---------------------------------------------------------------------------
// Worlds far from the origin.

/// A 2×2-chunk world full of ties and edge cases, moved by `offset`:
/// hilly terrain (0,0), flat terrain (1,0) and (1,1), void (0,1).
/// Offsets are whole numbers of metres and the boxes' coordinates dyadic, so
/// world coordinates (and the hill's f32 heights plus the offset) are exact
/// in f64 and the light-relative coordinates the trace sees (README
/// "Tolerances") are the same bits at the origin and far from it. The
/// exceptions are the rotated box and the oblique lights' grid axes, whose
/// products round at ~1e−10 m near 1e6 m — a million times below f32's
/// spacing at the world's scale, so they only matter for a vertex or texel
/// centre within that of a rounding boundary (none here).
struct TieWorld {
    world: World,
    /// Box standing on flat terrain (bottom face coplanar with the ground).
    standing: usize,
    /// Decal coplanar with the standing box's top.
    decal: usize,
    /// Box 1..3 m under flat terrain (below-ground test).
    sunk: usize,
    /// Box over the void of chunk (0,1).
    floating: usize,
    /// Box straddling the border of chunks (1,0) and (1,1).
    straddling: usize,
    /// A 1/64 m cube on flat terrain around a texel centre of the sun: far
    /// smaller than f32's spacing at 1e6 m (1/16 m), so it survives only
    /// because geometry is made light-relative in f64 before the f32 trace.
    pebble: usize,
}

fn tie_world(offset: DVec3) -> TieWorld {
    let mut world = World::new_at(2, 2, offset);
    world.terrain((0, 0), |x, z| {
        3.0 * (-((x - 8.0).powi(2) + (z - 8.0).powi(2)) / 16.0).exp()
    });
    world.terrain((1, 0), |_, _| 0.0);
    world.terrain((1, 1), |_, _| 0.0);
    let unit_box = one(&mut world, cube(Vec3::ZERO, Vec3::ONE), OPAQUE);
    let decal = one(&mut world, quad_up(0.25, 0.25, 0.75, 0.75, 1.0), OPAQUE);
    let canopy = one(&mut world, quad_up(0.0, 0.0, 4.0, 4.0, 0.0), CANOPY);
    // Placed in chunk order ((0,0), (0,1), (1,0), (1,1)) so the indices
    // `place` returns stay valid.
    // A mirrored, rotated box over the hill.
    world.place(
        (0, 0),
        &[unit_box],
        at(8.0, 4.0, 8.0)
            * DMat4::from_rotation_y(0.5)
            * DMat4::from_scale(DVec3::new(-1.0, 1.0, 2.0)),
        true,
    );
    let floating = world.place((0, 1), &[unit_box], at(4.0, 2.0, 4.0), true);
    let standing = world.place((1, 0), &[unit_box], at(4.0, 0.0, 4.0), true);
    let decal = world.place((1, 0), &[decal], at(4.0, 0.0, 4.0), true);
    let sunk = world.place(
        (1, 0),
        &[unit_box],
        at(10.0, -3.0, 4.0) * DMat4::from_scale(DVec3::new(2.0, 2.0, 2.0)),
        true,
    );
    let straddling = world.place(
        (1, 0),
        &[unit_box],
        at(6.0, 0.0, 14.0) * DMat4::from_scale(DVec3::new(2.0, 1.5, 4.0)),
        true,
    );
    let pebble = world.place(
        (1, 0),
        &[unit_box],
        at(2.1171875, 0.0, 10.1171875) * DMat4::from_scale(DVec3::splat(1.0 / 64.0)),
        true,
    );
    // An alpha-tested canopy (x 1..5, z 7..11, y 4) over a receiver-only
    // box and a small bush.
    world.place((1, 1), &[unit_box], at(2.0, 0.0, 8.0), false);
    world.place((1, 1), &[canopy], at(1.0, 4.0, 7.0), true);
    world.place(
        (1, 1),
        &[unit_box],
        at(3.5, 0.0, 9.5) * DMat4::from_scale(DVec3::new(0.5, 0.5, 0.5)),
        true,
    );
    TieWorld {
        world,
        standing,
        decal,
        sunk,
        floating,
        straddling,
        pebble,
    }
}

fn far_world_lights(offset: DVec3) -> Vec<LightSettings> {
    let centre = offset + DVec3::new(16.0, 0.0, 16.0);
    vec![
        directional(DOWN, 0.25),
        directional(DVec3::new(1.0, -2.0, 0.5), 0.25),
        directional(
            DVec3::new(1f64.to_radians().cos(), -(1f64.to_radians().sin()), 0.0),
            0.25,
        ),
        spot(
            centre + DVec3::new(0.0, 20.0, 0.0),
            DOWN,
            100.0,
            0.1,
            100.0,
            96,
        ),
        LightSettings {
            name: "point".into(),
            kind: LightKind::Point {
                position: centre + DVec3::new(0.0, 6.0, 0.0),
                near: 0.1,
                far: 40.0,
                resolution: 24,
            },
        },
    ]
}

#[test]
fn world_translated_by_1e5_and_1e6_metres_bakes_like_at_the_origin() {
    // docs/contract.md §7 "worlds far from the origin": geometry is made light-relative
    // in f64 before the f32 trace, so moving the whole world (chunk grid by
    // whole chunks in x and z, chunk transforms in y, lights with it) must
    // not change one mask (see `TieWorld` on why equality can be exact,
    // ties and edge texels included).
    let base = tie_world(DVec3::ZERO);
    let at_origin = run(&base.world, &config(far_world_lights(DVec3::ZERO)));
    // The design, so the comparison is about a world that has answers: the
    // standing box and its decal are useful for the sun (ground behind),
    // the sunk box never (its hits are below ground), the floating box over
    // the void not for the sun straight down.
    let masks = |index| instance_masks(&at_origin, &base.world, index);
    assert_eq!(masks(base.standing)[0] & 1, 1);
    assert_eq!(masks(base.decal)[0] & 1, 1);
    assert_eq!(masks(base.sunk), vec![0]);
    assert_eq!(masks(base.floating)[0] & 1, 0);
    assert_eq!(masks(base.straddling)[0] & 1, 1);
    assert_eq!(masks(base.pebble)[0] & 1, 1);
    assert!(at_origin.masks.contains(&0b11111));

    for offset in [
        DVec3::new(1e5, 0.0, 1e5),
        DVec3::new(-1e5, 1e5, 1e5),
        // 62 500 chunks of 16 m: past BigWorld's 16-bit chunk grid (real
        // spaces reach 1e6 m with 100 m chunks), but the scene keeps grid
        // numbers as i32 and only the chunk names (labels here) wrap.
        DVec3::new(1e6, 1e6, -1e6),
    ] {
        let moved = tie_world(offset);
        let result = run(&moved.world, &config(far_world_lights(offset)));
        assert_eq!(
            result.masks, at_origin.masks,
            "masks at offset {offset} differ from the origin's"
        );
        let rays: Vec<u64> = result.lights.iter().map(|l| l.rays).collect();
        let origin_rays: Vec<u64> = at_origin.lights.iter().map(|l| l.rays).collect();
        assert_eq!(rays, origin_rays, "grid sizes at offset {offset}");
    }
}

// ---------------------------------------------------------------------------
// Light directions.

#[test]
fn light_exactly_along_plus_and_minus_x_grazes_flat_terrain() {
    // docs/contract.md §4: the basis must be robust for a light parallel to any axis.
    // A wall (x 5..6, y 0..4, z 4..12) and a box B behind it (x 11..13,
    // y 0..2, z 6..10) on flat terrain. With texelSize 0.5 and the world's
    // lowest point at y = −0.25 (a sunk marker), texel centres lie at
    // y = 0, 0.5, …, 2, …: rays exactly in the terrain's plane and along the
    // boxes' bottom and B's top edges.
    // Light +x: the wall is hit first, B behind it → wall useful; B is
    // entirely in the wall's shadow → culled. Light −x: B first with the wall
    // behind → useful; the wall, where B does not cover it, has nothing
    // behind → culled. The terrain lies edge-on to every ray: never hit,
    // never useful, and never "something behind".
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let wall = one(
        &mut world,
        cube(Vec3::new(5.0, 0.0, 4.0), Vec3::new(6.0, 4.0, 12.0)),
        OPAQUE,
    );
    let b = one(
        &mut world,
        cube(Vec3::new(11.0, 0.0, 6.0), Vec3::new(13.0, 2.0, 10.0)),
        OPAQUE,
    );
    let marker = one(
        &mut world,
        cube(Vec3::new(14.0, -0.25, 0.0), Vec3::new(15.0, -0.2, 0.5)),
        OPAQUE,
    );
    let wall = world.place((0, 0), &[wall], DMat4::IDENTITY, true);
    let b = world.place((0, 0), &[b], DMat4::IDENTITY, true);
    let marker = world.place((0, 0), &[marker], DMat4::IDENTITY, true);
    // Spots pointing exactly along ±x (lights 2 and 3): +x, from (−10, 1, 8),
    // sees B only through the wall (B's lit faces project inside the wall's
    // face, y 0.29..1.71, z 6.6..9.4) → B culled, wall useful (B and the
    // ground beyond it behind). −x, from (24, 3, 8): B first with ground
    // behind → useful; the wall, seen past B's side (z 11.3..12) low enough
    // (y < 0.75) that the ray lands on the ground beyond it → useful.
    let result = run(
        &world,
        &config(vec![
            directional(DVec3::X, 0.5),
            directional(DVec3::NEG_X, 0.5),
            spot(DVec3::new(-10.0, 1.0, 8.0), DVec3::X, 60.0, 0.1, 100.0, 128),
            spot(
                DVec3::new(24.0, 3.0, 8.0),
                DVec3::NEG_X,
                60.0,
                0.1,
                100.0,
                128,
            ),
        ]),
    );
    assert_eq!(instance_masks(&result, &world, wall), vec![0b1101]);
    assert_eq!(instance_masks(&result, &world, b), vec![0b1010]);
    assert_eq!(instance_masks(&result, &world, marker), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
}

#[test]
fn sun_one_degree_above_the_horizon() {
    // Grazing light, docs/contract.md §7. Flat terrain over two chunks (x 0..32); box 1
    // (x 2..3, y 0..1, z 4..12), box 2 (x 12..13, y 0..0.5, z 6..10). At 1°
    // a ray drops tan 1° ≈ 0.01746 m per metre: any ray reaching box 2's
    // front (y ≤ 0.5 at x = 12) or top (x 12..13) was at most
    // 0.5 + 11·0.01746 ≈ 0.69 m high at x = 2, so it hit box 1 first → box 2
    // culled. Box 1: rays through it go on to the ground (y < 0.52 lands
    // before x = 32) or box 2 → useful. Flat terrain is crossed once with
    // nothing behind → culled.
    let mut world = World::new(2, 1);
    world.terrain((0, 0), |_, _| 0.0);
    world.terrain((1, 0), |_, _| 0.0);
    let b1 = one(
        &mut world,
        cube(Vec3::new(2.0, 0.0, 4.0), Vec3::new(3.0, 1.0, 12.0)),
        OPAQUE,
    );
    let b2 = one(
        &mut world,
        cube(Vec3::new(12.0, 0.0, 6.0), Vec3::new(13.0, 0.5, 10.0)),
        OPAQUE,
    );
    let b1 = world.place((0, 0), &[b1], DMat4::IDENTITY, true);
    let b2 = world.place((0, 0), &[b2], DMat4::IDENTITY, true);
    let angle = 1f64.to_radians();
    let result = run(
        &world,
        &config(vec![directional(
            DVec3::new(angle.cos(), -angle.sin(), 0.0),
            0.05,
        )]),
    );
    assert_eq!(instance_masks(&result, &world, b1), vec![1]);
    assert_eq!(instance_masks(&result, &world, b2), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
    assert_eq!(terrain_mask(&result, 1), 0);
}

#[test]
fn spot_with_near_1e_minus_4_and_far_1e5() {
    // docs/contract.md §4: spot hits count for near ≤ t ≤ far. A spot 10 m above a box
    // over the void, fov 60°, near 1e−4 m. A wide card ("lens", ±1 mm)
    // facing the light covers its whole cone (the widest ray is 39° off
    // axis: 0.82 mm off at 1 mm) at distance d below it; a floor 9e4 m
    // below, wide enough for the cone (±1e5 m).
    // - d = 5e−5 (< near): the lens is ignored → box first, floor behind →
    //   box useful, lens culled; with far = 5e4 the floor is out of reach →
    //   the box has nothing behind → culled.
    // - d = 5e−4 (> near): the lens is hit first, box behind → lens useful,
    //   box never first → culled.
    let light = |far| spot(DVec3::new(8.0, 10.0, 8.0), DOWN, 60.0, 1e-4, far, 32);
    for (d, far, lens_mask, box_mask) in [(5e-5, 1e5, 0, 1), (5e-5, 5e4, 0, 0), (5e-4, 1e5, 1, 0)] {
        let mut world = World::new(1, 1);
        let lens = one(&mut world, quad_up(-1e-3, -1e-3, 1e-3, 1e-3, 0.0), OPAQUE);
        let block = one(
            &mut world,
            cube(Vec3::new(4.0, 1.0, 4.0), Vec3::new(12.0, 2.0, 12.0)),
            OPAQUE,
        );
        let floor = one(&mut world, quad_up(-1e5, -1e5, 1e5, 1e5, 0.0), OPAQUE);
        let lens = world.place((0, 0), &[lens], at(8.0, 10.0 - d, 8.0), true);
        let block = world.place((0, 0), &[block], DMat4::IDENTITY, true);
        let floor = world.place((0, 0), &[floor], at(0.0, 10.0 - 9e4, 0.0), true);
        let result = run(&world, &config(vec![light(far)]));
        let what = format!("lens at {d}, far {far}");
        assert_eq!(
            instance_masks(&result, &world, lens),
            vec![lens_mask],
            "{what}"
        );
        assert_eq!(
            instance_masks(&result, &world, block),
            vec![box_mask],
            "{what}"
        );
        assert_eq!(instance_masks(&result, &world, floor), vec![0], "{what}");
    }
}

// ---------------------------------------------------------------------------
// Coplanar casters and shared edges.

#[test]
fn decal_on_a_vertical_wall_ties_with_it() {
    // docs/contract.md §4 ties (tieEpsilon 1e−4 m): a decal on the −x face of a closed
    // wall box (x 8..10), lit obliquely from −x and above so the hits on the
    // wall and the decal are computed from different triangles and differ
    // by rounding only (≪ tieEpsilon). Where the decal is, the ray crosses
    // decal and wall face at one depth: two crossings → both useful. A bare
    // wall box: front face, back face culled → one crossing → culled.
    let mut world = World::new(1, 1);
    let wall = one(
        &mut world,
        cube(Vec3::new(8.0, 0.0, 1.0), Vec3::new(10.0, 4.0, 7.0)),
        OPAQUE,
    );
    let bare = one(
        &mut world,
        cube(Vec3::new(8.0, 0.0, 9.0), Vec3::new(10.0, 4.0, 15.0)),
        OPAQUE,
    );
    let decal = one(&mut world, quad_neg_x(8.0, 1.0, 2.0, 3.0, 6.0), OPAQUE);
    let wall = world.place((0, 0), &[wall], DMat4::IDENTITY, true);
    let bare = world.place((0, 0), &[bare], DMat4::IDENTITY, true);
    let decal = world.place((0, 0), &[decal], DMat4::IDENTITY, true);
    let result = run(
        &world,
        &config(vec![
            directional(DVec3::new(1.0, -0.5, 0.3), 0.1),
            directional(DVec3::X, 0.1),
        ]),
    );
    assert_eq!(instance_masks(&result, &world, wall), vec![0b11]);
    assert_eq!(instance_masks(&result, &world, decal), vec![0b11]);
    assert_eq!(instance_masks(&result, &world, bare), vec![0]);
}

/// How the triangles of a fan are wound and flagged.
#[derive(Clone, Copy, Debug)]
enum Fan {
    /// Every triangle facing up, single-sided.
    Up,
    /// Every triangle facing up, double-sided.
    TwoSided,
    /// Every other triangle facing down, all double-sided.
    MixedTwoSided,
}

/// A fan of 8 triangles around (4.5, 3, 4.5) with ring vertices on the
/// square 0.5..8.5: edges run along x, along z and along both diagonals,
/// so with texelSize 1 and texel centres at integer + 0.5 rays pass exactly
/// through the centre vertex, the ring vertices and points of every shared
/// edge. Each triangle is its own group, so a ray that were given to two
/// triangles would tie two casters at one depth and make both useful.
/// Every triangle has texel centres strictly inside it (e.g. (5.5, 1.5)).
fn fan(kind: Fan) -> Mesh {
    let c = Vec3::new(4.5, 3.0, 4.5);
    let ring = [
        (0.5, 0.5),
        (4.5, 0.5),
        (8.5, 0.5),
        (8.5, 4.5),
        (8.5, 8.5),
        (4.5, 8.5),
        (0.5, 8.5),
        (0.5, 4.5),
    ]
    .map(|(x, z)| Vec3::new(x, 3.0, z));
    let mut groups = Vec::new();
    for i in 0..8 {
        let (a, b) = (ring[i], ring[(i + 1) % 8]);
        let mut t = [c, a, b];
        if (t[1] - t[0]).cross(t[2] - t[0]).y < 0.0 {
            t.swap(1, 2);
        }
        let flags = match kind {
            Fan::Up => OPAQUE,
            Fan::TwoSided => TWO_SIDED,
            Fan::MixedTwoSided => {
                if i % 2 == 1 {
                    t.swap(1, 2);
                }
                TWO_SIDED
            }
        };
        groups.push((vec![t], flags));
    }
    Mesh { groups }
}

#[test]
fn fans_hit_exactly_on_shared_edges_and_vertices_count_once() {
    // docs/contract.md §4: a ray through an edge or vertex shared by several triangles
    // of a surface crosses it once. Light straight down, texelSize 1; a
    // marker card at x, z 0..0.25 (never hit) puts the grid's lower edges at
    // 0, so texel centres are at integer + 0.5: on the fan's edges and
    // vertices (see `fan`).
    // Over the void each fan is one crossing everywhere → every triangle
    // culled, single-sided, double-sided, or double-sided with mixed
    // winding (the tie rule normalises the edge direction per facing, so
    // the two sides of a shared edge still split it). With flat terrain
    // and a box B (x, z 1..8, y 1..2) below, each triangle is first somewhere
    // with something behind → useful; and no ray leaks through an edge or
    // vertex (a rule that gave a shared edge to neither triangle), so B,
    // entirely under the fan, is never first → culled.
    for kind in [Fan::Up, Fan::TwoSided, Fan::MixedTwoSided] {
        for ground in [false, true] {
            let mut world = World::new(1, 1);
            if ground {
                world.terrain((0, 0), |_, _| 0.0);
            }
            let marker = one(&mut world, quad_up(0.0, 0.0, 0.25, 0.25, 3.0), OPAQUE);
            world.place((0, 0), &[marker], DMat4::IDENTITY, true);
            let f = world.model(fan(kind));
            let f = world.place((0, 0), &[f], DMat4::IDENTITY, true);
            let under = ground.then(|| {
                let b = one(
                    &mut world,
                    cube(Vec3::new(1.0, 1.0, 1.0), Vec3::new(8.0, 2.0, 8.0)),
                    OPAQUE,
                );
                world.place((0, 0), &[b], DMat4::IDENTITY, true)
            });
            let result = run(&world, &config(vec![directional(DOWN, 1.0)]));
            let expected = if ground { 1 } else { 0 };
            assert_eq!(
                instance_masks(&result, &world, f),
                vec![expected; 8],
                "{kind:?} fan, ground: {ground}"
            );
            if let Some(under) = under {
                assert_eq!(
                    instance_masks(&result, &world, under),
                    vec![0],
                    "{kind:?} fan: a ray leaked through it"
                );
            }
        }
    }
}

#[test]
fn terrain_hit_exactly_on_grid_lines_and_vertices_is_one_crossing() {
    // docs/contract.md §4: "test it with texel centres placed exactly on … terrain grid
    // lines". Terrain vertices are 2 m apart; a marker card at x, z
    // −0.5..−0.25 puts texel centres (texelSize 1, straight down) on every
    // integer: every vertex, every grid line and every cell diagonal. A
    // heightfield is crossed once by a vertical ray → the block is culled,
    // flat or hilly; a card above it is useful (the terrain behind it).
    for hilly in [false, true] {
        let mut world = World::new(1, 1);
        if hilly {
            world.terrain((0, 0), |x, z| (x * 0.5).sin() + (z * 0.25).cos());
        } else {
            world.terrain((0, 0), |_, _| 0.0);
        }
        let marker = one(&mut world, quad_up(-0.5, -0.5, -0.25, -0.25, 5.0), OPAQUE);
        world.place((0, 0), &[marker], DMat4::IDENTITY, true);
        let result = run(&world, &config(vec![directional(DOWN, 1.0)]));
        assert_eq!(terrain_mask(&result, 0), 0, "hilly: {hilly}");
        let card = one(&mut world, quad_up(4.0, 4.0, 8.0, 8.0, 5.0), OPAQUE);
        let card = world.place((0, 0), &[card], DMat4::IDENTITY, true);
        let result = run(&world, &config(vec![directional(DOWN, 1.0)]));
        assert_eq!(
            instance_masks(&result, &world, card),
            vec![1],
            "hilly: {hilly}"
        );
    }
}

// ---------------------------------------------------------------------------
// Degenerate and non-finite geometry.

#[test]
fn degenerate_and_non_finite_triangles_are_left_out_and_counted() {
    // docs/contract.md §6 "degenerate or NaN triangles": skip + count. Group 0 is a card
    // over flat terrain plus, among its triangles, a zero-area point, a
    // collinear triangle standing vertically on a texel centre's ray
    // (texelSize 0.25: centres at 0.125 + k/4), a repeated-vertex triangle,
    // one with a NaN and one with an infinite vertex. Group 1 holds the same
    // 5 alone. So 10 are left out per light and reported in `skipped`; the
    // card is useful as if they were not there; group 1 is never hit →
    // culled, and so is group 2, which has no triangles at all.
    let p = Vec3::new(5.125, 2.0, 5.125);
    let junk = vec![
        [p, p, p],
        [p, p + Vec3::Y * 0.5, p + Vec3::Y],
        [p, p, Vec3::new(6.0, 2.0, 6.0)],
        [p, Vec3::new(f32::NAN, 2.0, 5.0), Vec3::new(6.0, 2.0, 5.0)],
        [
            p,
            Vec3::new(6.0, f32::INFINITY, 5.0),
            Vec3::new(6.0, 2.0, 5.0),
        ],
    ];
    let mut card = quad_up(4.0, 4.0, 8.0, 8.0, 3.0);
    card.splice(1..1, junk.iter().copied());
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let m = world.model(Mesh {
        groups: vec![(card, OPAQUE), (junk, OPAQUE), (Vec::new(), OPAQUE)],
    });
    let i = world.place((0, 0), &[m], DMat4::IDENTITY, true);
    let result = run(
        &world,
        &config(vec![
            directional(DOWN, 0.25),
            spot(DVec3::new(6.0, 8.0, 6.0), DOWN, 60.0, 0.1, 20.0, 16),
        ]),
    );
    assert_eq!(instance_masks(&result, &world, i), vec![0b11, 0, 0]);
    for light in ["light 0", "light 1"] {
        assert!(
            result.skipped.iter().any(|s| s.what.starts_with(light)
                && s.why
                    .starts_with("10 zero-area, non-finite or absurdly far")),
            "{light}: {:?}",
            result.skipped
        );
    }
    // The sun's BVH holds the two card triangles and the whole terrain
    // block (8×8 cells, 2 triangles each); nothing else.
    assert_eq!(result.lights[0].triangles, 2 + 8 * 8 * 2);
}

#[test]
fn ten_km_triangles_next_to_a_tenth_of_a_millimetre() {
    // A 10 km square floor (two 10 km triangles, diagonal through (k, k))
    // and a 1e−4 m card 1 m above it at (250, 250). Directional light
    // straight down, texelSize 500: a 20×20 grid with a texel centre at
    // (250, 250), exactly on the floor's diagonal. That ray hits the tiny
    // card (useful: floor behind) and the floor once (tie rule on the
    // diagonal); every other ray crosses the floor once → culled. A spot
    // 0.2 mm above the card (near 1e−5, resolution 5, fov 60°) sees the card
    // with its three central texels (≤ 0.046 mm off axis) → useful for it
    // too. Relative to each light's reference point, the card's f32
    // coordinates keep it 1e−4 m wide (f32 spacing at 250 m is 1.5e−5 m).
    // Tracing in model space: the same card placed (in f64) at
    // (4750, 1, 4750), also on a texel centre but 6.7 km from the sun's
    // reference point (the world's centre). Flattened to light-relative f32
    // (f32 spacing 4.9e−4 m there) it collapsed to zero area and was lost;
    // traced through its instance, the ray is mapped into model space,
    // where the card keeps its 1e−4 m, so the sun keeps it (the spot does
    // not reach it) and nothing is left out.
    let h = 5e-5f32;
    let mut world = World::new(1, 1);
    let floor = one(
        &mut world,
        quad_up(-5000.0, -5000.0, 5000.0, 5000.0, 0.0),
        OPAQUE,
    );
    let tiny = one(
        &mut world,
        quad_up(250.0 - h, 250.0 - h, 250.0 + h, 250.0 + h, 1.0),
        OPAQUE,
    );
    let centred = one(&mut world, quad_up(-h, -h, h, h, 0.0), OPAQUE);
    let floor = world.place((0, 0), &[floor], DMat4::IDENTITY, true);
    let tiny = world.place((0, 0), &[tiny], DMat4::IDENTITY, true);
    let far = world.place((0, 0), &[centred], at(4750.0, 1.0, 4750.0), true);
    let result = run(
        &world,
        &config(vec![
            directional(DOWN, 500.0),
            spot(DVec3::new(250.0, 1.0002, 250.0), DOWN, 60.0, 1e-5, 100.0, 5),
        ]),
    );
    assert_eq!(result.lights[0].rays, 400);
    assert_eq!(instance_masks(&result, &world, tiny), vec![0b11]);
    assert_eq!(instance_masks(&result, &world, floor), vec![0]);
    assert_eq!(instance_masks(&result, &world, far), vec![0b01]);
    assert!(
        !result.skipped.iter().any(|s| s.why.contains("zero-area")),
        "{:?}",
        result.skipped
    );
    assert!(
        !result
            .skipped
            .iter()
            .any(|s| s.what.starts_with("light 1 ") && s.why.contains("zero-area")),
        "{:?}",
        result.skipped
    );
}

// ---------------------------------------------------------------------------
// Bad transforms, through files on disk.

#[test]
fn nan_zero_scale_and_singular_transforms_are_skipped_and_reported_by_the_bake() {
    // docs/contract.md §6 "NaN/Inf or singular transforms": the loader leaves such an
    // instance out as a problem; the bake completes and lists each in its
    // `skipped` (so the report counts them). Three placements of the small
    // world are damaged: a NaN, a zero scale (all-zero rotation rows) and a
    // singular matrix (two equal rows, determinant 0 with no zero scale).
    use shadowcull::files::read_bake_settings;
    use shadowcull::files::{write_tree, ResPaths};
    use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
    use shadowcull::scene::{load_scene, LoadConfig};
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(Preset::Small, 1).files).unwrap();
    let chunk = dir.path().join("spaces/small/00000000o.chunk");
    let text = std::fs::read_to_string(&chunk).unwrap();
    // The first three <transform>s of the chunk: each rewritten whole.
    let mut out = String::new();
    let mut rest = text.as_str();
    let replacements = [
        "<row0> nan 0 0 </row0> <row1> 0 1 0 </row1> <row2> 0 0 1 </row2> <row3> 1 0 1 </row3>",
        "<row0> 0 0 0 </row0> <row1> 0 0 0 </row1> <row2> 0 0 0 </row2> <row3> 2 0 2 </row3>",
        "<row0> 1 0 0 </row0> <row1> 0 1 0 </row1> <row2> 0 1 0 </row2> <row3> 3 0 3 </row3>",
    ];
    for replacement in replacements {
        let start = rest.find("<transform>").expect("a <transform>") + "<transform>".len();
        let end = rest[start..].find("</transform>").expect("its end") + start;
        out.push_str(&rest[..start]);
        out.push_str(replacement);
        rest = &rest[end..];
    }
    out.push_str(rest);
    std::fs::write(&chunk, out).unwrap();

    let settings = read_bake_settings(&dir.path().join(SETTINGS_FILE)).unwrap();
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
        speedtrees: settings.speedtrees.clone(),
    })
    .unwrap();
    let transform_problems = |why: &str| {
        scene
            .problems
            .iter()
            .filter(|p| p.what.contains("00000000o.chunk") && p.why.contains(why))
            .count()
    };
    assert_eq!(transform_problems("NaN"), 1, "{:#?}", scene.problems);
    assert_eq!(transform_problems("singular"), 2, "{:#?}", scene.problems);
    let config = BakeConfig {
        lights: vec![directional(DVec3::new(-0.3, -1.0, 0.2), 0.5)],
        ..BakeConfig::from_settings(&settings)
    };
    let result = bake::bake(&scene, &config, &Silent).expect("the bake completes");
    let skipped = skipped_why(&result);
    assert_eq!(
        skipped.iter().filter(|w| w.contains("NaN")).count(),
        1,
        "{skipped:#?}"
    );
    assert_eq!(
        skipped.iter().filter(|w| w.contains("singular")).count(),
        2,
        "{skipped:#?}"
    );
    assert!(result.masks.contains(&1), "the rest still bakes");
}

// ---------------------------------------------------------------------------
// Grid sizes.

#[test]
fn one_by_one_grids() {
    // One texel: a directional light whose texelSize is the world's width
    // (16 m → 1×1) and a spot of resolution 1. Each casts one ray: through
    // the world bounds' centre (8, 8), and along the spot's axis. A box under
    // that point on flat terrain is useful; a box off it is never sampled →
    // culled (a caster between texels is not seen: the documented cost of
    // sampling). A texelSize larger than the world is 1×1 too, but its one
    // centre lies half a texel from the grid's lower corner (the grid is
    // anchored there, `light` module docs), outside this world: no caster is
    // useful.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let centre = one(
        &mut world,
        cube(Vec3::new(7.0, 1.0, 7.0), Vec3::new(9.0, 2.0, 9.0)),
        OPAQUE,
    );
    let aside = one(
        &mut world,
        cube(Vec3::new(1.0, 1.0, 1.0), Vec3::new(3.0, 2.0, 3.0)),
        OPAQUE,
    );
    let centre = world.place((0, 0), &[centre], DMat4::IDENTITY, true);
    let aside = world.place((0, 0), &[aside], DMat4::IDENTITY, true);
    let result = run(
        &world,
        &config(vec![
            directional(DOWN, 16.0),
            spot(DVec3::new(8.0, 10.0, 8.0), DOWN, 60.0, 0.1, 50.0, 1),
            directional(DOWN, 100.0),
        ]),
    );
    for light in &result.lights {
        assert_eq!(light.rays, 1, "{}", light.name);
    }
    assert_eq!(instance_masks(&result, &world, centre), vec![0b011]);
    assert_eq!(instance_masks(&result, &world, aside), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
}

/// The spot grid of the large-grid test: 16384² (268 M rays). Memory does
/// not grow with it: texels are traced in 32×32 tiles generated on the fly
/// (`TexelGrid::ray` is a pure function of the texel), each thread folds its
/// results into one bitset of casters (`CasterSet`, one bit per caster) and
/// one reused hit list, and the sets are OR-ed at the end — there is no
/// per-texel buffer anywhere.
const LARGE_GRID: u32 = 16384;

/// The process's peak resident set (`VmHWM`, KiB), where Linux reports it.
fn peak_rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

#[test]
fn large_spot_grid_streams_tiles() {
    // A 120° spot 10 m above a small box (4 m wide, 8 m below it) with a
    // receiver-only card under it: `LARGE_GRID`² texels, of which about 2 %
    // see anything (the rest leave the BVH at its root, which keeps the test
    // quick). The ray count is the full grid, and the answer equals the 64²
    // bake's: the box is useful (the card behind it), the card never.
    let mut world = World::new(1, 1);
    let b = one(
        &mut world,
        cube(Vec3::new(6.0, 1.0, 6.0), Vec3::new(10.0, 2.0, 10.0)),
        OPAQUE,
    );
    let card = one(&mut world, quad_up(5.0, 5.0, 11.0, 11.0, 0.0), OPAQUE);
    let b = world.place((0, 0), &[b], DMat4::IDENTITY, true);
    let card = world.place((0, 0), &[card], DMat4::IDENTITY, false);
    let light = |res| spot(DVec3::new(8.0, 10.0, 8.0), DOWN, 120.0, 0.1, 50.0, res);
    let started = std::time::Instant::now();
    let peak_before = peak_rss_kib();
    let large = bake::bake(&world.scene, &config(vec![light(LARGE_GRID)]), &Silent).unwrap();
    let peak_after = peak_rss_kib();
    eprintln!(
        "{LARGE_GRID}² spot grid baked in {:.2} s; peak RSS {peak_before:?} → {peak_after:?} KiB",
        started.elapsed().as_secs_f64()
    );
    // The process's peak resident memory may grow by the tracing threads'
    // small buffers, never by anything per texel: one bit per texel would
    // already be 32 MiB. (Other tests of this binary run alongside; the
    // whole binary peaks under 20 MiB, so 32 MiB cannot be reached by them.)
    if let (Some(before), Some(after)) = (peak_before, peak_after) {
        assert!(
            after.saturating_sub(before) < 32 * 1024,
            "peak RSS grew from {before} to {after} KiB during the bake"
        );
    }
    assert_eq!(
        large.lights[0].rays,
        u64::from(LARGE_GRID) * u64::from(LARGE_GRID)
    );
    let small = run(&world, &config(vec![light(64)]));
    assert_eq!(instance_masks(&large, &world, b), vec![1]);
    assert_eq!(instance_masks(&large, &world, card), vec![0]);
    assert_eq!(large.masks, small.masks);
}

// ---------------------------------------------------------------------------
// Light counts, empty worlds, empty frusta (beyond tests/it/bake_rules.rs).

#[test]
fn thirty_two_lights_set_bit_31() {
    // docs/contract.md §3: up to 32 lights, bit i for light i. Two boxes on terrain in
    // two chunks; light i is a narrow spot straight above box A when bit i
    // of PATTERN is set, else above box B. So A's mask is PATTERN and B's
    // its complement — bit 31 included on A, bit 30 on B.
    const PATTERN: u32 = 0xA5C3_0F81;
    let mut world = World::new(2, 1);
    world.terrain((0, 0), |_, _| 0.0);
    world.terrain((1, 0), |_, _| 0.0);
    let m = one(
        &mut world,
        cube(Vec3::new(6.0, 1.0, 6.0), Vec3::new(10.0, 2.0, 10.0)),
        OPAQUE,
    );
    let a = world.place((0, 0), &[m], DMat4::IDENTITY, true);
    let b = world.place((1, 0), &[m], DMat4::IDENTITY, true);
    let lights = (0..32)
        .map(|i| {
            let x = if PATTERN & (1 << i) != 0 { 8.0 } else { 24.0 };
            let mut light = spot(DVec3::new(x, 6.0, 8.0), DOWN, 30.0, 0.1, 20.0, 8);
            light.name = format!("spot{i}");
            light
        })
        .collect();
    let result = run(&world, &config(lights));
    assert_eq!(result.lights.len(), 32);
    assert_eq!(instance_masks(&result, &world, a), vec![PATTERN]);
    assert_eq!(instance_masks(&result, &world, b), vec![!PATTERN]);
    assert_eq!(result.lights[31].useful_casters, 1);
    // Written into A's chunk, the mask is the unsigned decimal of PATTERN
    // (not a negative i32) on the instance and its one group.
    let shadows = bake::output::chunk_shadows(&world.scene, &result, 0);
    let original = b"<root>\n\t<model>\n\t\t<resource>\tmicro/0.model\t</resource>\n\t</model>\n\t<terrain>\n\t\t<resource>\t0000.cdata\t</resource>\n\t</terrain>\n</root>\n";
    let written = shadowcull::formats::shadow_write::write_shadows(original, &shadows)
        .expect("write the masks");
    let text = String::from_utf8(written).unwrap();
    assert_eq!(text.matches("2781024129").count(), 2, "{text}");
    assert!(!text.contains('-'), "{text}");
}

#[test]
fn thirty_three_lights_are_refused_before_any_work() {
    // docs/contract.md §3: more than 32 lights is a clear error — which names the count
    // and what to do — and it comes before anything is traced.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let lights: Vec<_> = (0..33).map(|_| directional(DOWN, 0.25)).collect();
    let err = bake::bake(&world.scene, &config(lights), &Silent).unwrap_err();
    assert!(
        matches!(err, bake::BakeError::TooManyLights { count: 33 }),
        "{err:?}"
    );
    let message = err.to_string();
    assert!(
        message.contains("33 lights") && message.contains("split"),
        "{message}"
    );
}

#[test]
fn worlds_with_nothing_to_hit_skip_every_light_kind() {
    // docs/contract.md §6 "empty worlds": an empty world, and a world whose only model
    // has nothing but degenerate triangles, skip directional, spot and point
    // lights alike with a reason, and bake no rays.
    let lights = vec![
        directional(DOWN, 1.0),
        spot(DVec3::new(8.0, 5.0, 8.0), DOWN, 60.0, 0.1, 20.0, 8),
        LightSettings {
            name: "point".into(),
            kind: LightKind::Point {
                position: DVec3::new(8.0, 5.0, 8.0),
                near: 0.1,
                far: 20.0,
                resolution: 8,
            },
        },
    ];
    let empty = World::new(1, 1);
    let result = run(&empty, &config(lights.clone()));
    assert!(result.lights.is_empty());
    for i in 0..3 {
        assert!(
            result.skipped.iter().any(
                |s| s.what.starts_with(&format!("light {i} ")) && s.why.contains("no geometry")
            ),
            "light {i}: {:?}",
            result.skipped
        );
    }

    let mut degenerate = World::new(1, 1);
    let p = Vec3::new(4.0, 1.0, 4.0);
    let m = one(
        &mut degenerate,
        vec![[p, p, p], [p, p + Vec3::X, p + Vec3::X * 2.0]],
        OPAQUE,
    );
    let i = degenerate.place((0, 0), &[m], DMat4::IDENTITY, true);
    let result = run(&degenerate, &config(lights));
    assert_eq!(instance_masks(&result, &degenerate, i), vec![0]);
    assert!(result
        .lights
        .iter()
        .all(|l| l.rays == 0 && l.triangles == 0));
    assert_eq!(
        skipped_why(&result)
            .iter()
            .filter(|w| w.contains("holds no geometry"))
            .count(),
        3,
        "{:?}",
        result.skipped
    );
}

#[test]
fn point_light_whose_reach_holds_nothing() {
    // A point light with far = 1 m, 5 m above a box on terrain: nothing in
    // its shell → no rays, every caster out of reach counted, masks 0.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let m = one(
        &mut world,
        cube(Vec3::new(6.0, 1.0, 6.0), Vec3::new(10.0, 2.0, 10.0)),
        OPAQUE,
    );
    let b = world.place((0, 0), &[m], DMat4::IDENTITY, true);
    let point = LightSettings {
        name: "point".into(),
        kind: LightKind::Point {
            position: DVec3::new(8.0, 7.0, 8.0),
            near: 0.1,
            far: 1.0,
            resolution: 16,
        },
    };
    let result = run(&world, &config(vec![point]));
    assert_eq!(instance_masks(&result, &world, b), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
    assert_eq!(result.lights[0].rays, 0);
    let why = skipped_why(&result);
    assert!(
        why.iter()
            .any(|w| w.starts_with("1 instance parts and 1 terrain blocks outside its reach")),
        "{why:?}"
    );
    assert!(
        why.iter().any(|w| w.contains("holds no geometry")),
        "{why:?}"
    );
}

#[test]
fn absurd_finite_vertices_and_scales_are_left_out_not_fatal() {
    // docs/contract.md §6: a damaged file can hold a finite but absurd vertex (1e30 m)
    // or a placement scaled by 1e20. Such geometry can never be traced in
    // f32 (the trace drops anything beyond MAX_COORDINATE = 1e15 m), so it
    // is left out and counted like a NaN triangle — and it must not stretch
    // the world bounds: one such vertex would make the sun's grid
    // impossibly wide and fail the whole bake.
    // Here: a card over flat terrain whose group also holds a triangle with
    // a 1e30 vertex, and a unit box placed with scale 1e20 (12 triangles).
    // The sun's grid is the 16 m world's (64² at 0.25 m), the card is useful,
    // and the sun counts 1 + 12 triangles left out.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let mut card = quad_up(4.0, 4.0, 8.0, 8.0, 3.0);
    card.push([
        Vec3::new(5.0, 3.0, 5.0),
        Vec3::new(1e30, 3.0, 5.0),
        Vec3::new(5.0, 3.0, 6.0),
    ]);
    let card = one(&mut world, card, OPAQUE);
    let unit_box = one(&mut world, cube(Vec3::ZERO, Vec3::ONE), OPAQUE);
    let card = world.place((0, 0), &[card], DMat4::IDENTITY, true);
    let huge = world.place(
        (0, 0),
        &[unit_box],
        at(12.0, 0.0, 12.0) * DMat4::from_scale(DVec3::splat(1e20)),
        true,
    );
    let result = run(
        &world,
        &config(vec![
            directional(DOWN, 0.25),
            spot(DVec3::new(6.0, 8.0, 6.0), DOWN, 60.0, 0.1, 20.0, 16),
        ]),
    );
    assert_eq!(result.lights[0].rays, 64 * 64);
    assert_eq!(instance_masks(&result, &world, card), vec![0b11]);
    assert_eq!(instance_masks(&result, &world, huge), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);
    assert!(
        result.skipped.iter().any(|s| s.what.starts_with("light 0 ")
            && s.why
                .starts_with("13 zero-area, non-finite or absurdly far (> 1e15 m)")),
        "{:?}",
        result.skipped
    );
}
