//! The per-light BVH: obvhs's compressed wide BVH8 (PLOC build, parallel with
//! rayon, no spatial splits) over the triangles' boxes, traversed with obvhs's
//! `traverse!` macro but with our own node and triangle tests.
//!
//! obvhs's own ray/node test is not conservative enough to be an exact
//! oracle-equivalent culler: it starts every ray at t = 1e-4, replaces the
//! inverse of direction components below f32::EPSILON by ±1/EPSILON (wrong
//! slab distances for nearly axis-parallel rays) and makes zero-width slabs of
//! flat geometry depend on exact rounding. Ours pads every child box at run
//! time by `m`, a few hundred ulps of the magnitude of the scene and the ray
//! origin, which covers the quantization rounding of the build and the
//! rounding of the slab arithmetic, and treats NaN slabs as unbounded. Boxes
//! only cull; the triangle test decides hits, so the hits of a ray do not
//! depend on the BVH's shape.

use super::triangle::{hit_t, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle};
use glam::{UVec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
use obvhs::cwbvh::node::{extract_byte64, CwBvhNode};
use obvhs::cwbvh::CwBvh;
use obvhs::ploc::PlocBuilder;
use obvhs::BvhBuildParams;

/// Hit::triangle is a u32; triangles past this index are ignored.
pub(crate) const MAX_TRIANGLES: usize = u32::MAX as usize;

/// Box padding in units of f32::EPSILON × magnitude. The build's rounding
/// (child − node origin, quantization exponent) and the slab arithmetic each
/// err by a few ulps of the magnitude; this leaves a wide margin.
const PAD_EPSILONS: f32 = 256.0;

/// Direction components smaller than this are raised to it (keeping the
/// sign) so the slab arithmetic stays finite; the position error it causes,
/// 1e-18·t, is far below the padding for any t within the scene.
const MIN_DIRECTION: f32 = 1e-18;

#[derive(Clone, Copy, Debug)]
struct BvhTriangle {
    tri: TraceTriangle,
    /// Index into the build input.
    index: u32,
}

/// A BVH over one light's triangles. Triangle data is laid out in BVH order so
/// traversal reads it sequentially.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    cwbvh: CwBvh,
    triangles: Vec<BvhTriangle>,
    /// Largest absolute coordinate of any built triangle.
    magnitude: f32,
}

impl Bvh {
    /// Builds in parallel (rayon); no spatial splits (each triangle in exactly
    /// one leaf). NaN, Inf and huge triangles ([`TraceTriangle::is_usable`]) are left out.
    pub fn build(triangles: &[TraceTriangle]) -> Bvh {
        let mut aabbs = Vec::with_capacity(triangles.len());
        let mut kept = Vec::with_capacity(triangles.len());
        let mut magnitude = 0.0f32;
        for (index, tri) in triangles.iter().enumerate().take(MAX_TRIANGLES) {
            if !tri.is_usable() {
                continue;
            }
            let [a, b, c] = tri.vertices.map(Vec3A::from);
            let aabb = Aabb::from_points(&[a, b, c]);
            magnitude = magnitude
                .max(aabb.min.abs().max_element())
                .max(aabb.max.abs().max_element());
            aabbs.push(aabb);
            kept.push(BvhTriangle {
                tri: *tri,
                index: index as u32,
            });
        }
        if aabbs.is_empty() {
            return Bvh::default();
        }
        // What obvhs's build_cwbvh does, minus its debug-build validation,
        // whose absolute 1e-5 tolerances fail on coordinates of ~1e4.
        let params = BvhBuildParams::medium_build();
        let mut bvh2 = PlocBuilder::with_capacity(aabbs.len()).build(
            params.ploc_search_distance,
            &aabbs,
            (0..aabbs.len() as u32).collect(),
            params.sort_precision,
            params.search_depth_threshold,
        );
        ReinsertionOptimizer::default().run(&mut bvh2, params.reinsertion_batch_ratio, None);
        let cwbvh = bvh2_to_cwbvh(&bvh2, params.max_prims_per_leaf.clamp(1, 3), true, false);
        let triangles = cwbvh
            .primitive_indices
            .iter()
            .map(|&p| kept[p as usize])
            .collect();
        Bvh {
            cwbvh,
            triangles,
            magnitude,
        }
    }

    /// Triangles in the BVH (unusable ones left out).
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Calls `on_hit` for every triangle the ray crosses with
    /// `t_min <= t <= current t_max`; `on_hit` returns the new t_max (a larger
    /// or NaN value is ignored) so callers can stop looking beyond what can
    /// still change their answer. Hits arrive in traversal order (not sorted).
    pub fn for_each_hit(&self, ray: &TraceRay, mut on_hit: impl FnMut(Hit) -> f32) {
        if self.cwbvh.nodes.is_empty() {
            return;
        }
        let prepared = PreparedRay::new(ray);
        // A NaN range was rejected by PreparedRay.
        if !prepared.is_valid() || ray.t_min > ray.t_max {
            return;
        }
        let boxes = BoxRay::new(ray, self.magnitude);
        let t_min = ray.t_min;
        let mut t_max = ray.t_max;
        let mut node_t_max = boxes.node_t_max(t_max);
        let mut state = self.cwbvh.new_traversal(Vec3A::from(ray.direction));
        let mut node: &CwBvhNode;
        'traversal: {
            obvhs::traverse!(
                self.cwbvh,
                node,
                state,
                boxes.hitmask(node, state.oct_inv4, t_min, node_t_max),
                {
                    let Some(entry) = self.triangles.get(state.primitive_id as usize) else {
                        continue;
                    };
                    if let Some((t, back_facing)) = hit_t(&prepared, &entry.tri) {
                        if t >= t_min && t <= t_max {
                            let next = on_hit(Hit {
                                t,
                                triangle: entry.index,
                                caster: entry.tri.caster,
                                back_facing,
                            });
                            if next < t_max {
                                t_max = next;
                                if t_max < t_min {
                                    break 'traversal;
                                }
                                node_t_max = boxes.node_t_max(t_max);
                            }
                        }
                    }
                }
            );
        }
    }

    /// The closest hit, with the same triangle test; equal t: the lowest
    /// triangle index, so the answer does not depend on traversal order.
    pub fn closest_hit(&self, ray: &TraceRay) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        self.for_each_hit(ray, |hit| {
            if best.is_none_or(|b| (hit.t, hit.triangle) < (b.t, b.triangle)) {
                best = Some(hit);
            }
            best.map_or(hit.t, |b| b.t)
        });
        best
    }

    /// obvhs's own closest-hit traversal and node test with its own
    /// (Möller–Trumbore) triangle test, for benchmarks only: not watertight,
    /// and its node test can miss hits (see the module doc).
    pub fn closest_hit_obvhs(&self, ray: &TraceRay) -> Option<f32> {
        if self.cwbvh.nodes.is_empty()
            || !ray.origin.is_finite()
            || !ray.direction.is_finite()
            || ray.direction == Vec3::ZERO
            || ray.t_min.is_nan()
            || ray.t_max.is_nan()
        {
            return None;
        }
        let r = obvhs::ray::Ray::new(
            ray.origin.into(),
            ray.direction.into(),
            ray.t_min,
            ray.t_max,
        );
        let mut hit = obvhs::ray::RayHit::none();
        let found = self.cwbvh.ray_traverse(r, &mut hit, |r, id| {
            self.triangles.get(id).map_or(f32::INFINITY, |e| {
                let [v0, v1, v2] = e.tri.vertices.map(Vec3A::from);
                obvhs::triangle::Triangle { v0, v1, v2 }.intersect(r)
            })
        });
        found.then_some(hit.t)
    }
}

/// The ray as the node test sees it: two origins shifted by ∓m along each
/// axis, so that near planes are moved towards the ray and far planes away,
/// i.e. every box is grown by m on every side.
struct BoxRay {
    inv: Vec3A,
    negative: [bool; 3],
    origin_near: Vec3A,
    origin_far: Vec3A,
    pad: f32,
}

impl BoxRay {
    fn new(ray: &TraceRay, magnitude: f32) -> BoxRay {
        let pad =
            PAD_EPSILONS * f32::EPSILON * (magnitude + ray.origin.abs().max_element()) + 1e-30;
        let mut inv = [0.0; 3];
        let mut negative = [false; 3];
        let mut origin_near = [0.0; 3];
        let mut origin_far = [0.0; 3];
        for i in 0..3 {
            // + 0.0 turns -0.0 into +0.0: a zero component picks lo as near.
            let d = ray.direction[i] + 0.0;
            let d = if d.abs() < MIN_DIRECTION {
                MIN_DIRECTION.copysign(d)
            } else {
                d
            };
            inv[i] = 1.0 / d;
            negative[i] = d < 0.0;
            let o = ray.origin[i];
            let s = if negative[i] { -pad } else { pad };
            origin_near[i] = o + s;
            origin_far[i] = o - s;
        }
        BoxRay {
            inv: inv.into(),
            negative,
            origin_near: origin_near.into(),
            origin_far: origin_far.into(),
            pad,
        }
    }

    /// The t bound used for culling: t_max plus slack, so that a hit whose
    /// computed t lies just within t_max while the exact point lies just
    /// beyond it is still visited.
    fn node_t_max(&self, t_max: f32) -> f32 {
        t_max + 4.0 * self.pad + t_max.abs() * (1.0 / 65536.0)
    }

    /// obvhs's hit mask for the children of `node` whose padded box the ray
    /// segment [t_lo, t_hi] touches. NaN anywhere counts as a touch.
    #[inline(always)]
    fn hitmask(&self, node: &CwBvhNode, oct_inv4: u32, t_lo: f32, t_hi: f32) -> u32 {
        #[cfg(target_arch = "x86_64")]
        {
            self.hitmask_sse(node, oct_inv4, t_lo, t_hi)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self.hitmask_scalar(node, oct_inv4, t_lo, t_hi)
        }
    }

    /// The same test four children at a time (SSE2, always present on
    /// x86_64). Operand order matters for NaN: `_mm_max_ps(a, b)` returns b
    /// when either is NaN, so a NaN slab is ignored (unbounded), as in the
    /// scalar version.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn hitmask_sse(&self, node: &CwBvhNode, oct_inv4: u32, t_lo: f32, t_hi: f32) -> u32 {
        use std::arch::x86_64::*;
        let p = Vec3A::from(node.p);
        let scale = node.compute_extent() * self.inv;
        let near0 = (p - self.origin_near) * self.inv;
        let far0 = (p - self.origin_far) * self.inv;
        let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
        let pick = |neg: bool, lo: &[u8; 8], hi: &[u8; 8], i: usize| {
            let (n, f) = if neg { (hi, lo) } else { (lo, hi) };
            let q = |v: &[u8; 8]| {
                // SAFETY: SSE2 is part of the x86_64 baseline; loads are
                // from in-bounds array elements.
                unsafe {
                    _mm_set_ps(
                        v[i * 4 + 3] as f32,
                        v[i * 4 + 2] as f32,
                        v[i * 4 + 1] as f32,
                        v[i * 4] as f32,
                    )
                }
            };
            (q(n), q(f))
        };
        let mut hit_mask = 0;
        // SAFETY: SSE2 is part of the x86_64 baseline.
        unsafe {
            let lo = _mm_set1_ps(t_lo);
            let hi = _mm_set1_ps(t_hi);
            for i in 0..2 {
                let (nx, fx) = pick(self.negative[0], &node.child_min_x, &node.child_max_x, i);
                let (ny, fy) = pick(self.negative[1], &node.child_min_y, &node.child_max_y, i);
                let (nz, fz) = pick(self.negative[2], &node.child_min_z, &node.child_max_z, i);
                let slab = |q: __m128, s: f32, o: f32| {
                    _mm_add_ps(_mm_mul_ps(q, _mm_set1_ps(s)), _mm_set1_ps(o))
                };
                let t_near = _mm_max_ps(slab(nx, scale.x, near0.x), lo);
                let t_near = _mm_max_ps(slab(ny, scale.y, near0.y), t_near);
                let t_near = _mm_max_ps(slab(nz, scale.z, near0.z), t_near);
                let t_far = _mm_min_ps(slab(fx, scale.x, far0.x), hi);
                let t_far = _mm_min_ps(slab(fy, scale.y, far0.y), t_far);
                let t_far = _mm_min_ps(slab(fz, scale.z, far0.z), t_far);
                let mask = _mm_movemask_ps(_mm_cmpngt_ps(t_near, t_far));
                for j in 0..4 {
                    if mask & (1 << j) != 0 {
                        let c = i * 4 + j;
                        hit_mask |= extract_byte64(child_bits8, c) << extract_byte64(bit_index8, c);
                    }
                }
            }
        }
        hit_mask
    }

    #[cfg_attr(target_arch = "x86_64", allow(dead_code))]
    #[inline(always)]
    fn hitmask_scalar(&self, node: &CwBvhNode, oct_inv4: u32, t_lo: f32, t_hi: f32) -> u32 {
        let p = Vec3A::from(node.p);
        let scale = node.compute_extent() * self.inv;
        let near0 = (p - self.origin_near) * self.inv;
        let far0 = (p - self.origin_far) * self.inv;
        let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
        let pick = |neg: bool, lo: &[u8; 8], hi: &[u8; 8], c: usize| {
            if neg {
                (hi[c] as f32, lo[c] as f32)
            } else {
                (lo[c] as f32, hi[c] as f32)
            }
        };
        let mut hit_mask = 0;
        for c in 0..8 {
            let (nx, fx) = pick(self.negative[0], &node.child_min_x, &node.child_max_x, c);
            let (ny, fy) = pick(self.negative[1], &node.child_min_y, &node.child_max_y, c);
            let (nz, fz) = pick(self.negative[2], &node.child_min_z, &node.child_max_z, c);
            let t_near = (nx * scale.x + near0.x)
                .max(ny * scale.y + near0.y)
                .max(nz * scale.z + near0.z)
                .max(t_lo);
            let t_far = (fx * scale.x + far0.x)
                .min(fy * scale.y + far0.y)
                .min(fz * scale.z + far0.z)
                .min(t_hi);
            // Written so that NaN (incomparable) counts as a touch.
            if t_near.partial_cmp(&t_far) != Some(std::cmp::Ordering::Greater) {
                hit_mask |= extract_byte64(child_bits8, c) << extract_byte64(bit_index8, c);
            }
        }
        hit_mask
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::vec3;

    fn quad_soup() -> Vec<TraceTriangle> {
        (0..50)
            .map(|i| TraceTriangle {
                vertices: [
                    vec3(i as f32, 0.0, 0.0),
                    vec3(i as f32 + 1.0, 0.0, 0.0),
                    vec3(i as f32, 1.0, 0.0),
                ],
                caster: i,
            })
            .collect()
    }

    #[test]
    fn empty_input_builds_and_never_hits() {
        let bvh = Bvh::build(&[]);
        assert_eq!(bvh.triangle_count(), 0);
        let ray = TraceRay {
            origin: vec3(0.0, 0.0, 1.0),
            direction: vec3(0.0, 0.0, -1.0),
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        let mut n = 0;
        bvh.for_each_hit(&ray, |h| {
            n += 1;
            h.t
        });
        assert_eq!(n, 0);
        assert_eq!(bvh.closest_hit(&ray), None);
        assert_eq!(bvh.closest_hit_obvhs(&ray), None);
    }

    #[test]
    fn nan_triangles_are_left_out_and_indices_are_the_callers() {
        let mut tris = quad_soup();
        tris[3].vertices[1].y = f32::NAN;
        tris[4].vertices[2].z = f32::INFINITY;
        tris[5].vertices[0].x = 3e38;
        tris[6].vertices[0].z = -2e15;
        let bvh = Bvh::build(&tris);
        assert_eq!(bvh.triangle_count(), 46);
        for i in 0..50u32 {
            let ray = TraceRay {
                origin: vec3(i as f32 + 0.25, 0.25, 1.0),
                direction: vec3(0.0, 0.0, -1.0),
                t_min: 0.0,
                t_max: f32::INFINITY,
            };
            let hit = bvh.closest_hit(&ray);
            if (3..=6).contains(&i) {
                assert_eq!(hit, None);
            } else {
                assert_eq!(
                    hit,
                    Some(Hit {
                        t: 1.0,
                        triangle: i,
                        caster: i,
                        back_facing: false
                    })
                );
                assert_eq!(bvh.closest_hit_obvhs(&ray), Some(1.0));
            }
        }
    }

    #[test]
    fn single_triangle() {
        let tris = &quad_soup()[..1];
        let bvh = Bvh::build(tris);
        assert_eq!(bvh.triangle_count(), 1);
        let ray = TraceRay {
            origin: vec3(0.25, 0.25, -2.0),
            direction: vec3(0.0, 0.0, 1.0),
            t_min: 0.0,
            t_max: 10.0,
        };
        assert_eq!(
            bvh.closest_hit(&ray).map(|h| (h.t, h.back_facing)),
            Some((2.0, true))
        );
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn sse_and_scalar_node_tests_agree() {
        let mut rng = crate::rng::Rng::new(21);
        let mut tris = Vec::new();
        for i in 0..3000 {
            let mut p = || {
                vec3(
                    rng.range(-50.0, 50.0) as f32,
                    rng.range(-50.0, 50.0) as f32,
                    rng.range(-5.0, 5.0) as f32,
                )
            };
            let c = p();
            tris.push(TraceTriangle {
                vertices: [c, c + p() * 0.1, c + p() * 0.1],
                caster: i,
            });
        }
        let bvh = Bvh::build(&tris);
        let mut tested = 0;
        let mut touched = 0;
        for k in 0..300 {
            let mut d = vec3(
                rng.range(-1.0, 1.0) as f32,
                rng.range(-1.0, 1.0) as f32,
                rng.range(-1.0, 1.0) as f32,
            );
            if k % 3 == 0 {
                d = [Vec3::X, Vec3::NEG_Y, Vec3::Z][k % 9 / 3];
            }
            let ray = TraceRay {
                origin: vec3(
                    rng.range(-60.0, 60.0) as f32,
                    rng.range(-60.0, 60.0) as f32,
                    20.0,
                ),
                direction: d.normalize(),
                t_min: rng.range(-10.0, 10.0) as f32,
                t_max: rng.range(10.0, 200.0) as f32,
            };
            let boxes = BoxRay::new(&ray, bvh.magnitude);
            let oct = bvh.cwbvh.new_traversal(Vec3A::from(ray.direction)).oct_inv4;
            for node in &bvh.cwbvh.nodes {
                let a = boxes.hitmask_sse(node, oct, ray.t_min, ray.t_max);
                assert_eq!(a, boxes.hitmask_scalar(node, oct, ray.t_min, ray.t_max));
                tested += 1;
                touched += (a != 0) as usize;
            }
        }
        assert!(touched > 100 && touched < tested, "{touched} of {tested}");
    }

    #[test]
    fn hits_at_t_zero_are_not_lost() {
        // obvhs's own node test starts rays at t = 1e-4.
        let tris = quad_soup();
        let bvh = Bvh::build(&tris);
        let ray = TraceRay {
            origin: vec3(7.25, 0.25, 0.0),
            direction: vec3(0.0, 0.0, -1.0),
            t_min: 0.0,
            t_max: 1.0,
        };
        assert_eq!(
            bvh.closest_hit(&ray).map(|h| (h.t, h.triangle)),
            Some((0.0, 7))
        );
    }
}
