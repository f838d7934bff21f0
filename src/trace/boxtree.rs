//! A box tree: obvhs's compressed wide BVH8 (PLOC build, parallel with
//! rayon, no spatial splits) over boxes, with our own conservative node
//! test. The per-model bottom levels (boxes of triangles) and the per-light
//! top level (boxes of placed instances and terrain blocks) are both box
//! trees; what a leaf holds is the caller's business.
//!
//! obvhs's own ray/node test is not conservative enough to be an exact
//! oracle-equivalent culler: it starts every ray at t = 1e-4, replaces the
//! inverse of direction components below f32::EPSILON by ±1/EPSILON (wrong
//! slab distances for nearly axis-parallel rays) and makes zero-width slabs of
//! flat geometry depend on exact rounding. Ours pads every child box at run
//! time by `m`, a few hundred ulps of the magnitude of the boxes and the ray
//! origin, which covers the quantization rounding of the build and the
//! rounding of the slab arithmetic, and treats NaN slabs as unbounded. Boxes
//! only cull; the leaf tests decide hits, so the hits of a ray do not depend
//! on the tree's shape.

use super::beam::Beam;
use super::{TraceRay, PAD_EPSILONS};
use glam::{UVec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::bvh2::reinsertion::ReinsertionOptimizer;
use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
use obvhs::cwbvh::node::{extract_byte64, CwBvhNode};
use obvhs::cwbvh::CwBvh;
use obvhs::ploc::PlocBuilder;
use obvhs::BvhBuildParams;

/// Direction components smaller than this are raised to it (keeping the
/// sign) so the slab arithmetic stays finite; the position error it causes,
/// 1e-18·t, is far below the padding for any t within the scene.
const MIN_DIRECTION: f32 = 1e-18;

/// A BVH over boxes. Leaves are numbered in tree order (`slot`), so callers
/// can lay their leaf data out in that order and read it sequentially;
/// [`BoxTree::input_index`] maps a slot back to the build input.
#[derive(Clone, Debug, Default)]
pub(crate) struct BoxTree {
    pub(crate) cwbvh: CwBvh,
    /// Slot → index into the build input.
    order: Vec<u32>,
    /// Largest absolute coordinate of any box.
    pub(crate) magnitude: f32,
}

impl BoxTree {
    /// Builds in parallel (rayon) over finite boxes (the caller leaves out
    /// the others); leaves of at most `max_per_leaf` boxes.
    pub(crate) fn build(aabbs: &[Aabb], max_per_leaf: u32) -> BoxTree {
        if aabbs.is_empty() {
            return BoxTree::default();
        }
        let magnitude = aabbs.iter().fold(0.0f32, |m, b| {
            m.max(b.min.abs().max_element())
                .max(b.max.abs().max_element())
        });
        // What obvhs's build_cwbvh does, minus its debug-build validation,
        // whose absolute 1e-5 tolerances fail on coordinates of ~1e4.
        let params = BvhBuildParams::medium_build();
        let mut bvh2 = PlocBuilder::with_capacity(aabbs.len()).build(
            params.ploc_search_distance,
            aabbs,
            (0..aabbs.len() as u32).collect(),
            params.sort_precision,
            params.search_depth_threshold,
        );
        ReinsertionOptimizer::default().run(&mut bvh2, params.reinsertion_batch_ratio, None);
        let cwbvh = bvh2_to_cwbvh(&bvh2, max_per_leaf.clamp(1, 3), true, false);
        let order = cwbvh.primitive_indices.clone();
        BoxTree {
            cwbvh,
            order,
            magnitude,
        }
    }

    /// Leaves in tree order: slot → build-input index.
    pub(crate) fn order(&self) -> &[u32] {
        &self.order
    }

    /// Heap bytes held (nodes and the slot table).
    pub(crate) fn heap_bytes(&self) -> usize {
        self.cwbvh.nodes.len() * std::mem::size_of::<CwBvhNode>()
            + (self.cwbvh.primitive_indices.len() + self.order.len()) * 4
    }

    /// Calls `leaf(slot, t_max, node_test)` for every leaf box the ray segment
    /// `[ray.t_min, t_max]` touches (padded); `leaf` returns the new t_max
    /// (a larger or NaN value is ignored), and traversal stops once it falls
    /// below t_min. `node_test` is the padded box test of this ray, which a
    /// leaf may reuse for boxes inside its own (its padding covers any
    /// box within the tree's magnitude).
    #[inline]
    pub(crate) fn visit(&self, ray: &TraceRay, mut leaf: impl FnMut(usize, f32, &BoxRay) -> f32) {
        if self.cwbvh.nodes.is_empty() || ray.t_min > ray.t_max || ray.t_min.is_nan() {
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
                    let slot = state.primitive_id as usize;
                    if slot >= self.order.len() {
                        continue;
                    }
                    let next = leaf(slot, t_max, &boxes);
                    if next < t_max {
                        t_max = next;
                        if t_max < t_min {
                            break 'traversal;
                        }
                        node_t_max = boxes.node_t_max(t_max);
                    }
                }
            );
        }
    }

    /// Calls `leaf(slot, beam)` for every leaf box `beam` may touch, in the
    /// order of `direction` (nearer children first); `leaf` may narrow the
    /// beam (rays settled) and returns false to stop.
    pub(crate) fn visit_beam(
        &self,
        beam: &mut Beam,
        direction: Vec3,
        mut leaf: impl FnMut(usize, &mut Beam) -> bool,
    ) {
        if self.cwbvh.nodes.is_empty() {
            return;
        }
        let mut state = self.cwbvh.new_traversal(Vec3A::from(direction));
        let mut node: &CwBvhNode;
        'traversal: {
            obvhs::traverse!(
                self.cwbvh,
                node,
                state,
                beam.hitmask(node, state.oct_inv4),
                {
                    let slot = state.primitive_id as usize;
                    if slot >= self.order.len() {
                        continue;
                    }
                    if !leaf(slot, beam) {
                        break 'traversal;
                    }
                }
            );
        }
    }

    /// obvhs's own closest-hit traversal and node test, for benchmarks only
    /// (see the module doc for why it can miss hits).
    pub(crate) fn visit_obvhs(
        &self,
        ray: &TraceRay,
        leaf: impl FnMut(&obvhs::ray::Ray, usize) -> f32,
    ) -> Option<f32> {
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
        let found = self.cwbvh.ray_traverse(r, &mut hit, leaf);
        found.then_some(hit.t)
    }
}

/// Where a ray segment lies in a padded box ([`BoxRay::span`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Span {
    Miss,
    /// Every point of the segment inside the box has t in this range.
    Within(f32, f32),
    /// A slab is NaN: the box bounds nothing.
    Unbounded,
}

/// The ray as the node test sees it: two origins shifted by ∓m along each
/// axis, so that near planes are moved towards the ray and far planes away,
/// i.e. every box is grown by m on every side.
pub(crate) struct BoxRay {
    inv: Vec3A,
    negative: [bool; 3],
    origin_near: Vec3A,
    origin_far: Vec3A,
    pad: f32,
}

impl BoxRay {
    pub(crate) fn new(ray: &TraceRay, magnitude: f32) -> BoxRay {
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

    /// Whether the ray segment `[t_lo, t_hi]` touches the box grown by the
    /// padding; NaN slabs count as unbounded (the same rule as the node
    /// test, for boxes that are not tree nodes: height-field tiles).
    #[inline(always)]
    pub(crate) fn touches(&self, min: Vec3, max: Vec3, t_lo: f32, t_hi: f32) -> bool {
        self.span(min, max, t_lo, t_hi) != Span::Miss
    }

    /// The part of the segment `[t_lo, t_hi]` inside the box grown by the
    /// padding, so a hit on anything inside the box has its t within it.
    /// A NaN slab bounds nothing (the other axes still do); a NaN end of
    /// the segment leaves it unbounded.
    #[inline(always)]
    pub(crate) fn span(&self, min: Vec3, max: Vec3, t_lo: f32, t_hi: f32) -> Span {
        let (mut t_near, mut t_far) = (t_lo, t_hi);
        for i in 0..3 {
            let (n, f) = if self.negative[i] {
                (max[i], min[i])
            } else {
                (min[i], max[i])
            };
            let a = (n - self.origin_near[i]) * self.inv[i];
            let b = (f - self.origin_far[i]) * self.inv[i];
            // Comparisons with NaN are false: a NaN slab bounds nothing.
            if a > t_near {
                t_near = a;
            }
            if b < t_far {
                t_far = b;
            }
        }
        if t_near <= t_far {
            Span::Within(t_near, t_far)
        } else if t_near.is_nan() || t_far.is_nan() {
            Span::Unbounded
        } else {
            Span::Miss
        }
    }

    /// The padding every box is grown by (metres of the frame).
    pub(crate) fn pad(&self) -> f32 {
        self.pad
    }

    /// The t bound used for culling: t_max plus slack, so that a hit whose
    /// computed t lies just within t_max while the exact point lies just
    /// beyond it is still visited.
    pub(crate) fn node_t_max(&self, t_max: f32) -> f32 {
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
    pub(crate) fn hitmask_sse(&self, node: &CwBvhNode, oct_inv4: u32, t_lo: f32, t_hi: f32) -> u32 {
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
    pub(crate) fn hitmask_scalar(
        &self,
        node: &CwBvhNode,
        oct_inv4: u32,
        t_lo: f32,
        t_hi: f32,
    ) -> u32 {
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
