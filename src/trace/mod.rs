//! Ray casting for the bake: a two-level structure and a multi-hit
//! traversal that reports every surface crossing of a ray, because the
//! culling rule (docs/contract.md §4) needs all hits near the first one, not just the
//! closest.
//!
//! - bottom levels ([`BottomLevels`], `blas.rs`): one BVH per distinct
//!   model in model space (`bvh.rs`) and one min/max pyramid per terrain
//!   block (`heightfield.rs`), built once per bake;
//! - top level ([`TopLevel`], `tlas.rs`): per light, a BVH over the placed
//!   parts and blocks in its reach; a ray enters an instance by its inverse
//!   transform (`instance.rs`) with t kept in world metres;
//! - [`Tracer`]: the top level through its trees, or the brute-force oracle
//!   over the same entries with the same arithmetic (`brute.rs`);
//! - packets (`packet.rs`): a tile of coherent rays walks the trees once
//!   under a padded beam (`beam.rs`), and the triangles it reaches are tested
//!   eight rays at a time, then by the single-ray test for each ray kept, so
//!   each ray's hits are the single-ray traversal's.
//!
//! Hits are decided by a watertight ray/triangle test with a consistent tie
//! rule ([`intersect`]), so a ray exactly through an edge or vertex shared by
//! several triangles of one surface crosses it exactly once. The BVH (obvhs's
//! compressed wide BVH8) only culls: its node test is made conservative, so the
//! set of hits of a ray is the brute-force oracle's ([`brute_force_hits`]),
//! whatever the BVH's shape or the thread count that built it. obvhs types do
//! not leave this module.

mod beam;
mod blas;
mod boxtree;
mod brute;
mod bvh;
mod heightfield;
mod instance;
mod packet;
mod tlas;
mod triangle;

#[cfg(test)]
mod tests;

pub use blas::BottomLevels;
pub use brute::brute_force_hits;
pub use bvh::Bvh;
pub use heightfield::{DecodeHeights, DeferredHeights, HeightField, HeightGrid, Heights};
pub use instance::ToModel;
pub use packet::{PacketScratch, PACKET_RAYS};
pub use tlas::{transform_box, Extent, PartsFrom, PlacedBlock, PlacedPart, PlacedParts, TopLevel};
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

/// Box padding in units of f32::EPSILON × magnitude, shared by the box
/// tree's single-ray node test (`BoxRay`) and the packet's beam, so a beam
/// culls no box a ray of it would enter. The build's rounding (child − node
/// origin, quantization exponent) and the slab arithmetic each err by a few
/// ulps of the magnitude; this leaves a wide margin.
pub(crate) const PAD_EPSILONS: f32 = 256.0;

impl TraceTriangle {
    /// False for NaN, infinite or absurdly large (> [`MAX_COORDINATE`])
    /// coordinates: such a triangle is never built into a BVH and never hit.
    pub fn is_usable(&self) -> bool {
        self.vertices
            .iter()
            .all(|v| v.is_finite() && v.abs().max_element() <= MAX_COORDINATE)
    }

    /// Zero area in f32 (the triangle test never reports such a triangle)
    /// or a normal that overflows.
    pub fn has_zero_area(&self) -> bool {
        let [a, b, c] = self.vertices;
        let n = (b - a).cross(c - a);
        n == Vec3::ZERO || !n.is_finite()
    }
}

/// The hits a caller drops for their facing alone (face culling), told to
/// a packet traversal so that a packet of parallel rays can skip a
/// triangle every one of whose hits would be dropped: one sign of facing
/// holds for all parallel rays, except for a triangle within rounding of
/// edge-on, which is tested as usual. And the hits of a stack of
/// coincident placements a caller drops as repeats ([`DropsRepeat`]).
#[derive(Clone, Copy, Default)]
pub struct FaceCull<'a> {
    /// `Some(true)`: back-facing hits are dropped, `Some(false)`: front
    /// facing ones; `None`: none.
    pub drops_back: Option<bool>,
    /// Casters (bits of their ids, 64 a word) whose hits count on either
    /// face (double-sided groups).
    pub either_face: &'a [u64],
    pub repeats: Option<&'a DropsRepeat<'a>>,
}

/// `drops(caster, [a, b])`: whether a caller drops a hit of `caster` that
/// lies where hits of the casters `a` and `b` it was given before lie
/// (the same group of three placements of one model at one transform:
/// the same triangle, distance and facing). A packet traversal then
/// reports such hits of a stack's third and later placements not at all,
/// so a stack of coincident copies costs a ray about what two do.
pub type DropsRepeat<'a> = dyn Fn(u32, [u32; 2]) -> bool + Sync + 'a;

impl FaceCull<'_> {
    /// Whether a hit of `caster` facing as `back_facing` is dropped.
    #[inline]
    pub fn drops(&self, caster: u32, back_facing: bool) -> bool {
        let either = self
            .either_face
            .get(caster as usize / 64)
            .is_some_and(|w| w & (1 << (caster % 64)) != 0);
        self.drops_back == Some(back_facing) && !either
    }
}

/// How a [`Tracer`] finds hits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TraceMode {
    /// Through the top level and the bottom levels' trees; packets of rays
    /// ([`Tracer::for_each_packet_hit`]) walk them once per packet.
    Trees,
    /// The same trees, but packets are traced ray by ray (the reference
    /// the packet traversal is measured and tested against).
    RayByRay,
    /// Every triangle and terrain cell of every entry (the oracle; slow).
    BruteForce,
}

/// One light's way of finding hits: its top level over the bake's bottom
/// levels.
#[derive(Clone, Copy)]
pub struct Tracer<'a> {
    pub bottom: &'a BottomLevels<'a>,
    pub top: &'a TopLevel,
    pub mode: TraceMode,
}

impl Tracer<'_> {
    /// Calls `on_hit` for every surface crossing with `t_min <= t <=
    /// current t_max`, caster ids already global; `on_hit` returns the new
    /// t_max (a larger or NaN value is ignored). Hits arrive unsorted; the
    /// set does not depend on the mode.
    #[inline]
    pub fn for_each_hit(&self, ray: &TraceRay, on_hit: impl FnMut(Hit) -> f32) {
        self.top
            .for_each_hit(self.bottom, ray, self.mode == TraceMode::BruteForce, on_hit);
    }

    /// [`Self::for_each_hit`] for a caller that drops the repeats `repeats`
    /// says ([`DropsRepeat`]): through the trees those are not reported
    /// (every other hit is); the oracle reports them all.
    pub fn for_each_hit_dropping(
        &self,
        ray: &TraceRay,
        repeats: Option<&DropsRepeat>,
        on_hit: impl FnMut(Hit) -> f32,
    ) {
        match self.mode {
            TraceMode::BruteForce => self.for_each_hit(ray, on_hit),
            TraceMode::Trees | TraceMode::RayByRay => {
                self.top
                    .for_each_hit_dropping(self.bottom, ray, repeats, on_hit)
            }
        }
    }

    /// [`Self::for_each_hit`] for each ray of `rays`, which should be
    /// coherent (a tile of one light's rays) to gain from it: `on_hit(lane,
    /// hit)` gets ray `lane`'s hits (the same set as its own
    /// [`Self::for_each_hit`], in another order) and returns its new t_max.
    /// `scratch` is reused across calls.
    pub fn for_each_packet_hit(
        &self,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        on_hit: impl FnMut(usize, Hit) -> f32,
    ) {
        let cull = FaceCull::default();
        self.for_each_packet_hit_culled(rays, scratch, &cull, PacketRays::All, on_hit);
    }

    /// Whether some ray of a packet of grid texels whose texel rectangle
    /// has the corner rays `corners` may meet a caster `unsettled`
    /// accepts ([`TopLevel::gate_packet`]); a packet it lets through is
    /// traced next with [`PacketRays::Gated`] and the same `scratch`.
    /// Without the trees every packet goes through.
    pub fn gate_packet(
        &self,
        corners: &[TraceRay; 4],
        scratch: &mut PacketScratch,
        unsettled: &dyn Fn(u32) -> bool,
    ) -> bool {
        self.mode != TraceMode::Trees
            || self
                .top
                .gate_packet(self.bottom, corners, scratch, unsettled)
    }

    /// [`Self::rays_reaching`] for the rays of a packet
    /// [`Self::gate_packet`] let through, against what it found (no second
    /// walk); without the trees, every ray.
    pub fn rays_reaching_gated(
        &self,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        unsettled: &dyn Fn(u32) -> bool,
        keep: &mut Vec<bool>,
    ) -> usize {
        if self.mode != TraceMode::Trees {
            return keep_every_ray(keep, rays.len());
        }
        self.top
            .rays_reaching_gated(self.bottom, rays, scratch, unsettled, keep)
    }

    /// Marks in `keep` the rays of `rays` (a packet, as
    /// [`Self::for_each_packet_hit_culled`] takes them) that may meet a
    /// caster `unsettled` accepts, and returns how many (see
    /// [`TopLevel::rays_reaching`]); without the trees (brute force, ray
    /// by ray) or for more than one packet's rays, every ray.
    pub fn rays_reaching(
        &self,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        unsettled: &dyn Fn(u32) -> bool,
        keep: &mut Vec<bool>,
    ) -> usize {
        if self.mode != TraceMode::Trees || rays.len() > PACKET_RAYS {
            return keep_every_ray(keep, rays.len());
        }
        let open = scratch.open_entries();
        self.top
            .rays_reaching(self.bottom, rays, open, unsettled, keep)
    }

    /// [`Self::for_each_packet_hit`] for a caller that drops the hits
    /// `cull` says: those may not be reported (every other hit is), and
    /// wants the hits of the rays `which` says (the others report none).
    pub fn for_each_packet_hit_culled(
        &self,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        cull: &FaceCull,
        which: PacketRays,
        mut on_hit: impl FnMut(usize, Hit) -> f32,
    ) {
        if self.mode != TraceMode::Trees {
            for (lane, ray) in rays.iter().enumerate() {
                self.for_each_hit_dropping(ray, cull.repeats, |hit| on_hit(lane, hit));
            }
            return;
        }
        let lone_parallel = match rays {
            [first, rest @ ..] if rays.len() <= LONE_PARALLEL_RAYS => {
                rest.iter().all(|r| r.direction == first.direction)
            }
            _ => false,
        };
        if (rays.len() <= LONE_RAYS || lone_parallel) && matches!(which, PacketRays::All) {
            for (lane, ray) in rays.iter().enumerate() {
                self.for_each_hit_dropping(ray, cull.repeats, |hit| on_hit(lane, hit));
            }
            return;
        }
        for (k, packet) in rays.chunks(PACKET_RAYS).enumerate() {
            let first = k * PACKET_RAYS;
            let mut relay = |lane, hit| on_hit(first + lane, hit);
            self.top
                .for_each_packet_hit(self.bottom, packet, scratch, cull, which, &mut relay);
        }
    }
}

/// Packets of at most this many rays go ray by ray: a packet's frame and
/// beam cost more than they save over so few rays (refinement's first
/// surface points).
const LONE_RAYS: usize = 2;

/// Packets of at most this many parallel rays (one direction: a
/// directional light's) go ray by ray too: their beam is as wide as their
/// origins lie apart all along its length, so over terrain its walk tests
/// every cell under it (refinement's corner probes of terrain blocks). A
/// spot or point light's few rays share a thin cone, which still pays.
const LONE_PARALLEL_RAYS: usize = 4;

/// `keep` marking all of `rays` rays, and their count: the answer of the
/// ray filters where they cannot tell (no trees, too many rays).
fn keep_every_ray(keep: &mut Vec<bool>, rays: usize) -> usize {
    keep.clear();
    keep.resize(rays, true);
    rays
}

/// Which rays of a packet a caller wants the hits of.
#[derive(Clone, Copy)]
pub enum PacketRays<'u> {
    /// Every ray.
    All,
    /// The rays that may meet a caster `unsettled` accepts (see
    /// [`Tracer::rays_reaching`]); the packet traversal may leave out the
    /// others, which then report no hit.
    MeetingUnsettled(&'u dyn Fn(u32) -> bool),
    /// The rays that may meet a caster the closure accepts (the one the
    /// gate was asked with) in the entries the latest
    /// [`Tracer::gate_packet`] on the same scratch found (every ray when
    /// it found many, or was not asked).
    Gated(&'u dyn Fn(u32) -> bool),
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
    /// Index of the triangle in the slice the BVH was built from (for a
    /// placed model: in the model; for terrain: 2 × cell + 0 or 1).
    pub triangle: u32,
    pub caster: u32,
    /// Geometric normal · ray direction > 0.
    pub back_facing: bool,
}
