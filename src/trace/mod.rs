//! Ray casting for the bake: one BVH per light over that light's triangles, and
//! a multi-hit traversal that reports every surface crossing of a ray, because
//! the culling rule (SPEC §4) needs all hits near the first one, not just the
//! closest.
//!
//! Hits are decided by a watertight ray/triangle test with a consistent tie
//! rule ([`intersect`]), so a ray exactly through an edge or vertex shared by
//! several triangles of one surface crosses it exactly once. The BVH (obvhs's
//! compressed wide BVH8) only culls: its node test is made conservative, so the
//! set of hits of a ray is the brute-force oracle's ([`brute_force_hits`]),
//! whatever the BVH's shape or the thread count that built it. obvhs types do
//! not leave this module.

mod brute;
mod bvh;
mod triangle;

#[cfg(test)]
mod tests;

pub use brute::brute_force_hits;
pub use bvh::Bvh;
pub use triangle::{intersect, PreparedRay};

use glam::Vec3;

/// One triangle in light-relative f32 coordinates (world minus a reference
/// point, computed in f64 by the caller), wound so that its geometric normal
/// (v1−v0)×(v2−v0) points to its front face (the caller has already swapped two
/// vertices of mirrored instances). `caster` is the caller's id for what the
/// triangle belongs to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceTriangle {
    pub vertices: [Vec3; 3],
    pub caster: u32,
}

/// Coordinates beyond this (in the light-relative frame, where a real scene
/// spans at most ~1e5 m) are treated like NaN: far enough from any real value,
/// and near enough to f32::MAX that box arithmetic would overflow.
pub const MAX_COORDINATE: f32 = 1e15;

impl TraceTriangle {
    /// False for NaN, infinite or absurdly large (> [`MAX_COORDINATE`])
    /// coordinates: such a triangle is never built into a BVH and never hit.
    pub fn is_usable(&self) -> bool {
        self.vertices
            .iter()
            .all(|v| v.is_finite() && v.abs().max_element() <= MAX_COORDINATE)
    }
}

/// A ray segment: the points `origin + t·direction` for `t_min <= t <= t_max`.
/// `direction` should be unit length so that t is a distance; the tests do not
/// require it, but any tolerance the caller applies to t assumes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceRay {
    pub origin: Vec3,
    pub direction: Vec3,
    pub t_min: f32,
    pub t_max: f32,
}

/// One ray/triangle crossing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    /// Index of the triangle in the slice the BVH was built from.
    pub triangle: u32,
    pub caster: u32,
    /// Geometric normal · ray direction > 0.
    pub back_facing: bool,
}
