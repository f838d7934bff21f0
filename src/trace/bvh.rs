//! A triangle BVH: a [`BoxTree`] over triangles' boxes with the triangles
//! laid out in tree order. The bake builds one per distinct model, in model
//! space (a bottom level, shared by every light and every placement).

use super::boxtree::BoxTree;
use super::triangle::{report_hit, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle};
use glam::{Vec3, Vec3A};
use obvhs::aabb::Aabb;

/// Hit::triangle is a u32; triangles past this index are ignored.
pub(crate) const MAX_TRIANGLES: usize = u32::MAX as usize;

#[derive(Clone, Copy, Debug)]
struct BvhTriangle {
    tri: TraceTriangle,
    /// Index into the build input.
    index: u32,
}

/// A BVH over triangles. Triangle data is laid out in BVH order so
/// traversal reads it sequentially.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    pub(crate) tree: BoxTree,
    triangles: Vec<BvhTriangle>,
    /// Box of the built triangles, `None` when there are none.
    bounds: Option<(Vec3, Vec3)>,
}

impl Bvh {
    /// Builds in parallel (rayon); no spatial splits (each triangle in exactly
    /// one leaf). NaN, Inf and huge triangles ([`TraceTriangle::is_usable`]) are left out.
    pub fn build(triangles: &[TraceTriangle]) -> Bvh {
        let mut aabbs = Vec::with_capacity(triangles.len());
        let mut kept = Vec::with_capacity(triangles.len());
        let mut bounds: Option<(Vec3, Vec3)> = None;
        for (index, tri) in triangles.iter().enumerate().take(MAX_TRIANGLES) {
            if !tri.is_usable() {
                continue;
            }
            let [a, b, c] = tri.vertices;
            let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
            bounds = Some(bounds.map_or((lo, hi), |(min, max)| (min.min(lo), max.max(hi))));
            aabbs.push(Aabb::new(Vec3A::from(lo), Vec3A::from(hi)));
            kept.push(BvhTriangle {
                tri: *tri,
                index: index as u32,
            });
        }
        let tree = BoxTree::build(&aabbs, 3);
        let triangles = tree.order().iter().map(|&p| kept[p as usize]).collect();
        Bvh {
            tree,
            triangles,
            bounds,
        }
    }

    /// Triangles in the BVH (unusable ones left out).
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Model-space box of the built triangles.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.bounds
    }

    /// Heap bytes held: nodes, slot table and triangles.
    pub fn heap_bytes(&self) -> usize {
        self.tree.heap_bytes() + self.triangles.len() * std::mem::size_of::<BvhTriangle>()
    }

    /// The triangle of leaf slot `slot` and its index in the build input.
    #[inline]
    pub(crate) fn slot(&self, slot: usize) -> (&TraceTriangle, u32) {
        let entry = &self.triangles[slot];
        (&entry.tri, entry.index)
    }

    /// The triangles as built (unusable ones left out), in tree order.
    pub(crate) fn triangles(&self) -> impl Iterator<Item = (u32, &TraceTriangle)> {
        self.triangles.iter().map(|e| (e.index, &e.tri))
    }

    /// Calls `on_hit` for every triangle the ray crosses with
    /// `t_min <= t <= current t_max`; `on_hit` returns the new t_max (a larger
    /// or NaN value is ignored) so callers can stop looking beyond what can
    /// still change their answer. Hits arrive in traversal order (not sorted).
    pub fn for_each_hit(&self, ray: &TraceRay, mut on_hit: impl FnMut(Hit) -> f32) {
        self.hits_within(ray, ray.t_max, &mut on_hit);
    }

    /// [`for_each_hit`](Self::for_each_hit) from a caller's running t_max
    /// (the top level's); returns the t_max it ends with.
    #[inline]
    pub(crate) fn hits_within(
        &self,
        ray: &TraceRay,
        t_max: f32,
        on_hit: &mut impl FnMut(Hit) -> f32,
    ) -> f32 {
        let prepared = PreparedRay::new(ray);
        // A NaN range was rejected by PreparedRay.
        if !prepared.is_valid() {
            return t_max;
        }
        self.visit_triangles(ray, t_max, |tri, index, t_max| {
            report_hit(&prepared, tri, index, t_max, on_hit)
        })
    }

    /// Calls `visit(triangle, index, t_max)` for every triangle whose leaf
    /// box (padded) the segment `[ray.t_min, t_max]` touches, with the
    /// running t_max; `visit` returns the new one (a larger or NaN value is
    /// ignored), and the t_max it ends with is returned. Whether a triangle
    /// is hit is `visit`'s business: a caller may test it in another frame,
    /// where the same point lies within the padding.
    #[inline]
    pub(crate) fn visit_triangles(
        &self,
        ray: &TraceRay,
        t_max: f32,
        mut visit: impl FnMut(&TraceTriangle, u32, f32) -> f32,
    ) -> f32 {
        let mut t_max = t_max;
        let segment = TraceRay { t_max, ..*ray };
        self.tree.visit(&segment, |slot, _, _| {
            let entry = &self.triangles[slot];
            let next = visit(&entry.tri, entry.index, t_max);
            if next < t_max {
                t_max = next;
            }
            t_max
        });
        t_max
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
    /// and its node test can miss hits (see `boxtree`).
    pub fn closest_hit_obvhs(&self, ray: &TraceRay) -> Option<f32> {
        self.tree.visit_obvhs(ray, |r, id| {
            self.triangles.get(id).map_or(f32::INFINITY, |e| {
                let [v0, v1, v2] = e.tri.vertices.map(Vec3A::from);
                obvhs::triangle::Triangle { v0, v1, v2 }.intersect(r)
            })
        })
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
            let boxes = crate::trace::boxtree::BoxRay::new(&ray, bvh.tree.magnitude);
            let oct = bvh
                .tree
                .cwbvh
                .new_traversal(Vec3A::from(ray.direction))
                .oct_inv4;
            for node in &bvh.tree.cwbvh.nodes {
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
