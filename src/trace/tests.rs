//! Surface-crossing counts through shared edges and vertices (the tie rule),
//! and the BVH against the brute-force oracle.

use super::*;
use crate::rng::Rng;
use glam::{vec3, Mat3, Vec3};

fn all_hits_brute(tris: &[TraceTriangle], ray: &TraceRay) -> Vec<Hit> {
    let mut hits = Vec::new();
    brute_force_hits(tris, ray, |h| {
        hits.push(h);
        f32::INFINITY
    });
    sorted(hits)
}

fn all_hits_bvh(bvh: &Bvh, ray: &TraceRay) -> Vec<Hit> {
    let mut hits = Vec::new();
    bvh.for_each_hit(ray, |h| {
        hits.push(h);
        f32::INFINITY
    });
    sorted(hits)
}

fn sorted(mut hits: Vec<Hit>) -> Vec<Hit> {
    hits.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.triangle.cmp(&b.triangle)));
    hits
}

/// A ray whose origin is exactly the given point, so it passes exactly
/// through it whatever its direction; both ways along the line.
fn line_through(p: Vec3, d: Vec3) -> TraceRay {
    TraceRay {
        origin: p,
        direction: d,
        t_min: -1e4,
        t_max: 1e4,
    }
}

fn random_unit(rng: &mut Rng) -> Vec3 {
    loop {
        let v = vec3(
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
        );
        let l = v.length();
        if l > 0.1 && l <= 1.0 {
            return v / l;
        }
    }
}

const AXES: [Vec3; 6] = [
    Vec3::X,
    Vec3::NEG_X,
    Vec3::Y,
    Vec3::NEG_Y,
    Vec3::Z,
    Vec3::NEG_Z,
];

/// Directions for crossing a surface of normal `n`: the axes that are not
/// parallel to it, the diagonals, and random ones not within ~3° of grazing.
fn crossing_directions(n: Vec3, rng: &mut Rng) -> Vec<Vec3> {
    let mut dirs: Vec<Vec3> = AXES.to_vec();
    for x in [-1.0f32, 1.0] {
        for y in [-1.0f32, 1.0] {
            dirs.push(vec3(x, y, 1.0).normalize());
            dirs.push(vec3(x, y, -1.0).normalize());
            dirs.push(vec3(x, 0.0, y).normalize());
            dirs.push(vec3(0.0, x, y).normalize());
            dirs.push(vec3(x, y, 0.0).normalize());
        }
    }
    for _ in 0..40 {
        dirs.push(random_unit(rng));
    }
    dirs.retain(|d| d.dot(n.normalize()).abs() > 0.05);
    dirs
}

/// An n×n grid of quads over [0,n]² (in the plane's own u, v), mapped by
/// `map`, each quad split into two triangles with alternating diagonals, all
/// wound the same way. Returns the triangles and the grid vertex function.
fn grid(n: i32, map: &dyn Fn(f32, f32) -> Vec3) -> Vec<TraceTriangle> {
    let mut tris = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let p = |a: i32, b: i32| map(a as f32, b as f32);
            let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
            let caster = (i * n + j) as u32;
            if (i + j) % 2 == 0 {
                tris.push(TraceTriangle {
                    vertices: [a, b, c],
                    caster,
                });
                tris.push(TraceTriangle {
                    vertices: [a, c, d],
                    caster,
                });
            } else {
                tris.push(TraceTriangle {
                    vertices: [a, b, d],
                    caster,
                });
                tris.push(TraceTriangle {
                    vertices: [b, c, d],
                    caster,
                });
            }
        }
    }
    tris
}

/// Maps grid coordinates (u, v) onto a plane.
type PlaneMap = Box<dyn Fn(f32, f32) -> Vec3>;

/// The planes the grid tests run on: axis-aligned ones with exact (dyadic)
/// coordinates, where ties really happen, and rotated, offset ones.
fn grid_planes() -> Vec<(PlaneMap, Vec3)> {
    let rot = Mat3::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 1.1);
    vec![
        (Box::new(|u, v| vec3(u, v, 0.0)), Vec3::Z),
        (Box::new(|u, v| vec3(v, 2.5, u)), Vec3::Y),
        (Box::new(|u, v| vec3(-3.0, u * 0.5, v * 0.25)), Vec3::X),
        (
            Box::new(|u, v| vec3(u * 1000.0 + 4096.0, v * 1000.0 - 8192.0, 512.0)),
            Vec3::Z,
        ),
        (
            Box::new(move |u, v| rot * vec3(u * 0.7, v * 1.3, 0.0) + vec3(10.1, -3.3, 7.7)),
            rot * Vec3::Z,
        ),
    ]
}

#[test]
fn grid_interior_edges_and_vertices_are_crossed_once() {
    let mut rng = Rng::new(1);
    let n = 4;
    for (map, normal) in grid_planes() {
        let tris = grid(n, &*map);
        let bvh = Bvh::build(&tris);
        let dirs = crossing_directions(normal, &mut rng);
        // Every interior vertex, every interior edge midpoint (incl.
        // diagonals), and points on edges at a quarter.
        let mut points = Vec::new();
        for i in 0..=2 * n {
            for j in 0..=2 * n {
                let (u, v) = (i as f32 * 0.5, j as f32 * 0.5);
                if u > 0.0 && u < n as f32 && v > 0.0 && v < n as f32 {
                    points.push(map(u, v));
                }
            }
        }
        for i in 1..n {
            for j in 0..n {
                points.push(map(i as f32, j as f32 + 0.25));
                points.push(map(j as f32 + 0.75, i as f32));
            }
        }
        for &p in &points {
            for &d in &dirs {
                let ray = line_through(p, d);
                let hits = all_hits_brute(&tris, &ray);
                assert_eq!(hits.len(), 1, "point {p} direction {d}: {hits:?}");
                assert_eq!(all_hits_bvh(&bvh, &ray), hits);
                assert_eq!(hits[0].back_facing, d.dot(normal) > 0.0);
            }
        }
    }
}

#[test]
fn grid_boundary_is_hit_at_most_once_and_consistently() {
    let mut rng = Rng::new(2);
    let n = 3;
    for (map, normal) in grid_planes() {
        let tris = grid(n, &*map);
        let dirs = crossing_directions(normal, &mut rng);
        let mut points = Vec::new();
        for k in 0..=2 * n {
            let s = k as f32 * 0.5;
            let e = n as f32;
            points.extend([map(s, 0.0), map(s, e), map(0.0, s), map(e, s)]);
        }
        let mut hit_counts = [0usize; 2];
        for &p in &points {
            for &d in &dirs {
                let ray = line_through(p, d);
                let hits = all_hits_brute(&tris, &ray);
                assert!(hits.len() <= 1, "point {p} direction {d}: {hits:?}");
                assert_eq!(all_hits_brute(&tris, &ray), hits, "deterministic");
                hit_counts[hits.len()] += 1;
            }
        }
        // The rule gives boundary points to the mesh from some directions
        // and not from others (it is not "always" or "never").
        assert!(hit_counts[0] > 0 && hit_counts[1] > 0, "{hit_counts:?}");
    }
}

/// A fan of 8 triangles around `centre` whose rim is a square's corners and
/// edge midpoints, in the plane spanned by `u`, `v`.
fn fan(centre: Vec3, u: Vec3, v: Vec3) -> Vec<TraceTriangle> {
    let rim = [
        (1, 0),
        (1, 1),
        (0, 1),
        (-1, 1),
        (-1, 0),
        (-1, -1),
        (0, -1),
        (1, -1),
    ]
    .map(|(a, b)| centre + u * a as f32 + v * b as f32);
    (0..8)
        .map(|k| TraceTriangle {
            vertices: [centre, rim[k], rim[(k + 1) % 8]],
            caster: k as u32,
        })
        .collect()
}

#[test]
fn fan_centre_and_spokes_are_crossed_once() {
    let mut rng = Rng::new(3);
    let rot = Mat3::from_euler(glam::EulerRot::ZYX, 0.9, 0.2, -0.4);
    let fans = [
        (Vec3::ZERO, Vec3::X, Vec3::Y),
        (vec3(1.0, 2.0, 3.0), Vec3::Z, Vec3::X),
        (vec3(-5000.0, 250.0, 3000.0), Vec3::Y * 2.0, Vec3::Z * 2.0),
        (vec3(0.1, 0.2, 0.3), rot * Vec3::X, rot * Vec3::Y),
    ];
    for (centre, u, v) in fans {
        let tris = fan(centre, u, v);
        let normal = u.cross(v);
        let bvh = Bvh::build(&tris);
        let mut points = vec![centre];
        for (a, b) in [
            (1, 0),
            (1, 1),
            (0, 1),
            (-1, 1),
            (-1, 0),
            (-1, -1),
            (0, -1),
            (1, -1),
        ] {
            points.push(centre + (u * a as f32 + v * b as f32) * 0.5);
        }
        for &p in &points {
            for d in crossing_directions(normal, &mut rng) {
                let ray = line_through(p, d);
                let hits = all_hits_brute(&tris, &ray);
                assert_eq!(
                    hits.len(),
                    1,
                    "fan at {centre}, point {p}, direction {d}: {hits:?}"
                );
                assert_eq!(all_hits_bvh(&bvh, &ray), hits);
            }
        }
    }
}

/// A closed box, 12 triangles wound outwards, transformed by `map`.
fn closed_box(map: &dyn Fn(Vec3) -> Vec3) -> Vec<TraceTriangle> {
    // Corner k has coordinates (k & 1, k >> 1 & 1, k >> 2 & 1), scaled by 2.
    let c = |k: usize| map(vec3((k & 1) as f32, (k >> 1 & 1) as f32, (k >> 2 & 1) as f32) * 2.0);
    // Each face as a quad wound counter-clockwise seen from outside.
    let faces = [
        [0, 2, 3, 1], // z = 0
        [4, 5, 7, 6], // z = 2
        [0, 1, 5, 4], // y = 0
        [2, 6, 7, 3], // y = 2
        [0, 4, 6, 2], // x = 0
        [1, 3, 7, 5], // x = 2
    ];
    let mut tris = Vec::new();
    for (f, q) in faces.iter().enumerate() {
        tris.push(TraceTriangle {
            vertices: [c(q[0]), c(q[1]), c(q[2])],
            caster: f as u32,
        });
        tris.push(TraceTriangle {
            vertices: [c(q[0]), c(q[2]), c(q[3])],
            caster: f as u32,
        });
    }
    tris
}

#[test]
fn closed_box_is_entered_and_left_once_through_corners_and_edges() {
    let rot = Mat3::from_euler(glam::EulerRot::XYZ, 0.5, 1.2, -0.3);
    let maps: Vec<Box<dyn Fn(Vec3) -> Vec3>> = vec![
        Box::new(|p| p),
        Box::new(|p| p * 3.0 + vec3(-4000.0, 1000.0, 2500.0)),
        Box::new(move |p| rot * p + vec3(0.3, -7.1, 2.2)),
    ];
    let mut rng = Rng::new(4);
    for map in maps {
        let tris = closed_box(&*map);
        // Outward normals must be right for the facing check.
        let centre = map(Vec3::ONE);
        for t in &tris {
            let [a, b, c] = t.vertices;
            assert!((b - a).cross(c - a).dot(a - centre) > 0.0);
        }
        let bvh = Bvh::build(&tris);
        // Surface points in box coordinates: corners, edge midpoints, face
        // centres and face-diagonal points, and random face points.
        let mut surface: Vec<Vec3> = Vec::new();
        for x in 0..=2 {
            for y in 0..=2 {
                for z in 0..=2 {
                    let p = vec3(x as f32, y as f32, z as f32);
                    if x != 1 || y != 1 || z != 1 {
                        surface.push(p);
                    }
                }
            }
        }
        for _ in 0..20 {
            let mut p = vec3(
                rng.range(0.0, 2.0) as f32,
                rng.range(0.0, 2.0) as f32,
                rng.range(0.0, 2.0) as f32,
            );
            p[rng.below(3)] = 2.0 * rng.below(2) as f32;
            surface.push(p);
        }
        surface.push(vec3(0.5, 0.5, 0.0)); // on the z = 0 face diagonal
        let mut checked = 0;
        for &a in &surface {
            for &b in &surface {
                // The segment a–b passes through the interior iff a and b are
                // not on a common face.
                let common_face = (0..3).any(|i| a[i] == b[i] && (a[i] == 0.0 || a[i] == 2.0));
                if common_face {
                    continue;
                }
                let (pa, pb) = (map(a), map(b));
                let ray = line_through(pa, (pb - pa).normalize());
                let hits = all_hits_brute(&tris, &ray);
                assert_eq!(hits.len(), 2, "box through {a} and {b}: {hits:?}");
                assert!(!hits[0].back_facing && hits[1].back_facing, "{hits:?}");
                assert_eq!(all_hits_bvh(&bvh, &ray), hits);
                checked += 1;
            }
        }
        assert!(checked > 500, "{checked}");
        // Axis-aligned rays through corners and edges (origin outside).
        if map(Vec3::ZERO) == Vec3::ZERO {
            for &a in &surface {
                for axis in 0..3 {
                    let mut through = a;
                    through[axis] = 1.0;
                    // Only lines that pass through the interior.
                    let interior =
                        (0..3).all(|i| i == axis || (through[i] > 0.0 && through[i] < 2.0));
                    if !interior {
                        continue;
                    }
                    let mut d = Vec3::ZERO;
                    d[axis] = 1.0;
                    let hits = all_hits_brute(&tris, &line_through(through, d));
                    assert_eq!(hits.len(), 2, "axis {axis} through {through}: {hits:?}");
                }
            }
        }
    }
}

/// Lines exactly through a box's corners, edges and face points in every
/// direction: through the interior exactly 2 hits; touching only the surface
/// (silhouette corners and edges, where a front and a back facing triangle
/// meet) an even count, never 1 or 3 — which needs the tie rule on
/// orientation-normalised edges.
#[test]
fn lines_grazing_a_box_corner_or_edge_cross_it_an_even_number_of_times() {
    let tris = closed_box(&|p| p);
    let mut rng = Rng::new(5);
    let mut dirs: Vec<Vec3> = AXES.to_vec();
    for x in -1..=1 {
        for y in -1..=1 {
            for z in -1..=1 {
                if (x, y, z) != (0, 0, 0) {
                    dirs.push(vec3(x as f32, y as f32, z as f32).normalize());
                }
            }
        }
    }
    for _ in 0..60 {
        dirs.push(random_unit(&mut rng));
    }
    let mut counts = [0usize; 3];
    for x in 0..=2 {
        for y in 0..=2 {
            for z in 0..=2 {
                if (x, y, z) == (1, 1, 1) {
                    continue;
                }
                let a = vec3(x as f32, y as f32, z as f32);
                for &d in &dirs {
                    // Does the exact line a + t·d meet the open box (0,2)³?
                    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
                    for i in 0..3 {
                        let (o, di) = (a[i] as f64, d[i] as f64);
                        if di == 0.0 {
                            if !(o > 0.0 && o < 2.0) {
                                hi = f64::NEG_INFINITY;
                            }
                        } else {
                            let (t0, t1) = ((0.0 - o) / di, (2.0 - o) / di);
                            lo = lo.max(t0.min(t1));
                            hi = hi.min(t0.max(t1));
                        }
                    }
                    let interior = lo < hi;
                    let hits = all_hits_brute(&tris, &line_through(a, d));
                    if interior {
                        assert_eq!(hits.len(), 2, "through {a} along {d}: {hits:?}");
                    } else {
                        assert!(
                            hits.len().is_multiple_of(2),
                            "grazing {a} along {d}: {hits:?}"
                        );
                    }
                    counts[hits.len().min(2)] += 1;
                }
            }
        }
    }
    // Many lines go through, and many only touch.
    assert!(counts[0] > 100 && counts[2] > 100, "{counts:?}");
}

/// A random triangle soup of the kinds the bake meets: ordinary triangles,
/// flat axis-aligned planes (zero-thickness boxes), tiny and huge ones,
/// coordinates up to ±1e4.
fn soup(rng: &mut Rng, count: usize) -> Vec<TraceTriangle> {
    let mut tris = Vec::with_capacity(count);
    let p = |rng: &mut Rng, s: f64| {
        vec3(
            rng.range(-s, s) as f32,
            rng.range(-s, s) as f32,
            rng.range(-s, s) as f32,
        )
    };
    while tris.len() < count {
        let caster = tris.len() as u32;
        match rng.below(6) {
            0 | 1 => {
                let c = p(rng, 100.0);
                let s = 10f64.powf(rng.range(-1.0, 1.5));
                tris.push(TraceTriangle {
                    vertices: [c + p(rng, s), c + p(rng, s), c + p(rng, s)],
                    caster,
                });
            }
            2 => {
                // A flat axis-aligned quad pair on an integer plane.
                let axis = rng.below(3);
                let level = rng.below(41) as f32 * 5.0 - 100.0;
                let (x0, y0) = (
                    rng.below(40) as f32 * 5.0 - 100.0,
                    rng.below(40) as f32 * 5.0 - 100.0,
                );
                let q = |x: f32, y: f32| {
                    let mut v = Vec3::splat(level);
                    v[(axis + 1) % 3] = x;
                    v[(axis + 2) % 3] = y;
                    v
                };
                let (a, b, c, d) = (
                    q(x0, y0),
                    q(x0 + 5.0, y0),
                    q(x0 + 5.0, y0 + 5.0),
                    q(x0, y0 + 5.0),
                );
                tris.push(TraceTriangle {
                    vertices: [a, b, c],
                    caster,
                });
                tris.push(TraceTriangle {
                    vertices: [a, c, d],
                    caster,
                });
            }
            3 => {
                let c = p(rng, 100.0);
                let s = 10f64.powf(rng.range(-4.0, -2.0));
                tris.push(TraceTriangle {
                    vertices: [c + p(rng, s), c + p(rng, s), c + p(rng, s)],
                    caster,
                });
            }
            4 => {
                tris.push(TraceTriangle {
                    vertices: [p(rng, 1e4), p(rng, 1e4), p(rng, 1e4)],
                    caster,
                });
            }
            _ => {
                // Vertical walls (box thin in one axis) and slivers.
                let a = p(rng, 100.0);
                let mut b = a + p(rng, 20.0);
                b.x = a.x;
                let mut c = a + p(rng, 20.0);
                c.x = a.x;
                tris.push(TraceTriangle {
                    vertices: [a, b, c],
                    caster,
                });
            }
        }
    }
    tris
}

fn random_rays(rng: &mut Rng, tris: &[TraceTriangle], count: usize) -> Vec<TraceRay> {
    let mut rays = Vec::with_capacity(count);
    while rays.len() < count {
        let tri = tris[rng.below(tris.len())];
        let vertex = tri.vertices[rng.below(3)];
        let (origin, direction) = match rng.below(5) {
            // Random lines through the scene.
            0 => {
                let o = vec3(
                    rng.range(-150.0, 150.0) as f32,
                    rng.range(-150.0, 150.0) as f32,
                    rng.range(-150.0, 150.0) as f32,
                );
                (o, random_unit(rng))
            }
            // Axis-parallel, exactly through a vertex (along box faces).
            1 => {
                let axis = rng.below(6);
                let d = AXES[axis];
                let mut o = vertex;
                o[axis / 2] -= d[axis / 2] * 300.0;
                (o, d)
            }
            // Axis-parallel from a random point.
            2 => {
                let o = vec3(
                    rng.range(-120.0, 120.0) as f32,
                    rng.range(-120.0, 120.0) as f32,
                    rng.range(-120.0, 120.0) as f32,
                );
                (o, AXES[rng.below(6)])
            }
            // Aimed at a point inside a triangle, from afar.
            3 => {
                let (a, b) = (rng.unit() as f32, rng.unit() as f32);
                let (a, b) = if a + b > 1.0 {
                    (1.0 - a, 1.0 - b)
                } else {
                    (a, b)
                };
                let [v0, v1, v2] = tri.vertices;
                let target = v0 + (v1 - v0) * a + (v2 - v0) * b;
                let o = target + random_unit(rng) * rng.range(1.0, 300.0) as f32;
                (o, (target - o).normalize())
            }
            // Starting exactly at a vertex, nearly axis-parallel.
            _ => {
                let mut d = AXES[rng.below(6)];
                d += vec3(1e-9, -3e-8, 2e-7) * rng.range(-1.0, 1.0) as f32;
                (vertex, d.normalize())
            }
        };
        if !direction.is_finite() {
            continue;
        }
        let (t_min, t_max) = match rng.below(3) {
            0 => (0.0, f32::INFINITY),
            1 => (-1e5, 1e5),
            _ => (rng.range(0.0, 50.0) as f32, rng.range(50.0, 400.0) as f32),
        };
        rays.push(TraceRay {
            origin,
            direction,
            t_min,
            t_max,
        });
    }
    rays
}

#[test]
fn bvh_agrees_with_brute_force_on_random_soups() {
    let mut total_hits = 0;
    for seed in 0..4 {
        let mut rng = Rng::new(100 + seed);
        let tris = soup(&mut rng, 3000);
        let bvh = Bvh::build(&tris);
        assert_eq!(bvh.triangle_count(), tris.len());
        for ray in random_rays(&mut rng, &tris, 1500) {
            let expected = all_hits_brute(&tris, &ray);
            assert_eq!(
                all_hits_bvh(&bvh, &ray),
                expected,
                "seed {seed} ray {ray:?}"
            );
            total_hits += expected.len();

            // A caller that stops looking 0.5 beyond its nearest hit.
            let (mut a, mut b) = (Vec::new(), Vec::new());
            brute_force_hits(&tris, &ray, |h| {
                a.push(h);
                h.t + 0.5
            });
            bvh.for_each_hit(&ray, |h| {
                b.push(h);
                h.t + 0.5
            });
            let cutoff = expected.first().map_or(f32::NEG_INFINITY, |h| h.t + 0.5);
            let keep = |v: Vec<Hit>| sorted(v.into_iter().filter(|h| h.t <= cutoff).collect());
            let want: Vec<Hit> = expected.iter().copied().filter(|h| h.t <= cutoff).collect();
            assert_eq!(keep(a), want);
            assert_eq!(keep(b), want, "shrinking, seed {seed} ray {ray:?}");
            assert_eq!(bvh.closest_hit(&ray), expected.first().copied());
        }
    }
    assert!(total_hits > 5000, "{total_hits}");
}

#[test]
fn hits_do_not_depend_on_threads_or_bvh_shape() {
    let mut rng = Rng::new(7);
    let tris = soup(&mut rng, 4000);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let bvh1 = one.install(|| Bvh::build(&tris));
    let bvh2 = Bvh::build(&tris);
    // A different shape: the same triangles in reverse order.
    let reversed: Vec<TraceTriangle> = tris.iter().rev().copied().collect();
    let bvh3 = Bvh::build(&reversed);
    let n = tris.len() as u32;
    for ray in random_rays(&mut rng, &tris, 1000) {
        let h1 = all_hits_bvh(&bvh1, &ray);
        assert_eq!(all_hits_bvh(&bvh2, &ray), h1);
        let h3: Vec<Hit> = all_hits_bvh(&bvh3, &ray)
            .into_iter()
            .map(|h| Hit {
                triangle: n - 1 - h.triangle,
                ..h
            })
            .collect();
        assert_eq!(sorted(h3), h1);
    }
}

#[test]
fn flat_plane_rays_along_axes_and_box_faces() {
    // A 20×20 grid on z = 0 (every box zero-thick in z), and rays along the
    // axes exactly through its vertices, edges and faces, from both sides,
    // and rays lying in the plane (edge-on: no hits).
    let tris = grid(20, &|u, v| vec3(u - 10.0, v - 10.0, 0.0));
    let bvh = Bvh::build(&tris);
    let mut rng = Rng::new(9);
    for i in 0..=40 {
        for j in 0..=40 {
            let (x, y) = (i as f32 * 0.5 - 10.0, j as f32 * 0.5 - 10.0);
            for (z, dz) in [(5.0, -1.0), (-5.0, 1.0), (0.0, 1.0)] {
                let ray = TraceRay {
                    origin: vec3(x, y, z),
                    direction: vec3(0.0, 0.0, dz),
                    t_min: if z == 0.0 { 0.0 } else { 0.5 },
                    t_max: 100.0,
                };
                let hits = all_hits_brute(&tris, &ray);
                let inside = x.abs() < 10.0 && y.abs() < 10.0;
                if inside {
                    assert_eq!(hits.len(), 1, "{ray:?}");
                    assert_eq!(hits[0].t, z.abs());
                }
                assert_eq!(all_hits_bvh(&bvh, &ray), hits, "{ray:?}");
            }
            let in_plane = TraceRay {
                origin: vec3(x, y, 0.0),
                direction: random_unit(&mut rng) * vec3(1.0, 1.0, 0.0),
                t_min: -50.0,
                t_max: 50.0,
            };
            if in_plane.direction.length() > 0.1 {
                assert!(all_hits_brute(&tris, &in_plane).is_empty());
                assert!(all_hits_bvh(&bvh, &in_plane).is_empty());
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Instances and height fields: the trees against the oracle, ray by ray.

mod two_level {
    use super::super::*;
    use crate::rng::Rng;
    use glam::{DMat4, DQuat, DVec3, Vec3};

    /// Blocks of `cells`² cells of `size` metres in an `n` × `n` grid with
    /// random heights that agree on shared borders (one height function
    /// of world x, z), some holes.
    fn terrain(n: i32, cells: usize, size: f64, holes: bool) -> Vec<(Vec<f32>, Vec<bool>, DVec3)> {
        let h = |x: f64, z: f64| ((x * 0.37).sin() * 2.0 + (z * 0.21).cos() * 1.5) as f32;
        let mut out = Vec::new();
        for gz in 0..n {
            for gx in 0..n {
                let origin = DVec3::new(gx as f64 * size, 0.5, gz as f64 * size);
                let mut heights = Vec::new();
                for z in 0..=cells {
                    for x in 0..=cells {
                        let wx = origin.x + x as f64 * size / cells as f64;
                        let wz = origin.z + z as f64 * size / cells as f64;
                        heights.push(h(wx, wz));
                    }
                }
                let mut hole = vec![false; cells * cells];
                if holes {
                    // A hole at the block's +x border, next to the neighbour.
                    hole[(cells / 2) * cells + cells - 1] = true;
                }
                out.push((heights, hole, origin));
            }
        }
        out
    }

    fn grids(
        blocks: &[(Vec<f32>, Vec<bool>, DVec3)],
        cells: usize,
        size: f64,
    ) -> Vec<HeightGrid<'_>> {
        blocks
            .iter()
            .map(|(heights, holes, origin)| HeightGrid {
                origin: *origin,
                chunk_size: size,
                cells_x: cells,
                cells_z: cells,
                heights: crate::trace::heightfield::Heights::Held(heights),
                holes,
                alternating: true,
                extremes: crate::trace::heightfield::extremes_of(heights),
            })
            .collect()
    }

    fn hits(tracer: &Tracer, ray: &TraceRay) -> Vec<(u32, u32, bool, u32)> {
        let mut out = Vec::new();
        tracer.for_each_hit(ray, |h| {
            out.push((h.t.to_bits(), h.caster, h.back_facing, h.triangle));
            f32::INFINITY
        });
        out.sort();
        out
    }

    #[test]
    fn terrain_edges_diagonals_borders_and_vertices_are_crossed_once() {
        // 3 cells of 100/3 m: the cell edges are not exact in binary, so
        // only one vertex function keeps shared vertices bit-equal.
        let (cells, size) = (3, 100.0);
        let blocks = terrain(2, cells, size, false);
        let bottom = BottomLevels::build(0, |_| Vec::new(), grids(&blocks, cells, size));
        let reference = DVec3::new(37.0, 0.0, 61.0);
        let placed = (0..4).map(|b| PlacedBlock {
            block: b,
            caster: b,
        });
        let top = TopLevel::build(&bottom, &[][..], placed, reference);
        let trees = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        let oracle = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::BruteForce,
        };
        let mut checked = 0;
        // Every vertex, every edge midpoint and every diagonal point of the
        // 6 × 6 cells, straight down and slanted.
        for zi in 0..=2 * 2 * cells {
            for xi in 0..=2 * 2 * cells {
                let step = size / cells as f64 / 2.0;
                let (wx, wz) = (xi as f64 * step, zi as f64 * step);
                if wx >= 2.0 * size || wz >= 2.0 * size {
                    continue;
                }
                for d in [
                    Vec3::NEG_Y,
                    Vec3::new(0.3, -1.0, 0.2).normalize(),
                    Vec3::new(-0.5, -1.0, 0.0).normalize(),
                ] {
                    // The ray passes exactly through the lattice point on
                    // the surface: its origin is the surface point itself
                    // (light-relative, as the vertex function rounds it),
                    // the segment reaching 50 m both ways.
                    let p = DVec3::new(wx, 0.0, wz) - reference;
                    let origin = Vec3::new(p.x as f32, 40.0, p.z as f32);
                    let ray = TraceRay {
                        origin,
                        direction: d,
                        t_min: 0.0,
                        t_max: 200.0,
                    };
                    let a = hits(&trees, &ray);
                    assert_eq!(a, hits(&oracle, &ray), "ray {ray:?}");
                    // Solid terrain everywhere: a ray from above crosses it
                    // exactly once (no leak at an edge, no double crossing).
                    let inside = |q: Vec3| {
                        let w = q.as_dvec3() + reference;
                        w.x > 0.0 && w.z > 0.0 && w.x < 2.0 * size && w.z < 2.0 * size
                    };
                    let exit = origin + d * 60.0;
                    if inside(origin) && inside(exit) && d == Vec3::NEG_Y {
                        assert_eq!(a.len(), 1, "ray {ray:?}: {a:?}");
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 300);
    }

    #[test]
    fn vertical_rays_exactly_on_block_borders_cross_once() {
        // Rays straight down exactly on x = 100 (the border of blocks 0 and
        // 1) at many z, on z = 100, and on the corner shared by all four
        // blocks, for many reference points off the lattice, as a light's
        // usually is: the border then lies at an f32 value that only the
        // shared vertex function reproduces exactly on both sides. Any other
        // arithmetic for a block's vertices (its own origin rounded to f32,
        // then its offsets added) puts some border one ulp apart on the two
        // sides for some of these references, and rays there cross zero or
        // two times.
        let (cells, size) = (3, 100.0);
        let blocks = terrain(2, cells, size, false);
        let bottom = BottomLevels::build(0, |_| Vec::new(), grids(&blocks, cells, size));
        let mut rng = Rng::new(5);
        for _ in 0..64 {
            let reference = DVec3::new(rng.range(-300.0, 300.0), 0.0, rng.range(-300.0, 300.0));
            let placed = (0..4).map(|b| PlacedBlock {
                block: b,
                caster: b,
            });
            let top = TopLevel::build(&bottom, &[][..], placed, reference);
            let trees = Tracer {
                bottom: &bottom,
                top: &top,
                mode: TraceMode::Trees,
            };
            for k in 0..60 {
                let along = rng.range(1.0, 199.0);
                let (x, z) = match k % 3 {
                    0 => (100.0, along),
                    1 => (along, 100.0),
                    _ => (100.0, 100.0),
                };
                let p = (DVec3::new(x, 0.0, z) - reference).as_vec3();
                let ray = TraceRay {
                    origin: Vec3::new(p.x, 30.0, p.z),
                    direction: Vec3::NEG_Y,
                    t_min: 0.0,
                    t_max: 100.0,
                };
                let found = hits(&trees, &ray);
                assert_eq!(found.len(), 1, "({x}, {z}) from {reference}: {found:?}");
            }
        }
    }

    /// Per ray of `rays` (one packet), how many hits it gets when traced
    /// with only caster `only` unsettled, each hit asserted to be on it.
    fn hits_meeting_only(tracer: &Tracer, rays: &[TraceRay], only: u32) -> Vec<usize> {
        let unsettled = |c: u32| c == only;
        let mut hit = vec![0; rays.len()];
        let mut scratch = PacketScratch::default();
        let (cull, which) = (
            FaceCull::default(),
            PacketRays::MeetingUnsettled(&unsettled),
        );
        tracer.for_each_packet_hit_culled(rays, &mut scratch, &cull, which, |lane, h| {
            assert_eq!(h.caster, only);
            hit[lane] += 1;
            f32::INFINITY
        });
        hit
    }

    #[test]
    fn a_packet_keeps_the_rays_that_may_reach_an_unsettled_group_of_a_part() {
        // One model, two groups: a 2 m card round x = 0 (group 0) and one
        // round x = 10 (group 1), placed once (casters 0 and 1). A packet
        // of rays straight down, eight columns 0.5 m apart over the first
        // card (x −1.75..1.75). With only caster 1 unsettled no ray can meet
        // it, though every ray crosses the model's box; with caster 0, the
        // rays over its card (|x| < 1) are kept and only they get hits.
        let card = |x: f32, group: u32| {
            let p = |dx: f32, dz: f32| Vec3::new(x + dx, 0.0, dz);
            [
                TraceTriangle {
                    vertices: [p(-1.0, -1.0), p(-1.0, 1.0), p(1.0, 1.0)],
                    caster: group,
                },
                TraceTriangle {
                    vertices: [p(1.0, 1.0), p(1.0, -1.0), p(-1.0, -1.0)],
                    caster: group,
                },
            ]
        };
        let model: Vec<TraceTriangle> = card(0.0, 0).into_iter().chain(card(10.0, 1)).collect();
        let bottom = BottomLevels::build(1, |_| model.clone(), Vec::new());
        let parts = [PlacedPart {
            model: 0,
            world: DMat4::IDENTITY,
            first_caster: 0,
        }];
        let top = TopLevel::build(&bottom, &parts[..], std::iter::empty(), DVec3::ZERO);
        let tracer = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        let rays: Vec<TraceRay> = (0..64)
            .map(|i| TraceRay {
                origin: Vec3::new(
                    -1.75 + (i % 8) as f32 * 0.5,
                    30.0,
                    -0.75 + (i / 8) as f32 * 0.2,
                ),
                direction: Vec3::NEG_Y,
                t_min: 0.0,
                t_max: 100.0,
            })
            .collect();
        let mut scratch = PacketScratch::default();
        let mut keep = Vec::new();
        assert_eq!(
            tracer.rays_reaching(&rays, &mut scratch, &|c| c == 1, &mut keep),
            0
        );
        let kept = tracer.rays_reaching(&rays, &mut scratch, &|c| c == 0, &mut keep);
        assert_eq!(kept, 32);
        for (ray, k) in rays.iter().zip(&keep) {
            assert_eq!(*k, ray.origin.x.abs() < 1.0, "{ray:?}");
        }
        let hit = hits_meeting_only(&tracer, &rays, 0);
        for (ray, n) in rays.iter().zip(&hit) {
            assert_eq!(*n, usize::from(ray.origin.x.abs() < 1.0), "{ray:?}");
        }
    }

    #[test]
    fn a_packet_keeps_the_rays_that_may_reach_an_unsettled_block() {
        // Four 100 m blocks (2×2); rays straight down, 8×8 of them 0.5 m
        // apart: over block 0 alone (x, z 10..13.5), or across the border
        // of blocks 0 and 1 (x 98.25..101.75: four columns each side).
        let (cells, size) = (4, 100.0);
        let blocks = terrain(2, cells, size, false);
        let bottom = BottomLevels::build(0, |_| Vec::new(), grids(&blocks, cells, size));
        let placed = (0..4).map(|b| PlacedBlock {
            block: b,
            caster: b,
        });
        let top = TopLevel::build(&bottom, &[][..], placed, DVec3::ZERO);
        let mut tracer = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        let packet = |x0: f32, t_max: f32| -> Vec<TraceRay> {
            (0..64)
                .map(|i| TraceRay {
                    origin: Vec3::new(x0 + (i % 8) as f32 * 0.5, 30.0, 10.0 + (i / 8) as f32 * 0.5),
                    direction: Vec3::NEG_Y,
                    t_min: 0.0,
                    t_max,
                })
                .collect()
        };
        let (inside, across) = (packet(10.0, 100.0), packet(98.25, 100.0));
        let mut scratch = PacketScratch::default();
        let mut keep = Vec::new();
        let mut kept = |tracer: &Tracer, rays: &[TraceRay], unsettled: &dyn Fn(u32) -> bool| {
            let n = tracer.rays_reaching(rays, &mut scratch, unsettled, &mut keep);
            assert_eq!(n, keep.iter().filter(|&&k| k).count());
            (n, keep.clone())
        };
        assert_eq!(kept(&tracer, &inside, &|c| c == 0).0, 64);
        assert_eq!(kept(&tracer, &inside, &|c| c != 0).0, 0);
        assert_eq!(kept(&tracer, &inside, &|_| false).0, 0);
        // Across the border: the rays over block 1 only.
        let (n, keep_1) = kept(&tracer, &across, &|c| c == 1);
        assert_eq!(n, 32);
        for (ray, k) in across.iter().zip(&keep_1) {
            assert_eq!(*k, ray.origin.x > 100.0, "{ray:?}");
        }
        assert_eq!(kept(&tracer, &across, &|c| c <= 1).0, 64);
        // Traced so, the rays over block 1 get their hits there, the
        // others none.
        let hit = hits_meeting_only(&tracer, &across, 1);
        for (ray, n) in across.iter().zip(&hit) {
            assert_eq!(*n, usize::from(ray.origin.x > 100.0), "{ray:?}");
        }
        // Rays ending above the ground reach nothing.
        assert_eq!(kept(&tracer, &packet(10.0, 5.0), &|_| true).0, 0);
        // Without the trees every ray is kept.
        tracer.mode = TraceMode::BruteForce;
        assert_eq!(kept(&tracer, &inside, &|_| false).0, 64);
    }

    #[test]
    fn holes_at_a_block_border_let_rays_through_and_match_the_oracle() {
        let (cells, size) = (4, 100.0);
        let blocks = terrain(2, cells, size, true);
        let bottom = BottomLevels::build(0, |_| Vec::new(), grids(&blocks, cells, size));
        let placed = (0..4).map(|b| PlacedBlock {
            block: b,
            caster: b,
        });
        let top = TopLevel::build(&bottom, &[][..], placed, DVec3::ZERO);
        let trees = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        let oracle = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::BruteForce,
        };
        // Block 0's hole is its cell (3, 2): x 75..100, z 50..75.
        let down = |x: f32, z: f32| TraceRay {
            origin: Vec3::new(x, 30.0, z),
            direction: Vec3::NEG_Y,
            t_min: 0.0,
            t_max: 100.0,
        };
        assert!(hits(&trees, &down(90.0, 60.0)).is_empty());
        assert_eq!(hits(&trees, &down(110.0, 60.0)).len(), 1);
        let mut rng = Rng::new(9);
        for _ in 0..500 {
            let d = Vec3::new(
                rng.range(-1.0, 1.0) as f32,
                -1.0,
                rng.range(-1.0, 1.0) as f32,
            )
            .normalize();
            let ray = TraceRay {
                origin: Vec3::new(
                    rng.range(60.0, 140.0) as f32,
                    20.0,
                    rng.range(30.0, 90.0) as f32,
                ),
                direction: d,
                t_min: 0.0,
                t_max: 100.0,
            };
            assert_eq!(hits(&trees, &ray), hits(&oracle, &ray));
        }
    }

    /// Two models placed 300 times: rotated, non-uniformly scaled,
    /// mirrored, far from the origin (1e5 m), over terrain; and one cube
    /// unrotated at the reference point, so model space is the
    /// light-relative frame and rays can run exactly along its edges.
    struct Instanced {
        blocks: Vec<(Vec<f32>, Vec<bool>, DVec3)>,
        models: [Vec<TraceTriangle>; 2],
        parts: Vec<PlacedPart>,
        reference: DVec3,
    }

    fn cube(s: f32) -> Vec<TraceTriangle> {
        // Two triangles a face, wound outward.
        let mut out = Vec::new();
        for axis in 0..3 {
            for sign in [-1.0f32, 1.0] {
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let corner = |a: f32, b: f32| {
                    let mut p = Vec3::ZERO;
                    p[axis] = sign * s;
                    p[u] = a * s;
                    p[v] = b * s * sign;
                    p
                };
                let q = [
                    corner(-1.0, -1.0),
                    corner(1.0, -1.0),
                    corner(1.0, 1.0),
                    corner(-1.0, 1.0),
                ];
                out.push(TraceTriangle {
                    vertices: [q[0], q[1], q[2]],
                    caster: 0,
                });
                out.push(TraceTriangle {
                    vertices: [q[0], q[2], q[3]],
                    caster: 0,
                });
            }
        }
        out
    }

    fn instanced(rng: &mut Rng) -> Instanced {
        let offset = DVec3::new(1e5, 0.0, -1e5);
        let card = vec![
            TraceTriangle {
                vertices: [
                    Vec3::new(-1.0, 0.0, -1.0),
                    Vec3::new(-1.0, 0.0, 1.0),
                    Vec3::new(1.0, 0.0, 1.0),
                ],
                caster: 0,
            },
            TraceTriangle {
                vertices: [
                    Vec3::new(1.0, 0.0, 1.0),
                    Vec3::new(1.0, 0.0, -1.0),
                    Vec3::new(-1.0, 0.0, -1.0),
                ],
                caster: 1,
            },
        ];
        let models = [cube(0.75), card];
        let blocks: Vec<(Vec<f32>, Vec<bool>, DVec3)> = terrain(1, 8, 100.0, true)
            .into_iter()
            .map(|(h, holes, o)| (h, holes, o + offset))
            .collect();
        let mut parts = Vec::new();
        for i in 0..300 {
            let mut scale = DVec3::new(
                rng.range(0.3, 3.0),
                rng.range(0.3, 3.0),
                rng.range(0.3, 3.0),
            );
            if rng.below(3) == 0 {
                scale.x = -scale.x;
            }
            let rotation = DQuat::from_euler(
                glam::EulerRot::YXZ,
                rng.range(0.0, 6.3),
                rng.range(-0.6, 0.6),
                rng.range(-0.6, 0.6),
            );
            let position = offset
                + DVec3::new(
                    rng.range(0.0, 100.0),
                    rng.range(0.0, 5.0),
                    rng.range(0.0, 100.0),
                );
            parts.push(PlacedPart {
                model: i % 2,
                world: DMat4::from_scale_rotation_translation(scale, rotation, position),
                first_caster: 10 + 2 * i,
            });
        }
        let reference = offset + DVec3::new(50.0, 0.0, 50.0);
        parts.push(PlacedPart {
            model: 0,
            world: DMat4::from_translation(reference + DVec3::new(0.0, 10.0, 0.0)),
            first_caster: 5,
        });
        // Stacks of coincident copies (an editor's duplicate key): five of
        // a cube part, four of a mirrored card (whose copies' ids give the
        // culling tests' double-sided bits to some and not others), and a
        // copy of a part placed first in the list, far from the rest of
        // its stack.
        let cube = parts[4];
        parts.extend((0..5).map(|k| PlacedPart {
            first_caster: 650 + k,
            ..cube
        }));
        let card = PlacedPart {
            model: 1,
            world: DMat4::from_scale_rotation_translation(
                DVec3::new(-1.5, 1.0, 2.0),
                DQuat::from_rotation_y(0.4),
                reference + DVec3::new(-10.0, 3.0, 6.0),
            ),
            first_caster: 720,
        };
        parts.extend((0..4).map(|k| PlacedPart {
            first_caster: 720 + 2 * k,
            ..card
        }));
        let early = PlacedPart {
            first_caster: 660,
            ..parts[9]
        };
        parts.insert(0, early);
        Instanced {
            blocks,
            models,
            parts,
            reference,
        }
    }

    #[test]
    fn instanced_models_match_the_oracle_ray_by_ray() {
        let mut rng = Rng::new(17);
        let world = instanced(&mut rng);
        let bottom = BottomLevels::build(
            2,
            |m| world.models[m].clone(),
            grids(&world.blocks, 8, 100.0),
        );
        let top = TopLevel::build(
            &bottom,
            &world.parts[..],
            std::iter::once(PlacedBlock {
                block: 0,
                caster: 1,
            }),
            world.reference,
        );
        let trees = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        let oracle = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::BruteForce,
        };
        let mut with_hits = 0;
        for _ in 0..3000 {
            let d = Vec3::new(
                rng.range(-1.0, 1.0) as f32,
                rng.range(-1.0, -0.1) as f32,
                rng.range(-1.0, 1.0) as f32,
            )
            .normalize();
            let ray = TraceRay {
                origin: Vec3::new(
                    rng.range(-60.0, 60.0) as f32,
                    30.0,
                    rng.range(-60.0, 60.0) as f32,
                ),
                direction: d,
                t_min: 0.0,
                t_max: 200.0,
            };
            let a = hits(&trees, &ray);
            with_hits += usize::from(a.len() > 1);
            assert_eq!(a, hits(&oracle, &ray), "ray {ray:?}");
        }
        assert!(with_hits > 200, "{with_hits}");
    }

    /// A part's model-space triangle in the light-relative frame, as a
    /// flat list of the placed world holds it.
    fn placed(part: &PlacedPart, tri: &TraceTriangle, reference: DVec3) -> TraceTriangle {
        let mut vertices = tri
            .vertices
            .map(|p| (part.world.transform_point3(p.as_dvec3()) - reference).as_vec3());
        if part.world.determinant() < 0.0 {
            vertices.swap(1, 2);
        }
        TraceTriangle {
            vertices,
            caster: part.first_caster + tri.caster,
        }
    }

    #[test]
    fn placed_hits_are_those_of_the_flat_placed_world() {
        let mut rng = Rng::new(29);
        let world = instanced(&mut rng);
        let bottom = BottomLevels::build(
            2,
            |m| world.models[m].clone(),
            grids(&world.blocks, 8, 100.0),
        );
        let block = PlacedBlock {
            block: 0,
            caster: 1,
        };
        let top = TopLevel::build(
            &bottom,
            &world.parts[..],
            std::iter::once(block),
            world.reference,
        );
        let reference = world.reference;
        let mut flat: Vec<TraceTriangle> = Vec::new();
        for part in &world.parts {
            flat.extend(
                world.models[part.model as usize]
                    .iter()
                    .map(|t| placed(part, t, reference)),
            );
        }
        let grid = &bottom.terrain[0].grid;
        for cz in 0..8 {
            for cx in 0..8 {
                let pair = grid.cell_trace_triangles((cx, cz), reference, 1);
                flat.extend(pair.into_iter().flatten().map(|(t, _)| t));
            }
        }
        let part_of = |first_caster: u32| {
            world
                .parts
                .iter()
                .find(|p| p.first_caster == first_caster)
                .unwrap()
        };
        let key = |h: &Hit, t: &TraceTriangle| {
            (
                h.t.to_bits(),
                h.caster,
                h.back_facing,
                t.vertices.map(|v| v.to_array().map(f32::to_bits)),
            )
        };
        let (mut with_hits, mut through_vertices) = (0, 0);
        for k in 0..4000 {
            let origin = Vec3::new(
                rng.range(-80.0, 80.0) as f32,
                40.0,
                rng.range(-80.0, 80.0) as f32,
            );
            // Half the rays aim exactly at a vertex or an edge's midpoint
            // of a placed triangle, where the model-space and the flat
            // tests round differently.
            let target = if k % 2 == 0 {
                let t = flat[rng.below(flat.len())];
                let [a, b, c] = t.vertices;
                [a, (a + b) * 0.5, (b + c) * 0.5, c][rng.below(4)]
            } else {
                Vec3::new(
                    rng.range(-50.0, 50.0) as f32,
                    0.0,
                    rng.range(-50.0, 50.0) as f32,
                )
            };
            let ray = TraceRay {
                origin,
                direction: (target - origin).normalize(),
                t_min: 0.0,
                t_max: f32::INFINITY,
            };
            let mut ours = Vec::new();
            top.for_each_placed_hit(
                &bottom,
                &ray,
                |first, t| placed(part_of(first), t, reference),
                |h, t| {
                    ours.push(key(&h, t));
                    f32::INFINITY
                },
            );
            let mut expected = Vec::new();
            brute_force_hits(&flat, &ray, |h| {
                expected.push(key(&h, &flat[h.triangle as usize]));
                f32::INFINITY
            });
            ours.sort();
            expected.sort();
            assert_eq!(ours, expected, "ray {ray:?}");
            with_hits += usize::from(ours.len() > 1);
            through_vertices += usize::from(k % 2 == 0 && !ours.is_empty());
        }
        assert!(
            with_hits > 500 && through_vertices > 1000,
            "{with_hits} {through_vertices}"
        );
    }

    /// The stacks of coincident copies of an instanced world: per stack,
    /// its parts' first caster ids in list order.
    fn stacks(world: &Instanced) -> Vec<Vec<u32>> {
        let mut stacks: Vec<(PlacedPart, Vec<u32>)> = Vec::new();
        for part in &world.parts {
            let same = |p: &PlacedPart| p.model == part.model && p.world == part.world;
            match stacks.iter_mut().find(|(p, _)| same(p)) {
                Some((_, ids)) => ids.push(part.first_caster),
                None => stacks.push((*part, vec![part.first_caster])),
            }
        }
        stacks
            .into_iter()
            .map(|(_, ids)| ids)
            .filter(|ids| ids.len() > 1)
            .collect()
    }

    /// Rays from above, half of them aimed at the stacks' parts; each run
    /// of `per_origin` rays from one point (a spot light's packet), its
    /// aimed rays at one part.
    fn rays_at_stacks(
        world: &Instanced,
        rng: &mut Rng,
        count: usize,
        per_origin: usize,
    ) -> Vec<TraceRay> {
        let stacked: Vec<&PlacedPart> = world
            .parts
            .iter()
            .filter(|p| stacks(world).iter().any(|s| s[0] == p.first_caster))
            .collect();
        let mut origin = Vec3::ZERO;
        (0..count)
            .map(|k| {
                if k % per_origin == 0 {
                    origin = Vec3::new(
                        rng.range(-60.0, 60.0) as f32,
                        30.0,
                        rng.range(-60.0, 60.0) as f32,
                    );
                }
                let target = if k % 2 == 0 {
                    let aim = if per_origin > 1 {
                        k / per_origin
                    } else {
                        k / 2
                    };
                    let part = stacked[aim % stacked.len()];
                    let jitter = DVec3::new(
                        rng.range(-1.0, 1.0),
                        rng.range(-0.5, 0.5),
                        rng.range(-1.0, 1.0),
                    );
                    (part.world.transform_point3(jitter) - world.reference).as_vec3()
                } else {
                    Vec3::new(
                        rng.range(-50.0, 50.0) as f32,
                        0.0,
                        rng.range(-50.0, 50.0) as f32,
                    )
                };
                TraceRay {
                    origin,
                    direction: (target - origin).normalize(),
                    t_min: 0.0,
                    t_max: 300.0,
                }
            })
            .collect()
    }

    #[test]
    fn coincident_copies_are_one_entry_and_each_reports_its_own_hits() {
        // The reference: a top level per part, so no two copies share one
        // (the same arithmetic, none of the folding).
        let mut rng = Rng::new(37);
        let world = instanced(&mut rng);
        let bottom = BottomLevels::build(
            2,
            |m| world.models[m].clone(),
            grids(&world.blocks, 8, 100.0),
        );
        let block = PlacedBlock {
            block: 0,
            caster: 1,
        };
        let top = TopLevel::build(
            &bottom,
            &world.parts[..],
            std::iter::once(block),
            world.reference,
        );
        let copies: usize = stacks(&world).iter().map(|s| s.len() - 1).sum();
        assert_eq!(stacks(&world).len(), 3);
        assert_eq!(top.len(), world.parts.len() + 1);
        assert_eq!(top.entries.len(), world.parts.len() + 1 - copies);
        let alone: Vec<TopLevel> = world
            .parts
            .iter()
            .map(|p| {
                TopLevel::build(
                    &bottom,
                    std::slice::from_ref(p),
                    std::iter::empty(),
                    world.reference,
                )
            })
            .collect();
        let ground = TopLevel::build(&bottom, &[][..], std::iter::once(block), world.reference);
        let stacked: Vec<u32> = stacks(&world).concat();
        let (mut on_copies, mut with_hits) = (0, 0);
        for ray in rays_at_stacks(&world, &mut rng, 1500, 1) {
            let mut expected = Vec::new();
            for top in alone.iter().chain(std::iter::once(&ground)) {
                let tracer = Tracer {
                    bottom: &bottom,
                    top,
                    mode: TraceMode::Trees,
                };
                expected.extend(hits(&tracer, &ray));
            }
            expected.sort();
            let tracer = Tracer {
                bottom: &bottom,
                top: &top,
                mode: TraceMode::Trees,
            };
            let got = hits(&tracer, &ray);
            assert_eq!(got, expected, "ray {ray:?}");
            // And with a t_max that shrinks to the nearest hit, the ties
            // at it on every copy.
            let mut nearest = Vec::new();
            tracer.for_each_hit(&ray, |h| {
                nearest.retain(|&(t, _)| t <= h.t);
                if nearest.first().is_none_or(|&(t, _)| h.t <= t) {
                    nearest.push((h.t, h.caster));
                }
                nearest.first().map_or(f32::INFINITY, |&(t, _)| t)
            });
            nearest.sort_by_key(|a| a.1);
            let t = expected.first().map(|h| f32::from_bits(h.0));
            let mut want: Vec<(f32, u32)> = expected
                .iter()
                .filter(|h| Some(f32::from_bits(h.0)) == t)
                .map(|h| (f32::from_bits(h.0), h.1))
                .collect();
            want.sort_by_key(|a| a.1);
            want.dedup();
            nearest.dedup();
            assert_eq!(nearest, want, "ray {ray:?}");
            on_copies += usize::from(
                got.iter()
                    .any(|h| stacked.contains(&(h.1 & !1)) || stacked.contains(&h.1)),
            );
            with_hits += usize::from(!got.is_empty());
        }
        assert!(
            on_copies > 300 && with_hits > 1000,
            "{on_copies} {with_hits}"
        );
    }

    #[test]
    fn packets_leave_out_the_repeated_hits_a_caller_drops_and_no_other() {
        let mut rng = Rng::new(43);
        let world = instanced(&mut rng);
        let bottom = BottomLevels::build(
            2,
            |m| world.models[m].clone(),
            grids(&world.blocks, 8, 100.0),
        );
        let top = TopLevel::build(
            &bottom,
            &world.parts[..],
            std::iter::empty(),
            world.reference,
        );
        let tracer = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        // The ids of each stack's third and later placements, each with
        // its first two's, group by group of the stack's model.
        let mut later = Vec::new();
        for stack in stacks(&world) {
            let part = world
                .parts
                .iter()
                .find(|p| p.first_caster == stack[0])
                .unwrap();
            let groups = world.models[part.model as usize]
                .iter()
                .map(|t| t.caster)
                .max()
                .unwrap()
                + 1;
            for &copy in &stack[2..] {
                for g in 0..groups {
                    later.push((copy + g, [stack[0] + g, stack[1] + g]));
                }
            }
        }
        let anchors_of = |c: u32| later.iter().find(|(id, _)| *id == c).map(|(_, a)| *a);
        let all = |_: u32, _: [u32; 2]| true;
        let even = |c: u32, _: [u32; 2]| c.is_multiple_of(2);
        let mut left_out = 0;
        for (k, drops) in [&all as &DropsRepeat, &even].into_iter().enumerate() {
            let cull = FaceCull {
                repeats: Some(drops),
                ..FaceCull::default()
            };
            for rays in rays_at_stacks(&world, &mut rng, 64 * 40, 64).chunks(64) {
                let mut got = vec![Vec::new(); rays.len()];
                let mut scratch = PacketScratch::default();
                tracer.for_each_packet_hit_culled(
                    rays,
                    &mut scratch,
                    &cull,
                    PacketRays::All,
                    |lane, h| {
                        got[lane].push((h.t.to_bits(), h.caster, h.back_facing, h.triangle));
                        f32::INFINITY
                    },
                );
                for (ray, mut list) in rays.iter().zip(got) {
                    list.sort();
                    let every = hits(&tracer, ray);
                    // Each hit reported is a hit, and every hit is reported
                    // but a later copy's the caller drops given its first
                    // two's, which are reported.
                    assert!(list.iter().all(|h| every.contains(h)), "ray {ray:?}");
                    for h in &every {
                        let dropped = anchors_of(h.1).is_some_and(|a| drops(h.1, a));
                        assert!(dropped || list.contains(h), "{h:?} of ray {ray:?}");
                        if let Some(a) = anchors_of(h.1) {
                            for anchor in a {
                                let twin = (h.0, anchor, h.2, h.3);
                                assert!(list.contains(&twin), "{twin:?} of ray {ray:?}");
                            }
                        }
                    }
                    // Dropping every repeat leaves out all of them.
                    if k == 0 {
                        let repeats = every.iter().filter(|h| anchors_of(h.1).is_some()).count();
                        assert_eq!(list.len(), every.len() - repeats, "ray {ray:?}");
                        left_out += repeats;
                    }
                }
            }
        }
        assert!(left_out > 500, "{left_out}");
    }

    // -----------------------------------------------------------------------
    // Packets: the tile traversal against the single-ray traversal, ray by
    // ray, hit lists (not only masks).

    type HitList = Vec<(u32, u32, bool, u32)>;

    /// Every hit of each ray of `rays` through the packet traversal.
    fn packet_hits(tracer: &Tracer, rays: &[TraceRay]) -> Vec<HitList> {
        let mut out = vec![Vec::new(); rays.len()];
        let mut scratch = PacketScratch::default();
        tracer.for_each_packet_hit(rays, &mut scratch, |lane, h| {
            out[lane].push((h.t.to_bits(), h.caster, h.back_facing, h.triangle));
            f32::INFINITY
        });
        for list in &mut out {
            list.sort();
        }
        out
    }

    /// The two nearest hits of each ray (all hits tying with the second),
    /// with t_max shrinking to the second nearest so far: rays settle and
    /// leave the packet at different times.
    fn two_nearest(tracer: &Tracer, rays: &[TraceRay], packets: bool) -> Vec<HitList> {
        let mut out: Vec<HitList> = vec![Vec::new(); rays.len()];
        let offer = |lane: usize, h: Hit, out: &mut Vec<HitList>| {
            let list = &mut out[lane];
            list.push((h.t.to_bits(), h.caster, h.back_facing, h.triangle));
            list.sort_by(|a, b| {
                f32::from_bits(a.0)
                    .total_cmp(&f32::from_bits(b.0))
                    .then(a.cmp(b))
            });
            if list.len() >= 2 {
                f32::from_bits(list[1].0)
            } else {
                f32::INFINITY
            }
        };
        if packets {
            let mut scratch = PacketScratch::default();
            tracer.for_each_packet_hit(rays, &mut scratch, |lane, h| offer(lane, h, &mut out));
        } else {
            for (lane, ray) in rays.iter().enumerate() {
                tracer.for_each_hit(ray, |h| offer(lane, h, &mut out));
            }
        }
        for list in &mut out {
            if list.len() >= 2 {
                let second = f32::from_bits(list[1].0);
                list.retain(|h| f32::from_bits(h.0) <= second);
            }
            list.sort();
        }
        out
    }

    /// Packets of `rays` (consecutive runs of `size`) agree with the
    /// single-ray traversal ray by ray, all hits and two nearest; returns
    /// the number of hits seen.
    fn assert_packets_agree(tracer: &Tracer, rays: &[TraceRay], size: usize) -> usize {
        let mut seen = 0;
        for packet in rays.chunks(size) {
            let got = packet_hits(tracer, packet);
            for (ray, list) in packet.iter().zip(&got) {
                assert_eq!(*list, hits(tracer, ray), "ray {ray:?}");
                seen += list.len();
            }
            assert_eq!(
                two_nearest(tracer, packet, true),
                two_nearest(tracer, packet, false),
                "packet from {:?}",
                packet[0]
            );
        }
        seen
    }

    /// A directional light's tile: `n`×`n` parallel rays along `d`, from a
    /// plane through `centre` perpendicular to d, `spacing` apart.
    /// Tile `k` of a seeded series: 8×8 parallel rays along `fixed[k]` or,
    /// for the next three k of each cycle, a random downward direction,
    /// centred at a random point within ±`reach` (x, z) and 0..`height`
    /// (y), 0.05, 0.25 or 1 m apart, starting 40 m back.
    fn random_parallel_tile(
        rng: &mut Rng,
        k: usize,
        fixed: &[Vec3],
        (reach, height): (f64, f64),
    ) -> Vec<TraceRay> {
        let d = match k % (fixed.len() + 3) {
            i if i < fixed.len() => fixed[i],
            _ => Vec3::new(
                rng.range(-1.0, 1.0) as f32,
                rng.range(-1.0, -0.2) as f32,
                rng.range(-1.0, 1.0) as f32,
            ),
        };
        let c = Vec3::new(
            rng.range(-reach, reach) as f32,
            rng.range(0.0, height) as f32,
            rng.range(-reach, reach) as f32,
        );
        let spacing = [0.05, 0.25, 1.0][k % 3];
        parallel_tile(c - d.normalize() * 40.0, d, 8, spacing, 200.0)
    }

    fn parallel_tile(centre: Vec3, d: Vec3, n: usize, spacing: f32, t_max: f32) -> Vec<TraceRay> {
        let d = d.normalize();
        let helper = if d.x.abs() < 0.6 { Vec3::X } else { Vec3::Y };
        let u = d.cross(helper).normalize();
        let v = d.cross(u);
        let half = (n as f32 - 1.0) / 2.0;
        (0..n * n)
            .map(|k| {
                let (i, j) = ((k % n) as f32 - half, (k / n) as f32 - half);
                TraceRay {
                    origin: centre + u * (i * spacing) + v * (j * spacing),
                    direction: d,
                    t_min: 0.0,
                    t_max,
                }
            })
            .collect()
    }

    /// A spot or point light's tile: `n`×`n` rays from `origin` through a
    /// square of half-angle tangent `spread` around `forward`.
    fn frustum_tile(
        origin: Vec3,
        forward: Vec3,
        n: usize,
        spread: f32,
        t_min: f32,
    ) -> Vec<TraceRay> {
        let f = forward.normalize();
        let helper = if f.x.abs() < 0.6 { Vec3::X } else { Vec3::Y };
        let u = f.cross(helper).normalize();
        let v = f.cross(u);
        (0..n * n)
            .map(|k| {
                let s = ((k % n) as f32 + 0.5) / n as f32 * 2.0 - 1.0;
                let t = ((k / n) as f32 + 0.5) / n as f32 * 2.0 - 1.0;
                TraceRay {
                    origin,
                    direction: (f + u * (s * spread) + v * (t * spread)).normalize(),
                    t_min,
                    t_max: 300.0,
                }
            })
            .collect()
    }

    fn instanced_tracer_check(check: impl Fn(&Tracer, &Instanced)) {
        let mut rng = Rng::new(23);
        let world = instanced(&mut rng);
        let bottom = BottomLevels::build(
            2,
            |m| world.models[m].clone(),
            grids(&world.blocks, 8, 100.0),
        );
        let top = TopLevel::build(
            &bottom,
            &world.parts[..],
            std::iter::once(PlacedBlock {
                block: 0,
                caster: 1,
            }),
            world.reference,
        );
        let tracer = Tracer {
            bottom: &bottom,
            top: &top,
            mode: TraceMode::Trees,
        };
        check(&tracer, &world);
    }

    #[test]
    fn directional_tiles_match_single_rays_far_from_the_origin() {
        instanced_tracer_check(|tracer, _| {
            let mut rng = Rng::new(31);
            let mut seen = 0;
            for k in 0..60 {
                // Straight down (axis-parallel), grazing, and slanted; tile
                // centres inside the world and across its border (the world
                // spans -50..50 around the reference).
                let fixed = [
                    Vec3::NEG_Y,
                    Vec3::new(1.0, -0.04, 0.3),
                    Vec3::new(-0.2, -1e-7, 1.0),
                ];
                let rays = random_parallel_tile(&mut rng, k, &fixed, (70.0, 12.0));
                seen += assert_packets_agree(tracer, &rays, 64);
            }
            assert!(seen > 2000, "{seen}");
        });
    }

    #[test]
    fn spot_and_point_tiles_match_single_rays() {
        instanced_tracer_check(|tracer, _| {
            let mut rng = Rng::new(37);
            let mut seen = 0;
            for k in 0..48 {
                let origin = Vec3::new(
                    rng.range(-40.0, 40.0) as f32,
                    rng.range(8.0, 30.0) as f32,
                    rng.range(-40.0, 40.0) as f32,
                );
                // The six cube faces of a point light, and random spots.
                let forward = match k % 8 {
                    0 => Vec3::NEG_Y,
                    1 => Vec3::X,
                    2 => Vec3::NEG_X,
                    3 => Vec3::Z,
                    4 => Vec3::NEG_Z,
                    5 => Vec3::Y,
                    _ => Vec3::new(
                        rng.range(-1.0, 1.0) as f32,
                        rng.range(-1.0, -0.3) as f32,
                        rng.range(-1.0, 1.0) as f32,
                    ),
                };
                // A whole face in one packet, and a narrow tile of it.
                let spread = if k % 2 == 0 { 1.0 } else { 0.05 };
                let rays = frustum_tile(origin, forward, 16, spread, 0.1);
                seen += assert_packets_agree(tracer, &rays, 64);
            }
            assert!(seen > 2000, "{seen}");
        });
    }

    #[test]
    fn tiles_along_shared_edges_of_models_and_terrain_match_single_rays() {
        instanced_tracer_check(|tracer, world| {
            let mut seen = 0;
            // The unrotated cube of half-size 0.75 at (0, 10, 0) relative
            // to the reference: rays straight down and slanted through its
            // edges, face diagonals and corners (multiples of 0.375 are
            // exact in f32).
            for d in [
                Vec3::NEG_Y,
                Vec3::new(0.5, -1.0, 0.25),
                Vec3::new(-1.0, -1.0, 0.0),
            ] {
                let d = d.normalize();
                let rays: Vec<TraceRay> = (0..=8)
                    .flat_map(|i| (0..=8).map(move |j| (i, j)))
                    .map(|(i, j)| {
                        let p = Vec3::new(-1.5 + 0.375 * i as f32, 10.75, -1.5 + 0.375 * j as f32);
                        TraceRay {
                            origin: p - d * 20.0,
                            direction: d,
                            t_min: 0.0,
                            t_max: 100.0,
                        }
                    })
                    .collect();
                seen += assert_packets_agree(tracer, &rays, 81);
                seen += assert_packets_agree(tracer, &rays, 8);
            }
            // Terrain cell corners, edges and diagonals (8 cells of 12.5 m):
            // the points exactly on the lattice, light-relative.
            let step = 100.0 / 8.0 / 2.0;
            let origin = world.blocks[0].2;
            for d in [Vec3::NEG_Y, Vec3::new(0.3, -1.0, 0.2).normalize()] {
                let rays: Vec<TraceRay> = (0..17 * 17)
                    .map(|k| {
                        let w = origin
                            + DVec3::new((k % 17) as f64 * step, 0.0, (k / 17) as f64 * step);
                        let p = (w - world.reference).as_vec3();
                        TraceRay {
                            origin: Vec3::new(p.x, 40.0, p.z),
                            direction: d,
                            t_min: 0.0,
                            t_max: 200.0,
                        }
                    })
                    .collect();
                seen += assert_packets_agree(tracer, &rays, 64);
            }
            assert!(seen > 300, "{seen}");
        });
    }

    #[test]
    fn tiles_at_the_silhouettes_of_rotated_scaled_instances_match_single_rays() {
        // Rays of parallel tiles aimed at the corners of the rotated,
        // scaled, mirrored cubes and cards 1e5 m from the origin, and
        // around them by a few ulps: the rays that decide the culling of a
        // packet's rays by the instance's image and of its groups by a
        // triangle's image (`packet::ShearPlane`).
        instanced_tracer_check(|tracer, world| {
            let mut seen = 0;
            let directions = [
                Vec3::NEG_Y,
                Vec3::new(0.3, -1.0, 0.2).normalize(),
                Vec3::new(1.0, -0.05, -0.4).normalize(),
            ];
            for (k, part) in world.parts.iter().enumerate().take(120) {
                let half = if part.model == 0 { 0.75 } else { 1.0 };
                let flat = part.model == 1;
                for corner in 0..8 {
                    if flat && corner & 2 != 0 {
                        continue;
                    }
                    let pick = |bit: usize| if corner & bit == 0 { -half } else { half };
                    let y = if flat { 0.0 } else { pick(2) };
                    let c = part.world.transform_point3(DVec3::new(pick(1), y, pick(4)));
                    let p = (c - world.reference).as_vec3();
                    let d = directions[(k + corner) % 3];
                    // Spacings of a few ulps up to a centimetre.
                    let ulp = p.abs().max_element() * f32::EPSILON;
                    let spacing = [ulp, 3.0 * ulp, 1e-3, 1e-2][corner % 4];
                    let rays = parallel_tile(p - d * 30.0, d, 8, spacing, 80.0);
                    seen += assert_packets_agree(tracer, &rays, 64);
                }
            }
            assert!(seen > 2000, "{seen}");
        });
    }

    #[test]
    fn culled_packets_report_every_hit_the_caller_keeps() {
        // Face culling told to the packet traversal: parallel rays skip
        // triangles every hit of which the caller would drop (back or front
        // faces, not of double-sided casters); the hits left must be the
        // single-ray hits the caller keeps, on rotated, scaled and mirrored
        // instances, terrain, and grazing and axis-parallel directions.
        instanced_tracer_check(|tracer, world| {
            let mut rng = Rng::new(41);
            let either: Vec<u64> = vec![0b1010_0000_0000_0000_0000_0000; 12];
            let mut kept = 0;
            for k in 0..90 {
                let drops_back = [Some(true), Some(false), None][k % 3];
                let cull = FaceCull {
                    drops_back,
                    either_face: &either,
                    repeats: None,
                };
                let fixed = [Vec3::NEG_Y, Vec3::new(1.0, -0.05, 0.3)];
                let rays = random_parallel_tile(&mut rng, k, &fixed, (60.0, 10.0));
                kept += assert_culled_packets_agree(tracer, &rays, &cull);
            }
            assert!(kept > 2000, "{kept}");
            // Nearly edge-on: rays along the cards' planes, tilted by
            // 1e-7 to 1e-3 radians, through their centres.
            for (k, part) in world_cards(world).enumerate().take(60) {
                let along = part.world.transform_vector3(DVec3::X).normalize();
                let normal = part
                    .world
                    .inverse()
                    .transpose()
                    .transform_vector3(DVec3::Y)
                    .normalize();
                let tilt = [1e-7, 1e-5, 1e-3][k % 3];
                let d = (along + normal * tilt).normalize().as_vec3();
                let centre = (part.world.transform_point3(DVec3::ZERO) - world.reference).as_vec3();
                let cull = FaceCull {
                    drops_back: [Some(true), Some(false)][k % 2],
                    either_face: &either,
                    repeats: None,
                };
                let rays = parallel_tile(centre - d * 20.0, d, 8, 0.01, 60.0);
                assert_culled_packets_agree(tracer, &rays, &cull);
            }
        });
    }

    /// The hits the packet traversal told `cull` reports for each ray of
    /// `rays` (one packet) that the caller keeps are the single-ray hits it
    /// keeps; returns how many.
    fn assert_culled_packets_agree(tracer: &Tracer, rays: &[TraceRay], cull: &FaceCull) -> usize {
        let mut got = vec![Vec::new(); rays.len()];
        let mut scratch = PacketScratch::default();
        tracer.for_each_packet_hit_culled(rays, &mut scratch, cull, PacketRays::All, |lane, h| {
            if !cull.drops(h.caster, h.back_facing) {
                got[lane].push((h.t.to_bits(), h.caster, h.back_facing, h.triangle));
            }
            f32::INFINITY
        });
        let mut kept = 0;
        for (ray, mut list) in rays.iter().zip(got) {
            list.sort();
            let mut want = hits(tracer, ray);
            want.retain(|&(_, caster, back, _)| !cull.drops(caster, back));
            assert_eq!(list, want, "ray {ray:?}, {:?}", cull.drops_back);
            kept += list.len();
        }
        kept
    }

    /// The card instances (model 1) of an instanced world.
    fn world_cards(world: &Instanced) -> impl Iterator<Item = &PlacedPart> {
        world.parts.iter().filter(|p| p.model == 1)
    }

    #[test]
    fn segments_reaching_behind_their_origins_match_single_rays() {
        instanced_tracer_check(|tracer, _| {
            let mut seen = 0;
            for d in [Vec3::new(0.4, -1.0, 0.1), Vec3::new(-1.0, -0.3, 0.5)] {
                // Origins under the surface, segments from 30 m behind.
                let mut rays = parallel_tile(Vec3::new(5.0, -3.0, 2.0), d, 8, 0.7, 40.0);
                for r in &mut rays {
                    r.t_min = -30.0;
                }
                seen += assert_packets_agree(tracer, &rays, 64);
                let mut rays = frustum_tile(Vec3::new(-8.0, 1.0, 4.0), d, 8, 0.3, -25.0);
                for r in &mut rays {
                    r.t_max = 30.0;
                }
                seen += assert_packets_agree(tracer, &rays, 64);
            }
            assert!(seen > 100, "{seen}");
        });
    }

    #[test]
    fn packets_with_unusable_or_spread_rays_fall_back_exactly() {
        instanced_tracer_check(|tracer, _| {
            let mut rays = parallel_tile(Vec3::new(3.0, 30.0, -7.0), Vec3::NEG_Y, 8, 0.5, 200.0);
            rays[5].origin.x = f32::NAN;
            rays[9].direction = Vec3::ZERO;
            rays[13].t_min = 500.0;
            rays[17].t_max = f32::NAN;
            assert_packets_agree(tracer, &rays, 64);
            // Opposite directions in one packet: no beam bounds them.
            let mut spread = parallel_tile(Vec3::new(3.0, 30.0, -7.0), Vec3::NEG_Y, 4, 0.5, 200.0);
            spread.extend(parallel_tile(
                Vec3::new(3.0, -30.0, -7.0),
                Vec3::Y,
                4,
                0.5,
                200.0,
            ));
            let seen = assert_packets_agree(tracer, &spread, 32);
            assert!(seen > 16, "{seen}");
            // Larger than one packet: split.
            let many = parallel_tile(Vec3::new(0.0, 30.0, 0.0), Vec3::NEG_Y, 20, 0.5, 200.0);
            assert_packets_agree(tracer, &many, 400);
        });
    }
}
