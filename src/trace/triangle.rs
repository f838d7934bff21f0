//! The watertight ray/triangle test (Woop, Benthin & Wald, "Watertight
//! Ray/Triangle Intersection", JCGT 2013) with a tie rule for rays exactly on
//! an edge or vertex, so that every surface crossing is counted exactly once.
//!
//! The ray is made the +z axis of a sheared frame (permute so that the
//! dominant direction axis is z, shear x and y along it). Each vertex is
//! transformed on its own, so a vertex shared by two triangles gets bit-equal
//! 2D coordinates in both. The three 2D edge functions are
//! `E = P.x·Q.y − P.y·Q.x` for an edge Q→P; the neighbour across that edge
//! computes `Q.x·P.y − Q.y·P.x`, the exact negation. A nonzero f32 edge
//! function has the exact sign (rounding is monotone), and an f32 zero is
//! recomputed in f64, where products of f32 are exact and only the final
//! subtraction rounds, so its sign (and zero) is exact too.
//!
//! # Tie rule
//! When an edge function is exactly 0 the ray's 2D point (the origin of the
//! sheared frame) lies on the edge's line. It counts as inside that edge if the
//! point moved by the symbolic perturbation s = (ε, ε²) (ε → 0⁺) is inside. For
//! an edge with direction D, E(s) = E + s.x·D.y − s.y·D.x, so with the
//! orientation-normalised direction D (reversed for back-facing triangles, so
//! the rule is the same for each facing) the edge owns the point iff
//! `D.y > 0 || (D.y == 0 && D.x < 0)` — a rasterizer's top-left rule. Because
//! this is one perturbation for the whole ray, it is consistent everywhere:
//! - an edge shared by two triangles that the ray crosses through (both front
//!   or both back facing, opposite edge directions) belongs to exactly one;
//! - a vertex (two edge functions 0) belongs to exactly one triangle of a fan
//!   covering its neighbourhood, the one the perturbed point falls into;
//! - at a silhouette fold (one front, one back facing triangle, the same
//!   normalised direction) both or neither are hit, so a grazing ray enters and
//!   leaves or does not touch — never an odd count.

use super::{TraceRay, TraceTriangle};
use glam::Vec3;

/// A ray prepared for [`intersect`]: the permutation and shear of the
/// watertight test, computed once per ray.
#[derive(Clone, Copy, Debug)]
pub struct PreparedRay {
    origin: Vec3,
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f32,
    sy: f32,
    sz: f32,
    /// False for a NaN/Inf origin or direction, a zero direction or a NaN
    /// t range: such a ray hits nothing.
    valid: bool,
    pub t_min: f32,
    pub t_max: f32,
}

impl PreparedRay {
    pub fn new(ray: &TraceRay) -> PreparedRay {
        let d = ray.direction.to_array();
        let abs = ray.direction.abs();
        // First maximum wins ties, so the frame is a pure function of the ray.
        let kz = if abs.x >= abs.y && abs.x >= abs.z {
            0
        } else if abs.y >= abs.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        // Keeps the sheared frame's winding, so det > 0 means front facing.
        if d[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let dz = d[kz];
        let valid = ray.origin.is_finite()
            && ray.direction.is_finite()
            && dz != 0.0
            && !ray.t_min.is_nan()
            && !ray.t_max.is_nan();
        let (sx, sy, sz) = if valid {
            (d[kx] / dz, d[ky] / dz, 1.0 / dz)
        } else {
            (0.0, 0.0, 0.0)
        };
        PreparedRay {
            origin: ray.origin,
            kx,
            ky,
            kz,
            sx,
            sy,
            sz,
            valid,
            t_min: ray.t_min,
            t_max: ray.t_max,
        }
    }

    pub(crate) fn is_valid(&self) -> bool {
        self.valid
    }

    /// The vertex in the sheared frame: 2D position and scaled depth.
    #[inline(always)]
    fn shear(&self, v: Vec3) -> (f32, f32, f32) {
        let a = (v - self.origin).to_array();
        let z = a[self.kz];
        (
            a[self.kx] - self.sx * z,
            a[self.ky] - self.sy * z,
            self.sz * z,
        )
    }
}

/// The watertight test within the ray's own `[t_min, t_max]`. Returns
/// `(t, back_facing)`, back_facing = geometric normal · direction > 0;
/// a triangle seen edge-on (det = 0), a NaN/Inf triangle or an invalid ray:
/// `None`.
pub fn intersect(ray: &PreparedRay, tri: &TraceTriangle) -> Option<(f32, bool)> {
    let (t, back) = hit_t(ray, tri)?;
    (t >= ray.t_min && t <= ray.t_max).then_some((t, back))
}

/// One triangle of a multi-hit traversal: if the ray crosses it within
/// `[t_min, t_max]`, reports the hit (`index`: the caller's triangle number)
/// and returns the caller's new t_max (a larger or NaN answer is ignored).
#[inline(always)]
pub(crate) fn report_hit(
    ray: &PreparedRay,
    tri: &TraceTriangle,
    index: u32,
    t_max: f32,
    on_hit: &mut impl FnMut(super::Hit) -> f32,
) -> f32 {
    if let Some((t, back_facing)) = hit_t(ray, tri) {
        if t >= ray.t_min && t <= t_max {
            let next = on_hit(super::Hit {
                t,
                triangle: index,
                caster: tri.caster,
                back_facing,
            });
            if next < t_max {
                return next;
            }
        }
    }
    t_max
}

/// The test without a range check, for traversals whose t_max shrinks.
#[inline(always)]
pub(crate) fn hit_t(ray: &PreparedRay, tri: &TraceTriangle) -> Option<(f32, bool)> {
    if !ray.valid {
        return None;
    }
    let [v0, v1, v2] = tri.vertices;
    let (ax, ay, az) = ray.shear(v0);
    let (bx, by, bz) = ray.shear(v1);
    let (cx, cy, cz) = ray.shear(v2);

    // U: edge v1→v2 (weight of v0), V: edge v2→v0, W: edge v0→v1.
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if !(u.is_finite() && v.is_finite() && w.is_finite()) {
        return None;
    }
    // Early out on the common miss before any exactness work.
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let (u, v, w) = if u == 0.0 || v == 0.0 || w == 0.0 {
        let f = |p: f32, q: f32, r: f32, s: f32| p as f64 * q as f64 - r as f64 * s as f64;
        (f(cx, by, cy, bx), f(ax, cy, ay, cx), f(bx, ay, by, ax))
    } else {
        (u as f64, v as f64, w as f64)
    };
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let front = det > 0.0;
    let edges = [
        (u, cx - bx, cy - by),
        (v, ax - cx, ay - cy),
        (w, bx - ax, by - ay),
    ];
    for (e, dx, dy) in edges {
        if e == 0.0 {
            let (dx, dy) = if front { (dx, dy) } else { (-dx, -dy) };
            let owns = dy > 0.0 || (dy == 0.0 && dx < 0.0);
            if !owns {
                return None;
            }
        } else if (e > 0.0) != front {
            return None;
        }
    }
    // Written relative to v0's depth so a plane facing the ray gets its exact
    // depth, and in f64 so tiny weights (f64 fallback) do not underflow.
    let (az, bz, cz) = (az as f64, bz as f64, cz as f64);
    let t = az + (v * (bz - az) + w * (cz - az)) / det;
    let t = t as f32;
    t.is_finite().then_some((t, !front))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::vec3;

    fn ray(o: Vec3, d: Vec3) -> PreparedRay {
        PreparedRay::new(&TraceRay {
            origin: o,
            direction: d,
            t_min: 0.0,
            t_max: f32::INFINITY,
        })
    }

    fn tri(a: Vec3, b: Vec3, c: Vec3) -> TraceTriangle {
        TraceTriangle {
            vertices: [a, b, c],
            caster: 7,
        }
    }

    /// Counter-clockwise seen from +z: normal +z.
    fn unit_xy() -> TraceTriangle {
        tri(
            vec3(0.0, 0.0, 0.0),
            vec3(1.0, 0.0, 0.0),
            vec3(0.0, 1.0, 0.0),
        )
    }

    #[test]
    fn front_and_back_facing_with_exact_t() {
        let t = unit_xy();
        // From above, looking down -z: normal · d = -1 → front.
        let r = ray(vec3(0.25, 0.25, 5.0), vec3(0.0, 0.0, -1.0));
        assert_eq!(intersect(&r, &t), Some((5.0, false)));
        // From below looking up: back.
        let r = ray(vec3(0.25, 0.25, -3.0), vec3(0.0, 0.0, 1.0));
        assert_eq!(intersect(&r, &t), Some((3.0, true)));
        // Along x onto a plane x = 2 facing -x (normal (-1,0,0)).
        let wall = tri(
            vec3(2.0, 0.0, 0.0),
            vec3(2.0, 0.0, 1.0),
            vec3(2.0, 1.0, 0.0),
        );
        let n = (wall.vertices[1] - wall.vertices[0]).cross(wall.vertices[2] - wall.vertices[0]);
        assert_eq!(n, vec3(-1.0, 0.0, 0.0));
        let r = ray(vec3(0.0, 0.25, 0.25), vec3(1.0, 0.0, 0.0));
        assert_eq!(intersect(&r, &wall), Some((2.0, false)));
        let r = ray(vec3(9.0, 0.25, 0.25), vec3(-1.0, 0.0, 0.0));
        assert_eq!(intersect(&r, &wall), Some((7.0, true)));
    }

    #[test]
    fn facing_agrees_with_the_geometric_normal_for_oblique_rays() {
        let mut rng = crate::rng::Rng::new(11);
        let mut checked = 0;
        for _ in 0..2000 {
            let mut p = || {
                vec3(
                    rng.range(-1.0, 1.0) as f32,
                    rng.range(-1.0, 1.0) as f32,
                    rng.range(-1.0, 1.0) as f32,
                )
            };
            let t = tri(p(), p(), p());
            let o = p() * 3.0;
            let target = (t.vertices[0] + t.vertices[1] + t.vertices[2]) / 3.0;
            let d = (target - o).normalize();
            let n = (t.vertices[1] - t.vertices[0]).cross(t.vertices[2] - t.vertices[0]);
            // Near grazing, the f32 rounding of d alone moves the hit a lot.
            if n.normalize().dot(d).abs() < 0.05 {
                continue;
            }
            let (hit_t, back) = intersect(&ray(o, d), &t).expect("ray through the centroid hits");
            assert_eq!(back, n.dot(d) > 0.0);
            assert!(
                (hit_t - (target - o).length()).abs() < 1e-4,
                "t {hit_t} want {} cos {}",
                (target - o).length(),
                n.normalize().dot(d)
            );
            checked += 1;
        }
        assert!(checked > 1000, "{checked}");
    }

    #[test]
    fn range_misses_and_edge_on() {
        let t = unit_xy();
        let r = PreparedRay::new(&TraceRay {
            origin: vec3(0.25, 0.25, 5.0),
            direction: vec3(0.0, 0.0, -1.0),
            t_min: 0.0,
            t_max: 4.0,
        });
        assert_eq!(intersect(&r, &t), None, "beyond t_max");
        let r = PreparedRay::new(&TraceRay {
            origin: vec3(0.25, 0.25, 5.0),
            direction: vec3(0.0, 0.0, -1.0),
            t_min: 5.0,
            t_max: 5.0,
        });
        assert_eq!(intersect(&r, &t), Some((5.0, false)), "t range is closed");
        // Outside the triangle.
        assert_eq!(
            intersect(&ray(vec3(0.75, 0.75, 1.0), vec3(0.0, 0.0, -1.0)), &t),
            None
        );
        // Edge-on: the ray lies in the triangle's plane, through its interior.
        assert_eq!(
            intersect(&ray(vec3(-1.0, 0.25, 0.0), vec3(1.0, 0.0, 0.0)), &t),
            None
        );
        assert_eq!(
            intersect(
                &ray(vec3(-1.0, -1.0, 0.0), vec3(1.0, 1.0, 0.0).normalize()),
                &t
            ),
            None
        );
    }

    #[test]
    fn nan_inf_and_degenerate_input_never_hit() {
        let r = ray(vec3(0.25, 0.25, 5.0), vec3(0.0, 0.0, -1.0));
        let mut t = unit_xy();
        t.vertices[1].x = f32::NAN;
        assert_eq!(intersect(&r, &t), None);
        t.vertices[1].x = f32::INFINITY;
        assert_eq!(intersect(&r, &t), None);
        let mut t = unit_xy();
        t.vertices[2].z = f32::NEG_INFINITY;
        assert_eq!(intersect(&r, &t), None);
        // Zero area: all three vertices equal; and collinear along x.
        let p = vec3(0.25, 0.25, 0.0);
        assert_eq!(intersect(&r, &tri(p, p, p)), None);
        let line = tri(
            vec3(0.0, 0.25, 0.0),
            vec3(0.5, 0.25, 0.0),
            vec3(1.0, 0.25, 0.0),
        );
        assert_eq!(intersect(&r, &line), None);
        // Invalid rays.
        let t = unit_xy();
        assert_eq!(intersect(&ray(vec3(0.25, 0.25, 5.0), Vec3::ZERO), &t), None);
        assert_eq!(
            intersect(&ray(vec3(0.25, 0.25, 5.0), vec3(0.0, f32::NAN, -1.0)), &t),
            None
        );
        assert_eq!(
            intersect(&ray(vec3(f32::NAN, 0.25, 5.0), vec3(0.0, 0.0, -1.0)), &t),
            None
        );
        let mut nan_range = ray(vec3(0.25, 0.25, 5.0), vec3(0.0, 0.0, -1.0));
        nan_range.t_max = f32::NAN;
        assert_eq!(intersect(&nan_range, &t), None);
        assert!(!PreparedRay::new(&TraceRay {
            origin: Vec3::ZERO,
            direction: vec3(0.0, 0.0, -1.0),
            t_min: f32::NAN,
            t_max: 1.0
        })
        .is_valid());
    }

    #[test]
    fn tie_rule_splits_a_shared_edge_for_both_facings() {
        // Two triangles of the square [0,1]² sharing the diagonal (1,0)-(0,1),
        // both wound +z.
        let a = tri(
            vec3(0.0, 0.0, 0.0),
            vec3(1.0, 0.0, 0.0),
            vec3(0.0, 1.0, 0.0),
        );
        let b = tri(
            vec3(1.0, 0.0, 0.0),
            vec3(1.0, 1.0, 0.0),
            vec3(0.0, 1.0, 0.0),
        );
        for (o, d) in [
            (vec3(0.5, 0.5, 2.0), vec3(0.0, 0.0, -1.0)),
            (vec3(0.5, 0.5, -2.0), vec3(0.0, 0.0, 1.0)),
        ] {
            let r = ray(o, d);
            let hits = [intersect(&r, &a), intersect(&r, &b)];
            assert_eq!(hits.iter().flatten().count(), 1, "{o} {d}: {hits:?}");
        }
    }
}
