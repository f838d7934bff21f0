//! The correctness oracle for the BVH: every ray against every triangle with
//! the same triangle test and the same callback contract, so the two can be
//! compared hit for hit (docs/contract.md §7).

use super::triangle::{report_hit, PreparedRay};
use super::{Hit, TraceRay, TraceTriangle};

/// Calls `on_hit` for every triangle the ray crosses with
/// `t_min <= t <= current t_max`, in input order; `on_hit` returns the new
/// t_max (a larger or NaN value is ignored). Unusable (NaN, Inf, huge) triangles are skipped,
/// as [`super::Bvh::build`] skips them.
pub fn brute_force_hits(
    triangles: &[TraceTriangle],
    ray: &TraceRay,
    mut on_hit: impl FnMut(Hit) -> f32,
) {
    let prepared = PreparedRay::new(ray);
    if !prepared.is_valid() {
        return;
    }
    let mut t_max = ray.t_max;
    for (index, tri) in triangles.iter().enumerate().take(super::bvh::MAX_TRIANGLES) {
        if !tri.is_usable() {
            continue;
        }
        t_max = report_hit(&prepared, tri, index as u32, t_max, &mut on_hit);
    }
}

/// Every triangle of a bottom level against a (model-space) ray, skipping
/// its tree: the oracle's half of an instanced trace. Returns the t_max it
/// ends with.
pub(crate) fn bvh_triangles_hits(
    bvh: &super::Bvh,
    ray: &TraceRay,
    t_max: f32,
    on_hit: &mut impl FnMut(Hit) -> f32,
) -> f32 {
    let prepared = PreparedRay::new(ray);
    let mut t_max = t_max;
    if !prepared.is_valid() {
        return t_max;
    }
    for (index, tri) in bvh.triangles() {
        t_max = report_hit(&prepared, tri, index, t_max, on_hit);
    }
    t_max
}
