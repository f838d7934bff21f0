//! Refinement's occlusion test (`bake::occlusion`) against the rays it
//! stands in for: on generated worlds, under suns from several directions,
//! every point it calls hidden from a caster must be one whose ray, traced
//! in full, does not have that caster in its front set in any pass.

use crate::tiles::{small_world, sun_index};
use glam::DVec3;
use shadowcull::bake::occlusion::{CasterImage, Occlusion};
use shadowcull::bake::setup::{BakeWorld, LightSetup};
use shadowcull::bake::BakeConfig;
use shadowcull::classify;
use shadowcull::formats::bake_settings::LightKind;
use shadowcull::rng::Rng;
use std::collections::HashMap;

#[test]
fn points_called_hidden_never_have_the_caster_in_front() {
    let (mut hidden_points, mut open_points) = (0, 0);
    for (seed, direction) in [
        (2, DVec3::new(-0.3, -1.0, 0.2)),
        (7, DVec3::new(0.8, -0.45, -0.5)),
        (11, DVec3::new(0.05, -1.0, 0.0)),
    ] {
        let (_dir, scene, settings) = small_world(seed);
        let baked = BakeWorld::new(&scene);
        let mut config = BakeConfig::from_settings(&settings);
        let index = sun_index(&config);
        if let LightKind::Directional {
            texel_size,
            direction: d,
        } = &mut config.lights[index].kind
        {
            *texel_size = 0.5;
            *d = direction;
        }
        let setup = LightSetup::new(&baked, &config, index).unwrap();
        let rays = setup.rays(&baked, &config);
        let occlusion = Occlusion::new(&baked, &setup, &rays, &config).unwrap();
        let grid = &setup.grid;
        let reference = grid.reference_point();
        let table = &rays.casters.casters;
        let mut images: HashMap<u32, CasterImage> = HashMap::new();
        let mut hits = Vec::new();
        let mut rng = Rng::new(seed);
        for caster in 0..table.len() as u32 {
            let info = &table[caster as usize];
            if info.is_terrain() || info.receiver_only {
                continue;
            }
            let triangles = setup.caster_triangles(&baked, caster);
            for t in triangles.iter().take(60).flat_map(|t| [t; 3]) {
                let [a, b, c] = t.vertices.map(|v| reference + v.as_dvec3());
                let (r1, r2) = (rng.unit().sqrt(), rng.unit());
                let on = a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2);
                let Some(p) = grid.project_point(0, on) else {
                    continue;
                };
                let ray = grid.ray_through(0, p.0, p.1);
                rays.all_hits(&ray, &mut hits);
                // The caster's own depth there, as the images measure it.
                let Some(t_caster) = hits.iter().find(|h| h.caster == caster).map(|h| h.t) else {
                    continue;
                };
                let near = f64::from(t_caster) + ray.origin.dot(ray.direction);
                // Occluders as refinement names them: what its rays met,
                // here this ray and one a texel away.
                let mut named: Vec<u32> = hits.iter().map(|h| h.caster).collect();
                let beside =
                    grid.ray_through(0, p.0 + rng.range(-1.0, 1.0), p.1 + rng.range(-1.0, 1.0));
                let mut more = Vec::new();
                rays.all_hits(&beside, &mut more);
                named.extend(more.iter().map(|h| h.caster));
                named.sort_unstable();
                named.dedup();
                // Receiver-only ones too, which refinement leaves out: the
                // test itself must not count them.
                named.retain(|&c| c != caster && !table[c as usize].is_terrain());
                for &c in &named {
                    images.entry(c).or_insert_with(|| occlusion.image(0, c));
                }
                let occluders: Vec<&CasterImage> = named.iter().map(|c| &images[c]).collect();
                let hidden = occlusion.hidden(&[p], &[near], info.alpha_tested, &occluders)[0];
                if !hidden {
                    open_points += 1;
                    continue;
                }
                hidden_points += 1;
                let passes = rays.rules.passes;
                for pass in 0..classify::pass_count(passes) {
                    classify::pass_depths(&hits, passes, pass, rays.rules.tie_epsilon, |c| {
                        assert_ne!(
                            c, caster,
                            "seed {seed}: caster {caster} called hidden at {p:?} is in front \
                             in pass {pass}: {hits:?}"
                        );
                    });
                }
            }
        }
    }
    // Both answers are given, often.
    assert!(
        hidden_points > 300,
        "{hidden_points} hidden, {open_points} open"
    );
    assert!(
        open_points > 300,
        "{hidden_points} hidden, {open_points} open"
    );
}

/// What covers a box caster (x, z 4..6, y 1..2) under a sun straight down
/// (1 m texels): a slab at y 5 over x, z 2..8, of the given kind, and
/// optionally flat terrain at y `ground` over the whole chunk.
#[derive(Clone, Copy, Debug)]
enum Slab {
    Opaque,
    ReceiverOnly,
    AlphaTested,
    BelowGround,
}

/// Whether the occlusion test calls the caster's points (a lattice over
/// its top, at its top's depth) hidden by the slab: all, or none.
fn slab_hides(slab: Slab) -> (usize, usize) {
    use crate::micro::*;
    use glam::{DMat4, Vec3};
    let mut world = World::new(1, 1);
    let caster = world.model(Mesh {
        groups: vec![(
            cube(Vec3::new(4.0, 1.0, 4.0), Vec3::new(6.0, 2.0, 6.0)),
            OPAQUE,
        )],
    });
    let flags = match slab {
        Slab::AlphaTested => CANOPY,
        _ => OPAQUE,
    };
    let cover = world.model(Mesh {
        groups: vec![(quad_up(2.0, 2.0, 8.0, 8.0, 5.0), flags)],
    });
    let placed = world.place((0, 0), &[caster], DMat4::IDENTITY, true);
    let casts = !matches!(slab, Slab::ReceiverOnly);
    let covering = world.place((0, 0), &[cover], DMat4::IDENTITY, casts);
    // Terrain above the slab makes every hit on it below ground; under
    // the others it lies below everything.
    let height = if matches!(slab, Slab::BelowGround) {
        7.0
    } else {
        0.0
    };
    world.terrain((0, 0), |_, _| height);
    let config = config(vec![directional(DVec3::new(0.0, -1.0, 0.0), 1.0)]);
    let baked = BakeWorld::new(&world.scene);
    let setup = LightSetup::new(&baked, &config, 0).unwrap();
    let rays = setup.rays(&baked, &config);
    let occlusion = Occlusion::new(&baked, &setup, &rays, &config).unwrap();
    let caster_of = |instance: usize| {
        baked
            .parts
            .iter()
            .find(|p| p.instance == instance)
            .unwrap()
            .first_caster
    };
    let (x, slab_caster) = (caster_of(placed), caster_of(covering));
    let image = occlusion.image(0, slab_caster);
    // Off the slab's diagonal (x = z), whose points lie within the inside
    // margin of both its triangles and so are hidden by neither.
    let mut points = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let on_top = DVec3::new(4.1 + 0.25 * i as f64, 2.0, 4.2 + 0.25 * j as f64);
            points.push(setup.grid.project_point(0, on_top).unwrap());
        }
    }
    // Depth along the light (t plus a constant): -y under a sun straight
    // down.
    let near = vec![-2.0; points.len()];
    let alpha = rays.casters.casters[x as usize].alpha_tested;
    let hidden = occlusion.hidden(&points, &near, alpha, &[&image]);
    let count = hidden.iter().filter(|&&h| h).count();
    (count, points.len())
}

#[test]
fn only_a_counted_opaque_cover_above_ground_hides() {
    // The slab is 3 m nearer the sun than the caster's top everywhere over
    // it, so as an opaque caster above ground it hides every point.
    let (hidden, all) = slab_hides(Slab::Opaque);
    assert_eq!(hidden, all);
    // A receiver-only slab is no caster: the caster stays in front (the
    // nearest caster hit) wherever the slab lies.
    assert_eq!(slab_hides(Slab::ReceiverOnly).0, 0);
    // An alpha-tested slab is left out of the Opaque pass, where the
    // caster is in front.
    assert_eq!(slab_hides(Slab::AlphaTested).0, 0);
    // Under terrain at y 7 every hit on the slab is dropped as below
    // ground: it hides nothing.
    assert_eq!(slab_hides(Slab::BelowGround).0, 0);
}

#[test]
fn ground_at_most_bounds_the_terrain_over_a_rectangle() {
    // Hills over 2 × 2 chunks; random rectangles, many across chunk
    // borders; whenever `at_most` says H ≤ level over one, no height
    // sampled inside it is above.
    use crate::micro::*;
    use shadowcull::bake::ground::Ground;
    let mut world = World::new(2, 2);
    for grid in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let (ox, oz) = (grid.0 as f64 * CHUNK, grid.1 as f64 * CHUNK);
        world.terrain_of(grid, 16, move |x, z| {
            3.0 * ((x + ox) * 0.4).sin() * ((z + oz) * 0.3).cos() + 0.1 * (x + ox)
        });
    }
    let ground = Ground::new(&world.scene).unwrap();
    let mut rng = Rng::new(9);
    let (mut below, mut above) = (0, 0);
    for _ in 0..400 {
        let (x0, z0) = (rng.range(-2.0, 2.0 * CHUNK), rng.range(-2.0, 2.0 * CHUNK));
        let (x1, z1) = (x0 + rng.range(0.0, 6.0), z0 + rng.range(0.0, 6.0));
        let level = rng.range(-3.0, 6.0);
        if !ground.at_most((x0, z0), (x1, z1), level, 4096) {
            above += 1;
            continue;
        }
        below += 1;
        for i in 0..=24 {
            for j in 0..=24 {
                let (x, z) = (
                    x0 + (x1 - x0) * i as f64 / 24.0,
                    z0 + (z1 - z0) * j as f64 / 24.0,
                );
                if let Some(h) = ground.height(x, z) {
                    assert!(
                        h <= level + 1e-9,
                        "H({x}, {z}) = {h} above {level} in {x0}..{x1} × {z0}..{z1}"
                    );
                }
            }
        }
    }
    assert!(below > 50 && above > 50, "{below} below, {above} above");
}

/// `Occlusion::hidden_block` (a block of lattice points at once, triangle
/// by triangle over each row's span) answers every point as
/// `Occlusion::hidden` (point by point): on generated worlds, blocks over
/// casters' footprints, with the refined caster's depth from well in front
/// of to well behind them, alpha-tested or not. Both answers come often.
#[test]
fn a_block_of_lattice_points_is_hidden_as_point_by_point() {
    use shadowcull::bake::occlusion::LatticeBlock;
    let (mut hidden_points, mut open_points) = (0, 0);
    for seed in [3, 5] {
        let (_dir, scene, settings) = small_world(seed);
        let baked = BakeWorld::new(&scene);
        let config = BakeConfig::from_settings(&settings);
        let index = sun_index(&config);
        let setup = LightSetup::new(&baked, &config, index).unwrap();
        let rays = setup.rays(&baked, &config);
        let occlusion = Occlusion::new(&baked, &setup, &rays, &config).unwrap();
        let grid = &setup.grid;
        let reference = grid.reference_point();
        let direction = grid.direction().unwrap();
        let table = &rays.casters.casters;
        let mut rng = Rng::new(seed);
        let models: Vec<u32> = (0..table.len() as u32)
            .filter(|&c| !table[c as usize].is_terrain())
            .collect();
        for (k, &caster) in models.iter().enumerate().take(200) {
            let triangles = setup.caster_triangles(&baked, caster);
            let vertices: Vec<DVec3> = triangles
                .iter()
                .flat_map(|t| t.vertices.map(|v| reference + v.as_dvec3()))
                .collect();
            let projected: Vec<(f64, f64)> = vertices
                .iter()
                .filter_map(|&v| grid.project_point(0, v))
                .collect();
            if projected.is_empty() {
                continue;
            }
            let density = [4, 8][k % 2];
            let d = f64::from(density);
            let (lo, hi) = shadowcull::bake::texel_beam::bounds(projected.iter().copied());
            let block = LatticeBlock {
                i0: ((lo.0 - 1.0) * d).floor() as i64,
                j0: ((lo.1 - 1.0) * d).floor() as i64,
                ni: (((hi.0 - lo.0 + 2.0) * d).ceil() as i64).min(96),
                nj: (((hi.1 - lo.1 + 2.0) * d).ceil() as i64).min(96),
                density,
            };
            // The caster and a neighbour in id order as occluders.
            let other = models[(k + 1) % models.len()];
            let images = [occlusion.image(0, caster), occlusion.image(0, other)];
            let occluders: Vec<&CasterImage> = images.iter().collect();
            let least = vertices
                .iter()
                .map(|v| v.dot(direction))
                .fold(f64::INFINITY, f64::min);
            let near = least + rng.range(-2.0, 6.0);
            let alpha = rng.chance(0.3);
            let by_block = occlusion.hidden_block(block, near, alpha, &occluders);
            let points: Vec<(f64, f64)> = (block.j0..block.j0 + block.nj)
                .flat_map(|j| (block.i0..block.i0 + block.ni).map(move |i| block.point(i, j)))
                .collect();
            let by_point = occlusion.hidden(&points, &vec![near; points.len()], alpha, &occluders);
            assert_eq!(by_block.len(), points.len());
            for (at, (&a, &b)) in by_block.iter().zip(&by_point).enumerate() {
                assert_eq!(
                    a, b,
                    "seed {seed} caster {caster}: point {:?} of {block:?} at depth {near}",
                    points[at]
                );
            }
            hidden_points += by_block.iter().filter(|&&h| h).count();
            open_points += by_block.iter().filter(|&&h| !h).count();
        }
    }
    assert!(
        hidden_points > 2000 && open_points > 2000,
        "{hidden_points} hidden, {open_points} open"
    );
}
