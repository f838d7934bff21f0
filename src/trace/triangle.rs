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

    /// [`PreparedRay::new`] of `ray`, whose direction is bit for bit the
    /// one `self` was prepared from: the permutation and shear are pure
    /// functions of the direction, so only the origin and range change
    /// (rays of a directional light's tile share their direction).
    #[inline]
    pub(crate) fn with_direction_of(&self, ray: &TraceRay) -> PreparedRay {
        if !self.valid {
            return PreparedRay::new(ray);
        }
        let valid = ray.origin.is_finite() && !ray.t_min.is_nan() && !ray.t_max.is_nan();
        if !valid {
            return PreparedRay::new(ray);
        }
        let prepared = PreparedRay {
            origin: ray.origin,
            t_min: ray.t_min,
            t_max: ray.t_max,
            ..*self
        };
        debug_assert_eq!(
            format!("{prepared:?}"),
            format!("{:?}", PreparedRay::new(ray)),
            "{ray:?}"
        );
        prepared
    }

    pub(crate) fn is_valid(&self) -> bool {
        self.valid
    }

    /// The shear along the first two axes of the test's permutation.
    pub(crate) fn sx(&self) -> f32 {
        self.sx
    }

    pub(crate) fn sy(&self) -> f32 {
        self.sy
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

/// Lanes per [`Lanes`] group: one AVX register of f32.
pub(crate) const LANES: usize = 8;

/// Up to [`LANES`] prepared rays sharing one permutation, laid out lane by
/// lane for the first step of [`hit_t`] over many rays at once: the shear of
/// the three vertices and the three f32 edge functions, with the same
/// operations in the same order (Rust does not contract `a - b * c`), so
/// each lane's values are bit for bit the single-ray test's. A lane that
/// step rejects is rejected by [`hit_t`] too; every other lane goes through
/// [`hit_t`] itself, so the hits are exactly the single-ray test's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Lanes {
    axes: [usize; 3],
    ox: [f32; LANES],
    oy: [f32; LANES],
    oz: [f32; LANES],
    sx: [f32; LANES],
    sy: [f32; LANES],
    live: u32,
}

impl Lanes {
    /// The permutation (kx, ky, kz) of a ray: rays of one group share it.
    pub(crate) fn axes_of(ray: &PreparedRay) -> [usize; 3] {
        [ray.kx, ray.ky, ray.kz]
    }

    /// At most [`LANES`] valid rays, all with the same [`Self::axes_of`].
    pub(crate) fn new<'r>(rays: impl Iterator<Item = &'r PreparedRay>) -> Lanes {
        let mut lanes = Lanes {
            axes: [0, 1, 2],
            ox: [0.0; LANES],
            oy: [0.0; LANES],
            oz: [0.0; LANES],
            sx: [0.0; LANES],
            sy: [0.0; LANES],
            live: 0,
        };
        for (l, ray) in rays.take(LANES).enumerate() {
            debug_assert!(ray.valid);
            lanes.axes = Self::axes_of(ray);
            let o = ray.origin.to_array();
            lanes.ox[l] = o[ray.kx];
            lanes.oy[l] = o[ray.ky];
            lanes.oz[l] = o[ray.kz];
            lanes.sx[l] = ray.sx;
            lanes.sy[l] = ray.sy;
            lanes.live |= 1 << l;
        }
        lanes
    }

    /// Bit l set when ray l passes [`hit_t`]'s early out (finite edge
    /// functions, not of mixed signs) for `tri`: only those can hit it.
    // Lanes index several arrays in lockstep: the form that vectorizes.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn candidates_inline(&self, tri: &TraceTriangle) -> u32 {
        let [kx, ky, kz] = self.axes;
        let permuted = |v: Vec3| {
            let a = v.to_array();
            (a[kx], a[ky], a[kz])
        };
        let (p0x, p0y, p0z) = permuted(tri.vertices[0]);
        let (p1x, p1y, p1z) = permuted(tri.vertices[1]);
        let (p2x, p2y, p2z) = permuted(tri.vertices[2]);
        let mut keep = [0u32; LANES];
        for l in 0..LANES {
            let (ox, oy, oz, sx, sy) = (self.ox[l], self.oy[l], self.oz[l], self.sx[l], self.sy[l]);
            let az = p0z - oz;
            let ax = (p0x - ox) - sx * az;
            let ay = (p0y - oy) - sy * az;
            let bz = p1z - oz;
            let bx = (p1x - ox) - sx * bz;
            let by = (p1y - oy) - sy * bz;
            let cz = p2z - oz;
            let cx = (p2x - ox) - sx * cz;
            let cy = (p2y - oy) - sy * cz;
            let u = cx * by - cy * bx;
            let v = ax * cy - ay * cx;
            let w = bx * ay - by * ax;
            let finite = u.is_finite() & v.is_finite() & w.is_finite();
            let negative = (u < 0.0) | (v < 0.0) | (w < 0.0);
            let positive = (u > 0.0) | (v > 0.0) | (w > 0.0);
            keep[l] = u32::from(finite & !(negative & positive));
        }
        let mut mask = 0;
        for (l, k) in keep.iter().enumerate() {
            mask |= k << l;
        }
        mask & self.live
    }

    /// [`Self::candidates_inline`] for the groups whose bit is set in
    /// `selected` (the others get an empty mask: the caller knows none of
    /// their rays can hit `tri`), into `masks`; with AVX2 when the processor
    /// has it (the same operations, eight lanes wide).
    pub(crate) fn candidates(
        groups: &[Lanes],
        tri: &TraceTriangle,
        masks: &mut [u32],
        selected: u64,
    ) {
        masks.fill(0);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the processor has AVX2 (checked just above).
            unsafe { candidates_avx2(groups, tri, masks, selected) };
            return;
        }
        candidates_portable(groups, tri, masks, selected);
    }
}

/// Every group of a frame (at most 64: a packet's 256 rays in groups of 8,
/// plus a partial group per permutation).
pub(crate) const ALL_GROUPS: u64 = u64::MAX;

#[inline(always)]
fn each_selected(
    groups: &[Lanes],
    masks: &mut [u32],
    selected: u64,
    mut f: impl FnMut(&Lanes) -> u32,
) {
    let mut bits = selected;
    while bits != 0 {
        let g = bits.trailing_zeros() as usize;
        bits &= bits - 1;
        let (Some(group), Some(mask)) = (groups.get(g), masks.get_mut(g)) else {
            return;
        };
        *mask = f(group);
    }
}

fn candidates_portable(groups: &[Lanes], tri: &TraceTriangle, masks: &mut [u32], selected: u64) {
    each_selected(groups, masks, selected, |g| g.candidates_inline(tri));
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn candidates_avx2(groups: &[Lanes], tri: &TraceTriangle, masks: &mut [u32], selected: u64) {
    each_selected(groups, masks, selected, |g| g.candidates_inline(tri));
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

    /// The lane filter keeps every ray the single-ray test hits (and
    /// rejects only what its early out rejects), portable and AVX2 alike.
    #[test]
    fn lane_filter_keeps_every_hit_and_matches_the_early_out() {
        let mut rng = crate::rng::Rng::new(5);
        let mut p = |s: f64| {
            vec3(
                rng.range(-s, s) as f32,
                rng.range(-s, s) as f32,
                rng.range(-s, s) as f32,
            )
        };
        let (mut kept, mut hits) = (0, 0);
        for round in 0..400 {
            let d = if round % 4 == 0 {
                Vec3::NEG_Y
            } else {
                (p(1.0) + vec3(0.0, -2.0, 0.0)).normalize()
            };
            let rays: Vec<PreparedRay> = (0..LANES)
                .map(|_| {
                    ray(
                        p(2.0) + vec3(0.0, 5.0, 0.0),
                        if round % 2 == 0 {
                            d
                        } else {
                            (d + p(0.05)).normalize()
                        },
                    )
                })
                .collect();
            let axes = Lanes::axes_of(&rays[0]);
            let same: Vec<&PreparedRay> =
                rays.iter().filter(|r| Lanes::axes_of(r) == axes).collect();
            let lanes = Lanes::new(same.iter().copied());
            for _ in 0..20 {
                let c = p(1.5);
                let t = tri(c + p(1.0), c + p(1.0), c + p(1.0));
                let mut portable = [0u32];
                candidates_portable(&[lanes], &t, &mut portable, ALL_GROUPS);
                let mut best = [0u32];
                Lanes::candidates(&[lanes], &t, &mut best, ALL_GROUPS);
                assert_eq!(portable, best);
                for (l, r) in same.iter().enumerate() {
                    let keep = portable[0] & (1 << l) != 0;
                    if hit_t(r, &t).is_some() {
                        assert!(keep, "lane {l} hits but was filtered out");
                        hits += 1;
                    }
                    kept += usize::from(keep);
                }
            }
        }
        assert!(hits > 100 && kept < 400 * 20 * LANES / 2, "{hits} {kept}");
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
