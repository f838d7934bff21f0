//! Grid geometry checked against values worked out by hand, and seeded-random
//! properties (coverage, partition of the sphere, conservative `reaches`).

use super::*;
use crate::rng::Rng;

fn directional(direction: DVec3, texel_size: f64) -> LightSettings {
    LightSettings {
        name: "sun".to_string(),
        kind: LightKind::Directional {
            direction,
            texel_size,
        },
    }
}

fn spot(
    position: DVec3,
    direction: DVec3,
    fov_degrees: f64,
    near: f64,
    far: f64,
    resolution: u32,
) -> LightSettings {
    LightSettings {
        name: "lamp".to_string(),
        kind: LightKind::Spot {
            position,
            direction,
            fov_degrees,
            near,
            far,
            resolution,
        },
    }
}

fn point(position: DVec3, near: f64, far: f64, resolution: u32) -> LightSettings {
    LightSettings {
        name: "bulb".to_string(),
        kind: LightKind::Point {
            position,
            near,
            far,
            resolution,
        },
    }
}

/// Bounds are ignored by spot and point lights.
const NO_WORLD: (DVec3, DVec3) = (DVec3::ZERO, DVec3::ZERO);

fn random_bounds(rng: &mut Rng) -> (DVec3, DVec3) {
    let centre = DVec3::new(
        rng.range(-5000.0, 5000.0),
        rng.range(-100.0, 100.0),
        rng.range(-5000.0, 5000.0),
    );
    let half = DVec3::new(
        rng.range(0.0, 300.0),
        rng.range(0.0, 50.0),
        rng.range(0.0, 300.0),
    );
    (centre - half, centre + half)
}

/// Angle between two unit vectors, accurate for small angles too.
fn angle(a: DVec3, b: DVec3) -> f64 {
    a.cross(b).length().atan2(a.dot(b))
}

// ---------------------------------------------------------------- directional

#[test]
fn straight_down_sun_puts_texel_centres_on_known_points() {
    // d = (0, −1, 0) gives u = +X, v = +Z exactly (see basis tests), so
    // texel x runs along world x and texel y along world z, from the
    // bounds' minimum: centres at 0.5, 1.5, 2.5, 3.5.
    let grid = TexelGrid::new(
        &directional(DVec3::NEG_Y, 1.0),
        (DVec3::new(0.0, 0.0, 0.0), DVec3::new(4.0, 2.0, 4.0)),
    )
    .unwrap();
    assert_eq!((grid.faces(), grid.width(), grid.height()), (1, 4, 4));
    assert_eq!(grid.texel_count(), 16);
    assert_eq!(grid.reference_point(), DVec3::new(2.0, 1.0, 2.0));
    for y in 0..4 {
        for x in 0..4 {
            let ray = grid.ray(0, x, y);
            assert_eq!(ray.origin.x, x as f64 + 0.5);
            assert_eq!(ray.origin.z, y as f64 + 0.5);
            assert_eq!(ray.direction, DVec3::NEG_Y);
            assert!(
                ray.origin.y > 2.0,
                "origin {} not above the world",
                ray.origin
            );
            assert_eq!(ray.t_min, 0.0);
            // The ray reaches the bottom of the world (y = 0).
            assert!(ray.t_max > ray.origin.y, "t_max {} too short", ray.t_max);
        }
    }
}

#[test]
fn sun_along_x_maps_texels_to_minus_z_and_y() {
    // d = +X: u = −Z, v = +Y. Bounds x 0..1, y 0..2, z 0..3, texel 0.5:
    // u ranges over −3..0 (6 texels), v over 0..2 (4 texels).
    let grid = TexelGrid::new(
        &directional(DVec3::X, 0.5),
        (DVec3::ZERO, DVec3::new(1.0, 2.0, 3.0)),
    )
    .unwrap();
    assert_eq!((grid.width(), grid.height()), (6, 4));
    let ray = grid.ray(0, 0, 0);
    // u = −3 + 0.25 → z = 2.75; v = 0.25 → y = 0.25.
    assert_eq!(ray.origin.z, 2.75);
    assert_eq!(ray.origin.y, 0.25);
    assert!(ray.origin.x < 0.0);
    assert_eq!(grid.ray(0, 5, 3).origin.z, 0.25);
    assert_eq!(grid.ray(0, 5, 3).origin.y, 1.75);
}

#[test]
fn directional_grids_cover_the_world_with_exact_spacing() {
    let mut rng = Rng::new(0xd1_2ec7);
    for case in 0..300 {
        let d = rng.unit_vector();
        let bounds = random_bounds(&mut rng);
        let texel_size = rng.range(0.5, 20.0);
        let grid = TexelGrid::new(&directional(d, texel_size), bounds).unwrap();
        let (u, v) = orthonormal_basis(d);
        let (w, h) = (grid.width(), grid.height());
        let first = grid.ray(0, 0, 0);
        // Light-plane coordinates in texel units, relative to the grid's
        // lower edge (the first centre is at 0.5).
        let grid_coords = |p: DVec3| {
            let rel = p - first.origin;
            (rel.dot(u) / texel_size + 0.5, rel.dot(v) / texel_size + 0.5)
        };
        let tol = 1e-9;
        let mut extent_u = (f64::INFINITY, f64::NEG_INFINITY);
        let mut extent_v = (f64::INFINITY, f64::NEG_INFINITY);
        for c in corners(bounds.0, bounds.1) {
            let (gu, gv) = grid_coords(c);
            assert!(
                (-tol..=w as f64 + tol).contains(&gu) && (-tol..=h as f64 + tol).contains(&gv),
                "case {case}: corner {c} at grid ({gu}, {gv}) outside {w}×{h}"
            );
            extent_u = (extent_u.0.min(gu), extent_u.1.max(gu));
            extent_v = (extent_v.0.min(gv), extent_v.1.max(gv));
            // Every ray starts in front of every corner and reaches past it.
            for (x, y) in [
                (0, 0),
                (w - 1, 0),
                (0, h - 1),
                (w - 1, h - 1),
                (w / 2, h / 2),
            ] {
                let ray = grid.ray(0, x, y);
                let t = (c - ray.origin).dot(ray.direction);
                assert!(t > 0.0, "case {case}: corner {c} behind the ray origin");
                assert!(t < ray.t_max, "case {case}: corner {c} beyond t_max");
            }
        }
        // The grid starts at the smallest projection and is not wider than
        // needed: the last column still starts inside the projection.
        assert!(
            extent_u.0.abs() < tol && extent_v.0.abs() < tol,
            "case {case}"
        );
        assert!(
            (w as f64 - 1.0) < extent_u.1 + tol || w == 1,
            "case {case}: too wide"
        );
        assert!(
            (h as f64 - 1.0) < extent_v.1 + tol || h == 1,
            "case {case}: too tall"
        );

        for _ in 0..20 {
            let x = rng.below(w as usize) as u32;
            let y = rng.below(h as usize) as u32;
            let ray = grid.ray(0, x, y);
            assert_eq!(ray.direction, first.direction, "rays must be parallel");
            assert!((ray.direction.length() - 1.0).abs() < 1e-15);
            assert!((ray.direction - d).length() < 1e-15);
            if x + 1 < w {
                let step = grid.ray(0, x + 1, y).origin - ray.origin;
                let rel = 1e-12 * (1.0 + ray.origin.abs().max_element());
                assert!(
                    (step.dot(u) - texel_size).abs() < rel,
                    "case {case}: u step"
                );
                assert!(
                    step.dot(v).abs() < rel && step.dot(d).abs() < rel,
                    "case {case}"
                );
            }
            if y + 1 < h {
                let step = grid.ray(0, x, y + 1).origin - ray.origin;
                let rel = 1e-12 * (1.0 + ray.origin.abs().max_element());
                assert!(
                    (step.dot(v) - texel_size).abs() < rel,
                    "case {case}: v step"
                );
                assert!(
                    step.dot(u).abs() < rel && step.dot(d).abs() < rel,
                    "case {case}"
                );
            }
        }
    }
}

#[test]
fn zero_size_and_flat_worlds_get_at_least_one_texel() {
    let p = DVec3::new(12.5, -3.0, 1e5);
    let grid = TexelGrid::new(&directional(DVec3::new(0.6, -0.8, 0.0), 2.0), (p, p)).unwrap();
    assert_eq!((grid.width(), grid.height()), (1, 1));
    // The single ray passes through the point (the texel centre is half a
    // texel from the lower edge, which sits at the point's projection).
    let ray = grid.ray(0, 0, 0);
    let t = (p - ray.origin).dot(ray.direction);
    let miss = (ray.at(t) - p).length();
    assert!((miss - 2.0f64.sqrt()).abs() < 1e-9, "miss {miss}");

    // A flat 10 × 10 plane seen from above: 10 × 10 texels of 1 m.
    let grid = TexelGrid::new(
        &directional(DVec3::NEG_Y, 1.0),
        (DVec3::ZERO, DVec3::new(10.0, 0.0, 10.0)),
    )
    .unwrap();
    assert_eq!((grid.width(), grid.height()), (10, 10));
    // Seen edge-on, the plane is one texel tall.
    let grid = TexelGrid::new(
        &directional(DVec3::X, 1.0),
        (DVec3::ZERO, DVec3::new(10.0, 0.0, 10.0)),
    )
    .unwrap();
    assert_eq!((grid.width(), grid.height()), (10, 1));
}

#[test]
fn far_from_origin_world_keeps_origins_in_front() {
    let min = DVec3::new(3e7, 10.0, -3e7);
    let max = min + DVec3::new(100.0, 50.0, 100.0);
    let d = DVec3::new(-0.3, -1.0, 0.2).normalize();
    let grid = TexelGrid::new(&directional(d, 0.25), (min, max)).unwrap();
    assert_eq!(grid.reference_point(), (min + max) * 0.5);
    for (x, y) in [(0, 0), (grid.width() - 1, grid.height() - 1)] {
        let ray = grid.ray(0, x, y);
        for c in corners(min, max) {
            // The margin is 1 m + 1e-6·3e7 = 31 m; f64 rounding at 3e7 is ~4e-9.
            let t = (c - ray.origin).dot(ray.direction);
            assert!(t > 30.0 && t < ray.t_max, "t = {t}");
        }
    }
}

#[test]
fn empty_or_non_finite_worlds_are_errors() {
    let light = directional(DVec3::NEG_Y, 1.0);
    let cases = [
        (DVec3::new(1.0, 0.0, 0.0), DVec3::new(0.0, 5.0, 5.0)),
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        (DVec3::new(0.0, f64::NAN, 0.0), DVec3::ONE),
        (DVec3::ZERO, DVec3::new(1.0, 1.0, f64::INFINITY)),
    ];
    for bounds in cases {
        let err = TexelGrid::new(&light, bounds).unwrap_err();
        assert!(
            matches!(err, GridError::EmptyWorld { .. }),
            "{bounds:?}: {err:?}"
        );
        let text = err.to_string();
        assert!(
            text.contains("`sun`") && text.contains("no extent"),
            "{text}"
        );
    }
    // Spot and point lights do not depend on the world.
    let empty = (DVec3::ONE, DVec3::ZERO);
    assert!(TexelGrid::new(&point(DVec3::ZERO, 0.1, 10.0, 4), empty).is_ok());
}

#[test]
fn oversized_grids_are_errors_that_say_what_to_change() {
    let light = directional(DVec3::NEG_Y, 1.0);
    // 2^18 = 262 144 texels on a side is the limit, and 2^18 squared = 2^36
    // in total. Building a grid traces nothing, so the limit is cheap to hit.
    assert_eq!((MAX_SIDE, MAX_TEXELS), (262_144, 68_719_476_736));
    let far = DVec3::new(262144.0, 1.0, 262144.0);
    let grid = TexelGrid::new(&light, (DVec3::ZERO, far)).unwrap();
    assert_eq!((grid.width(), grid.height()), (262144, 262144));
    assert_eq!(grid.texel_count(), MAX_TEXELS);
    assert_eq!(grid.texel_at(MAX_TEXELS - 1), Some((0, 262143, 262143)));
    assert_eq!(grid.texel_at(MAX_TEXELS), None);
    // The far corner's ray lies where the convention puts it: u64 indices
    // and u32 coordinates do not wrap at this size.
    let ray = grid.ray(0, 262143, 262143);
    let (u, v) = orthonormal_basis(DVec3::NEG_Y);
    let lowest = |axis: DVec3| {
        corners(DVec3::ZERO, far)
            .map(|c| c.dot(axis))
            .into_iter()
            .fold(f64::INFINITY, f64::min)
    };
    assert!((ray.origin.dot(u) - (lowest(u) + 262143.5)).abs() < 1e-6);
    assert!((ray.origin.dot(v) - (lowest(v) + 262143.5)).abs() < 1e-6);

    let err = TexelGrid::new(&light, (DVec3::ZERO, DVec3::new(262144.5, 1.0, 10.0))).unwrap_err();
    assert!(
        matches!(
            err,
            GridError::TooLarge {
                width: 262145,
                height: 10,
                faces: 1,
                ..
            }
        ),
        "{err:?}"
    );
    assert!(err.to_string().contains("raise <texelSize>"), "{err}");
    // Absurd ratios saturate instead of overflowing.
    let tiny = directional(DVec3::NEG_Y, 1e-300);
    let err = TexelGrid::new(&tiny, (DVec3::ZERO, DVec3::splat(1e300))).unwrap_err();
    assert!(matches!(err, GridError::TooLarge { .. }), "{err:?}");

    let s = |res| spot(DVec3::ZERO, DVec3::NEG_Y, 60.0, 0.1, 10.0, res);
    assert!(TexelGrid::new(&s(262144), NO_WORLD).is_ok());
    let err = TexelGrid::new(&s(262145), NO_WORLD).unwrap_err();
    assert!(err.to_string().contains("lower <resolution>"), "{err}");

    // Six faces: 6·107019² = 68 718 398 166 ≤ 2^36 < 6·107020² = 68 719 682 400.
    let p = |res| point(DVec3::ZERO, 0.1, 10.0, res);
    assert_eq!(
        TexelGrid::new(&p(107019), NO_WORLD).unwrap().texel_count(),
        68_718_398_166
    );
    let err = TexelGrid::new(&p(107020), NO_WORLD).unwrap_err();
    assert!(
        matches!(
            err,
            GridError::TooLarge {
                faces: 6,
                width: 107020,
                ..
            }
        ),
        "{err:?}"
    );
    assert!(err.to_string().contains("`bulb`"), "{err}");
}

#[test]
fn invalid_lights_built_in_code_are_errors() {
    let world = (DVec3::ZERO, DVec3::ONE);
    let bad = [
        directional(DVec3::ZERO, 1.0),
        directional(DVec3::new(f64::NAN, 1.0, 0.0), 1.0),
        directional(DVec3::NEG_Y, 0.0),
        directional(DVec3::NEG_Y, f64::INFINITY),
        spot(DVec3::ZERO, DVec3::Y, 0.0, 0.1, 1.0, 8),
        spot(DVec3::ZERO, DVec3::Y, 180.0, 0.1, 1.0, 8),
        spot(DVec3::ZERO, DVec3::ZERO, 60.0, 0.1, 1.0, 8),
        spot(DVec3::ZERO, DVec3::Y, 60.0, 0.0, 1.0, 8),
        spot(DVec3::ZERO, DVec3::Y, 60.0, 1.0, 1.0, 8),
        spot(DVec3::ZERO, DVec3::Y, 60.0, 0.1, 1.0, 0),
        point(DVec3::new(0.0, f64::NAN, 0.0), 0.1, 1.0, 8),
        point(DVec3::ZERO, 0.1, f64::INFINITY, 8),
    ];
    for light in bad {
        let err = TexelGrid::new(&light, world).unwrap_err();
        assert!(
            matches!(err, GridError::BadLight { .. }),
            "{light:?}: {err:?}"
        );
        assert!(
            err.to_string().contains(&format!("`{}`", light.name)),
            "{err}"
        );
    }
}

// ----------------------------------------------------------------------- spot

#[test]
fn spot_rays_follow_the_opening_angle() {
    let mut rng = Rng::new(0x5b07);
    for _ in 0..200 {
        let d = rng.unit_vector();
        let position = DVec3::new(
            rng.range(-1e4, 1e4),
            rng.range(-1e2, 1e2),
            rng.range(-1e4, 1e4),
        );
        let fov = rng.range(1.0, 170.0);
        let res = 2 * rng.below(200) as u32 + 1;
        let grid = TexelGrid::new(&spot(position, d, fov, 0.5, 40.0, res), NO_WORLD).unwrap();
        assert_eq!((grid.faces(), grid.width(), grid.height()), (1, res, res));
        assert_eq!(grid.reference_point(), position);

        let centre = grid.ray(0, res / 2, res / 2);
        assert!(
            (centre.direction - d).length() < 1e-15,
            "odd grid centre is the axis"
        );
        assert_eq!(
            (centre.origin, centre.t_min, centre.t_max),
            (position, 0.5, 40.0)
        );

        // Texel (0, 0): image-plane point (−k·(1 − 1/res), −k·(1 − 1/res), 1)
        // with k = tan(fov/2), at angle atan(k·(1 − 1/res)·√2) from the axis.
        let k = (fov.to_radians() / 2.0).tan();
        let off = k * (1.0 - 1.0 / res as f64);
        let expected = (off * 2f64.sqrt()).atan();
        for (x, y) in [(0, 0), (res - 1, 0), (0, res - 1), (res - 1, res - 1)] {
            let ray = grid.ray(0, x, y);
            let a = angle(ray.direction, d);
            assert!(
                (a - expected).abs() < 1e-12,
                "corner angle {a} vs {expected}"
            );
            assert!(a < fov.to_radians() / 2.0 * 2f64.sqrt());
        }
        // Texel x grows along u, y along v, with the exact tangent.
        let (u, v) = orthonormal_basis(d);
        for _ in 0..20 {
            let x = rng.below(res as usize) as u32;
            let y = rng.below(res as usize) as u32;
            let ray = grid.ray(0, x, y);
            assert!((ray.direction.length() - 1.0).abs() < 1e-15);
            let fwd = ray.direction.dot(d);
            let s = k * ((x as f64 + 0.5) / res as f64 * 2.0 - 1.0);
            let t = k * ((y as f64 + 0.5) / res as f64 * 2.0 - 1.0);
            assert!((ray.direction.dot(u) / fwd - s).abs() < 1e-12 * (1.0 + k));
            assert!((ray.direction.dot(v) / fwd - t).abs() < 1e-12 * (1.0 + k));
        }
    }
}

#[test]
fn spot_along_an_axis_has_an_exact_centre_and_mirror_symmetry() {
    let grid = TexelGrid::new(
        &spot(DVec3::ONE, DVec3::NEG_Y, 90.0, 0.1, 10.0, 5),
        NO_WORLD,
    )
    .unwrap();
    assert_eq!(grid.ray(0, 2, 2).direction, DVec3::NEG_Y);
    // u = +X, v = +Z for −Y: texel (4, 2) leans towards +X, (0, 2) to −X by
    // the same amount.
    let right = grid.ray(0, 4, 2).direction;
    let left = grid.ray(0, 0, 2).direction;
    assert!(right.x > 0.0 && right.z.abs() < 1e-16);
    assert_eq!(left, DVec3::new(-right.x, right.y, right.z));
    let front = grid.ray(0, 2, 4).direction;
    assert!(front.z > 0.0 && front.x.abs() < 1e-16);
}

// ---------------------------------------------------------------------- point

#[test]
fn cube_face_table_matches_the_basis_and_is_right_handed() {
    for (axis, u, v) in CUBE_FACES {
        assert_eq!(orthonormal_basis(axis), (u, v), "face {axis}");
        assert_eq!(u.cross(v), axis);
    }
}

#[test]
fn point_light_face_centres_are_the_axes() {
    let position = DVec3::new(-7.0, 3.0, 1e6);
    let grid = TexelGrid::new(&point(position, 0.25, 30.0, 9), NO_WORLD).unwrap();
    assert_eq!((grid.faces(), grid.width(), grid.height()), (6, 9, 9));
    assert_eq!(grid.texel_count(), 6 * 81);
    let axes = [
        DVec3::X,
        DVec3::NEG_X,
        DVec3::Y,
        DVec3::NEG_Y,
        DVec3::Z,
        DVec3::NEG_Z,
    ];
    for (face, axis) in axes.into_iter().enumerate() {
        let ray = grid.ray(face, 4, 4);
        assert_eq!(ray.direction, axis, "face {}", CUBE_FACE_NAMES[face]);
        assert_eq!((ray.origin, ray.t_min, ray.t_max), (position, 0.25, 30.0));
        // Face corners are at 45°·√2-ish: atan(√2·(1 − 1/9)).
        let a = angle(grid.ray(face, 0, 8).direction, axis);
        assert!((a - (2f64.sqrt() * (1.0 - 1.0 / 9.0)).atan()).abs() < 1e-12);
    }
}

#[test]
fn point_light_faces_partition_the_sphere() {
    let res = 16u32;
    let grid = TexelGrid::new(&point(DVec3::ZERO, 0.1, 10.0, res), NO_WORLD).unwrap();
    let mut rng = Rng::new(0xc0be);
    let mut per_face = [0usize; 6];
    for _ in 0..50_000 {
        let r = rng.unit_vector();
        let owners: Vec<usize> = (0..6)
            .filter(|&f| {
                let (axis, u, v) = CUBE_FACES[f];
                let fwd = r.dot(axis);
                fwd > 0.0 && r.dot(u).abs() <= fwd && r.dot(v).abs() <= fwd
            })
            .collect();
        assert_eq!(owners.len(), 1, "direction {r} is in faces {owners:?}");
        let face = owners[0];
        per_face[face] += 1;
        // The texel of that face containing r has a ray within half a texel
        // diagonal of r (a texel spans at most 2/res radians on a cube face).
        let (axis, u, v) = CUBE_FACES[face];
        let fwd = r.dot(axis);
        let cell = |c: f64| (((c / fwd + 1.0) / 2.0 * res as f64) as u32).min(res - 1);
        let ray = grid.ray(face, cell(r.dot(u)), cell(r.dot(v)));
        let a = angle(ray.direction, r);
        assert!(a <= 2f64.sqrt() / res as f64, "texel ray {a} rad from {r}");
        // And the ray itself lies in the face's pyramid.
        let rf = ray.direction.dot(axis);
        assert!(ray.direction.dot(u).abs() < rf && ray.direction.dot(v).abs() < rf);
    }
    // Each face owns about a sixth of the sphere.
    for n in per_face {
        assert!((7_000..9_700).contains(&n), "face counts {per_face:?}");
    }
}

// -------------------------------------------------------------------- reaches

/// Boxes around points that rays really reach (including the ends of their
/// [t_min, t_max] and zero-size boxes) are always reachable.
fn assert_reaches_hit_boxes(grid: &TexelGrid, rng: &mut Rng) {
    let t_count = grid.texel_count();
    for _ in 0..2_000 {
        let index = (rng.next_u64() % t_count).min(t_count - 1);
        let (face, x, y) = grid.texel_at(index).unwrap();
        let ray = grid.ray(face, x, y);
        let t = match rng.below(4) {
            0 => ray.t_min,
            1 => ray.t_max,
            _ => rng.range(ray.t_min, ray.t_max),
        };
        let p = ray.at(t);
        let size = [0.0, 1e-6, 0.5, 20.0][rng.below(4)];
        let lo = DVec3::new(
            rng.range(0.0, size),
            rng.range(0.0, size),
            rng.range(0.0, size),
        );
        let hi = DVec3::new(
            rng.range(0.0, size),
            rng.range(0.0, size),
            rng.range(0.0, size),
        );
        assert!(
            grid.reaches(p - lo, p + hi),
            "box {}..{} around the hit point {p} of texel ({face}, {x}, {y}) at t = {t}",
            p - lo,
            p + hi
        );
    }
}

#[test]
fn reaches_keeps_every_box_a_ray_enters() {
    let mut rng = Rng::new(0x4eac);
    for _ in 0..40 {
        let position = DVec3::new(
            rng.range(-1e3, 1e3),
            rng.range(0.0, 50.0),
            rng.range(-1e3, 1e3),
        );
        let near = rng.range(0.01, 2.0);
        let far = near + rng.range(0.1, 200.0);
        let res = 1 + rng.below(64) as u32;
        let d = rng.unit_vector();
        let fov = rng.range(0.5, 179.0);
        let s = TexelGrid::new(&spot(position, d, fov, near, far, res), NO_WORLD).unwrap();
        assert_reaches_hit_boxes(&s, &mut rng);
        let p = TexelGrid::new(&point(position, near, far, res), NO_WORLD).unwrap();
        assert_reaches_hit_boxes(&p, &mut rng);
        let bounds = random_bounds(&mut rng);
        let texel_size = rng.range(1.0, 30.0);
        let g = TexelGrid::new(&directional(d, texel_size), bounds).unwrap();
        assert_reaches_hit_boxes(&g, &mut rng);
        // Every box inside the world bounds is reachable by a directional light.
        for _ in 0..200 {
            let a =
                bounds.0 + (bounds.1 - bounds.0) * DVec3::new(rng.unit(), rng.unit(), rng.unit());
            let b =
                bounds.0 + (bounds.1 - bounds.0) * DVec3::new(rng.unit(), rng.unit(), rng.unit());
            assert!(g.reaches(a.min(b), a.max(b)));
        }
        assert!(g.reaches(bounds.0, bounds.1));
    }
}

#[test]
fn reaches_drops_boxes_out_of_a_spot_lights_frustum() {
    // At the origin looking along −Y, 60° opening: the side planes are at
    // |x|, |z| = tan 30°·depth ≈ 0.577·depth.
    let grid = TexelGrid::new(
        &spot(DVec3::ZERO, DVec3::NEG_Y, 60.0, 1.0, 50.0, 64),
        NO_WORLD,
    )
    .unwrap();
    let cube = |c: DVec3, h: f64| (c - DVec3::splat(h), c + DVec3::splat(h));
    let reaches = |(lo, hi): (DVec3, DVec3)| grid.reaches(lo, hi);
    assert!(
        reaches(cube(DVec3::new(0.0, -10.0, 0.0), 1.0)),
        "on the axis"
    );
    assert!(
        !reaches(cube(DVec3::new(0.0, 10.0, 0.0), 1.0)),
        "behind the light"
    );
    assert!(
        !reaches(cube(DVec3::new(0.0, -60.0, 0.0), 5.0)),
        "beyond far"
    );
    assert!(
        reaches(cube(DVec3::new(0.0, -52.0, 0.0), 5.0)),
        "straddling far"
    );
    assert!(
        !reaches(cube(DVec3::new(0.0, -0.5, 0.0), 0.1)),
        "inside near"
    );
    assert!(
        !reaches(cube(DVec3::new(10.0, -10.0, 0.0), 1.0)),
        "beside the pyramid"
    );
    assert!(
        !reaches(cube(DVec3::new(0.0, -10.0, -8.0), 1.0)),
        "beside the pyramid"
    );
    // Touching the side plane x = 0.577·depth from outside still counts.
    let depth = 10.0;
    let edge = (30f64).to_radians().tan() * depth;
    assert!(reaches((
        DVec3::new(edge, -depth, -0.1),
        DVec3::new(edge + 1.0, -depth, 0.1)
    )));
    assert!(!reaches((
        DVec3::new(edge + 0.01, -depth, -0.1),
        DVec3::new(edge + 1.0, -depth, 0.1)
    )));
    // A box around the light itself reaches out of the near sphere.
    assert!(reaches(cube(DVec3::ZERO, 3.0)));
    // Empty boxes are never reached; NaN boxes always are (kept, not hidden).
    assert!(!grid.reaches(DVec3::new(1.0, -10.0, 0.0), DVec3::new(0.0, -9.0, 1.0)));
    assert!(grid.reaches(DVec3::splat(f64::NAN), DVec3::ONE));
}

#[test]
fn reaches_drops_boxes_out_of_a_point_lights_shell() {
    let c = DVec3::new(100.0, 5.0, -40.0);
    let grid = TexelGrid::new(&point(c, 0.5, 30.0, 32), NO_WORLD).unwrap();
    let mut rng = Rng::new(0x9017);
    for _ in 0..1_000 {
        let dir = rng.unit_vector();
        let h = rng.range(0.0, 3.0);
        // The box's nearest point is at least 30.5 away along some axis...
        let beyond = c + dir * (30.5 + h * 3f64.sqrt());
        assert!(!grid.reaches(beyond - DVec3::splat(h), beyond + DVec3::splat(h)));
        // ...while a box whose centre is inside the shell is reached.
        let inside = c + dir * rng.range(0.5, 30.0);
        assert!(grid.reaches(inside - DVec3::splat(h), inside + DVec3::splat(h)));
    }
    // Entirely within the near sphere: farthest corner at 0.25·√3 ≈ 0.433 < 0.5;
    // at 0.3·√3 ≈ 0.520 the corners poke out.
    assert!(!grid.reaches(c - DVec3::splat(0.25), c + DVec3::splat(0.25)));
    assert!(grid.reaches(c - DVec3::splat(0.3), c + DVec3::splat(0.3)));
}

#[test]
fn reaches_drops_boxes_outside_a_directional_lights_slab() {
    let bounds = (DVec3::ZERO, DVec3::new(100.0, 20.0, 100.0));
    let grid = TexelGrid::new(&directional(DVec3::NEG_Y, 1.0), bounds).unwrap();
    assert!(grid.reaches(bounds.0, bounds.1));
    assert!(!grid.reaches(DVec3::new(200.0, 0.0, 0.0), DVec3::new(210.0, 10.0, 10.0)));
    assert!(!grid.reaches(DVec3::new(0.0, 0.0, -50.0), DVec3::new(10.0, 10.0, -1.0)));
    // Above the ray origins (the light's "back"), and far below the world.
    assert!(!grid.reaches(DVec3::new(0.0, 500.0, 0.0), DVec3::new(10.0, 510.0, 10.0)));
    assert!(!grid.reaches(DVec3::new(0.0, -500.0, 0.0), DVec3::new(10.0, -490.0, 10.0)));
    // Just outside the world but inside the grid's last texel column.
    assert!(grid.reaches(DVec3::new(100.0, 0.0, 0.0), DVec3::new(100.0, 1.0, 1.0)));
}

// ----------------------------------------------------------------- indexing

#[test]
fn texel_indices_run_over_faces_rows_and_columns() {
    let grid = TexelGrid::new(&point(DVec3::ZERO, 0.1, 1.0, 3), NO_WORLD).unwrap();
    assert_eq!(grid.texel_at(0), Some((0, 0, 0)));
    assert_eq!(grid.texel_at(1), Some((0, 1, 0)));
    assert_eq!(grid.texel_at(3), Some((0, 0, 1)));
    assert_eq!(grid.texel_at(9), Some((1, 0, 0)));
    assert_eq!(grid.texel_at(53), Some((5, 2, 2)));
    assert_eq!(grid.texel_at(54), None);
    let mut seen = std::collections::HashSet::new();
    for i in 0..grid.texel_count() {
        assert!(seen.insert(grid.texel_at(i).unwrap()));
    }
    assert_eq!(seen.len(), 54);
}

#[test]
fn a_directional_point_projects_as_a_triangle_corner_does() {
    // Refinement's footprint box takes a caster's corners one at a time;
    // they must land where its triangles' polygons do (one formula serves
    // both), with the grid's sub-texel offset too.
    let mut rng = Rng::new(23);
    for _ in 0..200 {
        let bounds = random_bounds(&mut rng);
        let direction = DVec3::new(rng.unit() - 0.5, -rng.unit() - 0.1, rng.unit() - 0.5);
        let grid = TexelGrid::new(&directional(direction, 0.3 + rng.unit()), bounds)
            .unwrap()
            .with_offset((rng.unit(), rng.unit()));
        let p = bounds.0 + (bounds.1 - bounds.0) * DVec3::new(rng.unit(), rng.unit(), rng.unit());
        let corner = grid.project_triangle(0, [p, p, p]).unwrap()[0];
        assert_eq!(grid.project_point_directional(p), Some(corner));
    }
    let point_light = TexelGrid::new(
        &point(DVec3::ZERO, 0.1, 10.0, 64),
        (DVec3::splat(-1.0), DVec3::splat(1.0)),
    )
    .unwrap();
    assert_eq!(point_light.project_point_directional(DVec3::X), None);
}
