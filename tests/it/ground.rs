//! The below-ground rule's shortcut (`Ground::is_below`): the ceilings over
//! squares of the world bound every height the exact lookup can answer, so
//! the rule answers as the exact test alone does, on chunk borders, square
//! borders and sample points, near the origin and far from it.

use crate::micro::*;
use glam::DVec3;
use shadowcull::bake::ground::Ground;
use shadowcull::rng::Rng;

/// Hills over 3 × 2 chunks with a narrow spike on every fifth sample, so a
/// ceiling that leaves out one row or column of samples falls below the
/// terrain there.
fn hilly(offset: DVec3, cells: usize) -> World {
    let mut world = World::new_at(3, 2, offset);
    let spacing = CHUNK / cells as f64;
    for gx in 0..3 {
        for gz in 0..2 {
            let (ox, oz) = (f64::from(gx) * CHUNK, f64::from(gz) * CHUNK);
            world.terrain_of((gx, gz), cells, move |x, z| {
                let (i, j) = (((x + ox) / spacing).round(), ((z + oz) / spacing).round());
                let spike = if (i + 3.0 * j).rem_euclid(5.0) == 0.0 {
                    2.5
                } else {
                    0.0
                };
                4.0 * ((x + ox) * 0.35).sin() * ((z + oz) * 0.25).cos() + spike
            });
        }
    }
    world
}

/// Points to ask about: random ones over the world and a chunk around it,
/// and every sample, chunk border and square border crossing.
fn points(rng: &mut Rng, origin: DVec3, cells: usize) -> Vec<(f64, f64)> {
    let mut out: Vec<(f64, f64)> = (0..3000)
        .map(|_| {
            (
                rng.range(-CHUNK, 4.0 * CHUNK),
                rng.range(-CHUNK, 3.0 * CHUNK),
            )
        })
        .collect();
    for step in [CHUNK / cells as f64, CHUNK / 8.0, CHUNK] {
        let (nx, nz) = ((3.0 * CHUNK / step) as i32, (2.0 * CHUNK / step) as i32);
        for i in 0..=nx {
            for j in 0..=nz {
                out.push((f64::from(i) * step, f64::from(j) * step));
            }
        }
    }
    out.into_iter()
        .map(|(x, z)| (origin.x + x, origin.z + z))
        .collect()
}

#[test]
fn ceilings_bound_the_terrain_and_leave_the_rule_unchanged() {
    let mut rng = Rng::new(31);
    let (mut shortcuts, mut exact) = (0, 0);
    for (offset, cells) in [
        (DVec3::ZERO, 16),
        // Spacing that is not a power of two, lifted chunks.
        (DVec3::new(-40.0 * CHUNK, 120.0, 7.0 * CHUNK), 5),
        // Far from the origin (65 km), where the f32 rounding of the
        // ceilings and of the square lookup is coarse.
        (DVec3::new(4096.0 * CHUNK, -30.0, -4096.0 * CHUNK), 16),
    ] {
        let world = hilly(offset, cells);
        let ground = Ground::new(&world.scene).expect("terrain");
        for (x, z) in points(&mut rng, offset, cells) {
            let h = ground.height(x, z);
            if let Some(h) = h {
                let c = ground.ceiling(x, z).expect("a ceiling over terrain");
                assert!(c >= h, "ceiling {c} below H({x}, {z}) = {h}");
                // Tight: a square's samples, not the world's highest.
                assert!(c - h < 9.0, "ceiling {c} far above H({x}, {z}) = {h}");
            }
            let c = ground.ceiling(x, z);
            for bias in [0.05, 0.0, -0.3] {
                let mut heights = vec![
                    offset.y + rng.range(-8.0, 10.0),
                    offset.y + rng.range(-8.0, 10.0),
                ];
                for level in [h, c].into_iter().flatten() {
                    for d in [-1e-3, -1e-7, 0.0, 1e-7, 1e-3, 2e-3] {
                        heights.push(level - bias + d);
                    }
                }
                for y in heights {
                    let rule = h.is_some_and(|h| y < h - bias);
                    assert_eq!(
                        ground.is_below(DVec3::new(x, y, z), bias),
                        rule,
                        "({x}, {y}, {z}), bias {bias}, H {h:?}, ceiling {c:?}"
                    );
                    if c.is_some_and(|c| y >= c + 1e-3 - bias) {
                        shortcuts += 1;
                    } else {
                        exact += 1;
                    }
                }
            }
        }
    }
    assert!(
        shortcuts > 10_000 && exact > 10_000,
        "{shortcuts} answered by the ceiling, {exact} exactly"
    );
}

#[test]
fn no_ceiling_outside_the_blocks_reach() {
    // Far outside every block (several chunks away) there is no ceiling or
    // an empty one (−∞: no block comes near), and nothing is below ground.
    let world = hilly(DVec3::ZERO, 8);
    let ground = Ground::new(&world.scene).expect("terrain");
    for (x, z) in [
        (-3.0 * CHUNK, 0.0),
        (10.0 * CHUNK, CHUNK),
        (CHUNK, -1.5 * CHUNK),
    ] {
        assert!(ground.ceiling(x, z).is_none_or(|c| c == f64::NEG_INFINITY));
        assert!(!ground.is_below(DVec3::new(x, -1e6, z), 0.0));
    }
}

#[test]
fn blocks_off_their_grid_cells_keep_the_rule() {
    // Chunk (1, 0)'s block moved along x and z (a chunk transform that
    // disagrees with its name). Half a chunk stays within the grid of
    // ceilings, which then bound the moved block where it lies; five
    // chunks leave it, and there are no ceilings at all. Either way the
    // rule answers as the exact lookup does.
    for (shift, ceilings) in [(0.5 * CHUNK, true), (5.0 * CHUNK, false)] {
        let mut world = World::new(2, 2);
        for chunk in world.scene.chunks.iter_mut() {
            if chunk.grid == Some((1, 0)) {
                chunk.transform.w_axis.x += shift;
                chunk.transform.w_axis.z += shift;
            }
        }
        for grid in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            world.terrain_of(grid, 8, |x, z| 2.0 * (x * 0.5).sin() + 0.2 * z + 1.0);
        }
        let ground = Ground::new(&world.scene).expect("terrain");
        let mut rng = Rng::new(4);
        let mut under = 0;
        for _ in 0..4000 {
            let (x, z) = (
                rng.range(-2.0, 2.0 * CHUNK + shift + 2.0),
                rng.range(-2.0, 2.0 * CHUNK + shift + 2.0),
            );
            let h = ground.height(x, z);
            let c = ground.ceiling(x, z);
            assert_eq!(c.is_some(), ceilings, "({x}, {z})");
            if let (Some(h), Some(c)) = (h, c) {
                assert!(c >= h, "ceiling {c} below H({x}, {z}) = {h}");
            }
            let y = rng.range(-4.0, 8.0);
            let rule = h.is_some_and(|h| y < h - 0.05);
            under += usize::from(rule);
            assert_eq!(ground.is_below(DVec3::new(x, y, z), 0.05), rule);
        }
        assert!(under > 100, "{under} points below ground");
    }
}

#[test]
fn ceilings_are_the_same_whichever_points_ask_first() {
    // A square's bound is found when a point first asks for it: asked in
    // another order, or by many threads at once, it is the same.
    use rayon::prelude::*;
    let world = hilly(DVec3::new(-3.0 * CHUNK, 12.0, 5.0 * CHUNK), 16);
    let pts = points(
        &mut Rng::new(77),
        world.scene.chunks[0].transform.w_axis.truncate(),
        16,
    );
    let forward = Ground::new(&world.scene).expect("terrain");
    let backward = Ground::new(&world.scene).expect("terrain");
    let parallel = Ground::new(&world.scene).expect("terrain");
    let asked: Vec<Option<f64>> = pts.iter().map(|&(x, z)| forward.ceiling(x, z)).collect();
    let reversed: Vec<Option<f64>> = pts
        .iter()
        .rev()
        .map(|&(x, z)| backward.ceiling(x, z))
        .collect();
    let at_once: Vec<Option<f64>> = pts
        .par_iter()
        .map(|&(x, z)| parallel.ceiling(x, z))
        .collect();
    assert!(asked.iter().filter(|c| c.is_some()).count() > 1000);
    assert_eq!(asked, reversed.into_iter().rev().collect::<Vec<_>>());
    assert_eq!(asked, at_once);
}
