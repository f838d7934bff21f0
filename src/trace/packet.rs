//! Packet traversal: a tile of coherent rays (a directional light's
//! parallel rays, a spot or point light's rays from one origin) walks the top
//! level, each bottom level and each height field once, culled by the
//! packet's [`Beam`]; the triangles and terrain cells that survive are tested
//! for all of the packet's live rays eight lanes at a time ([`Lanes`]).
//!
//! Exact: the beam only culls (conservatively, padded like the single-ray
//! node test) and each ray's hits come from the single-ray triangle test
//! with that ray's own running t_max, so every ray gets the hits the
//! single-ray traversal gives it; only their order differs. Rays whose t_max
//! falls below their t_min are settled and leave the packet. A packet the
//! beam cannot bound (directions spread too wide, a ray not finite) is
//! traced ray by ray.
//!
//! Before tracing, a caller may ask which of a packet's rays can meet a
//! caster it has not settled yet ([`TopLevel::rays_reaching`]): the beam
//! walks the top level alone, and each ray gets, against the few entries
//! found, the box test the single-ray traversal gives it there.

use super::beam::Beam;
use super::blas::{BottomLevels, ModelGroup};
use super::boxtree::BoxRay;
use super::heightfield::Step;
use super::instance::row_sum_norm;
use super::tlas::{block_box, repeated_groups, Entry, Placements, TopLevel};
use super::triangle::{report_hit, Lanes, PreparedRay, ALL_GROUPS, LANES};
use super::{Bvh, FaceCull, Hit, PacketRays, ToModel, TraceRay, TraceTriangle};
use glam::Vec3;

/// Rays of one packet at most (lane numbers are u8).
pub const PACKET_RAYS: usize = 256;

/// Most entries with an unsettled caster [`TopLevel::rays_reaching`]
/// tests each ray against (each test maps the ray into a model's space);
/// a packet reaching more traces every ray.
pub const MOST_OPEN_ENTRIES: usize = 8;

/// The live rays of a packet in one frame (light-relative, or one
/// instance's model space), grouped for the lane test. Scratch reused
/// from entry to entry, so a packet allocates only while it grows.
#[derive(Default)]
struct Frame {
    /// Per live ray: the ray in this frame, its preparation, its lane.
    rays: Vec<TraceRay>,
    prepared: Vec<PreparedRay>,
    lanes: Vec<u8>,
    /// Groups of up to [`LANES`] rays sharing a permutation, and which
    /// live ray each group lane is.
    groups: Vec<Lanes>,
    members: Vec<[u8; LANES]>,
    masks: Vec<u32>,
    order: Vec<u8>,
    /// The shear every live ray shares (parallel rays: a directional
    /// light's packet, in any frame), when they share one, and per group
    /// the box of its rays' points in the shear plane ([`ShearPlane`]).
    plane: Option<ShearPlane>,
    group_boxes: Vec<[f32; 4]>,
    /// Largest absolute coordinate of the geometry the frame's rays meet
    /// (its tree's), and of a live ray's origin.
    magnitude: f32,
    origin_max: f32,
    /// [`ShearPlane::pad`] for both.
    plane_pad: f32,
}

/// The plane perpendicular to rays that share a direction, in the
/// coordinates of the watertight test's shear: a point p maps to
/// `(p[kx] − sx·p[kz], p[ky] − sy·p[kz])`. The test of ray o against a
/// triangle works on `v − o` sheared, which is the difference of the two
/// points' images up to rounding, so a ray can hit a triangle only if its
/// origin's image lies in the box of the vertices' images grown by that
/// rounding ([`ShearPlane::pad`]): groups of rays whose box misses it are
/// not tested at all (a triangle of a packet of 8 × 8 texels meets two or
/// three of its eight rows).
#[derive(Clone, Copy, Debug)]
struct ShearPlane {
    axes: [usize; 3],
    sx: f32,
    sy: f32,
}

impl ShearPlane {
    #[inline(always)]
    fn point(&self, p: Vec3) -> (f32, f32) {
        let a = p.to_array();
        let [kx, ky, kz] = self.axes;
        (a[kx] - self.sx * a[kz], a[ky] - self.sy * a[kz])
    }

    /// A bound on the difference between the test's sheared `v − o` and
    /// `image(v) − point(o)` for coordinates up to `magnitude` (the f64
    /// image of a vertex is nearer the truth than `point`'s): each side
    /// rounds a few times (a subtraction, a product, a subtraction) at most
    /// one ulp of `(1 + |sx| + |sy|)·magnitude` each; thirty-two of those
    /// (also covering a vertex a rounding beyond its tree's magnitude).
    fn pad(&self, magnitude: f32) -> f32 {
        32.0 * f32::EPSILON * (1.0 + self.sx.abs() + self.sy.abs()) * magnitude
    }

    /// The box `[x0, y0, x1, y1]` holding the image of every light-frame
    /// ray (origin within `origin_max` of 0, t up to `reach`) that the
    /// model-space test can find a hit of inside the instance's model box
    /// `bounds`; `None` when it cannot be bounded (not finite). The model
    /// box's corners are mapped back in f64 (`world`: the inverse of the
    /// instance's linear part); the padding bounds what the
    /// mapping into model space and the model-space test round, grown by
    /// the conditioning of the instance's transform, four times over.
    fn instance_image(
        &self,
        to_model: &ToModel,
        world: glam::DMat3,
        (min, max): (Vec3, Vec3),
        origin_max: f32,
        reach: f32,
    ) -> Option<[f32; 4]> {
        let (linear, offset) = to_model.parts();
        let (to_norm, back_norm) = (row_sum_norm(&linear), row_sum_norm(&world));
        let (sx, sy) = (f64::from(self.sx), f64::from(self.sy));
        let [kx, ky, kz] = self.axes;
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for corner in 0..8 {
            let pick =
                |bit: usize, i: usize| f64::from(if corner & bit == 0 { min[i] } else { max[i] });
            let c = glam::DVec3::new(pick(1, 0), pick(2, 1), pick(4, 2));
            let p = (world * (c - offset)).to_array();
            let (x, y) = (p[kx] - sx * p[kz], p[ky] - sy * p[kz]);
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
        let eps = f64::from(f32::EPSILON);
        let origin_model = to_norm * f64::from(origin_max) + offset.abs().max_element();
        let model_magnitude = origin_model.max(f64::from(min.abs().max(max.abs()).max_element()));
        let drift = back_norm
            * eps
            * (64.0 * model_magnitude + 2.0 * origin_model + f64::from(reach) * to_norm);
        let shear = 1.0 + sx.abs() + sy.abs();
        let pad = 4.0 * shear * (drift + 4.0 * eps * f64::from(origin_max));
        let image = [x0 - pad, y0 - pad, x1 + pad, y1 + pad];
        let outward = |v: f64, down: bool| {
            let f = v as f32;
            match down {
                true if f64::from(f) > v => f.next_down(),
                false if f64::from(f) < v => f.next_up(),
                _ => f,
            }
        };
        let image = [
            outward(image[0], true),
            outward(image[1], true),
            outward(image[2], false),
            outward(image[3], false),
        ];
        image.iter().all(|v| v.is_finite()).then_some(image)
    }

    /// Whether every ray of the plane that can hit `tri` meets it from
    /// behind (`Some(true)`) or from the front (`Some(false)`), as the
    /// watertight test judges each: the sign of the image's doubled area,
    /// which is minus the test's determinant for every ray, when it is
    /// beyond what rounding could change; `None` near edge-on. A ray that
    /// can hit lies within `pad` of the image, so its sheared vertices are
    /// within the image's extent (plus `pad`) of it, each off by `delta`
    /// (a few ulps of the coordinates, up to `magnitude`, sheared); the
    /// determinant sums three edge functions, each two products of such
    /// coordinates, rounded to f32.
    #[inline]
    fn facing(&self, image: &TriangleImage, magnitude: f32, pad: f32) -> Option<bool> {
        let [a, b, c] = image.points;
        let det = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
        let [x0, y0, x1, y1] = image.bounds;
        let eps = f64::from(f32::EPSILON);
        let extent = (x1 - x0) + (y1 - y0) + 2.0 * f64::from(pad);
        let shear = 1.0 + f64::from(self.sx).abs() + f64::from(self.sy).abs();
        let delta = 8.0 * eps * shear * 2.0 * f64::from(magnitude);
        let bound =
            4.0 * (6.0 * extent * delta + 3.0 * delta * delta + 3.0 * eps * extent * extent);
        if !det.is_finite() || !bound.is_finite() || det.abs() <= bound {
            return None;
        }
        // The test's determinant (the sum of its edge functions) is minus
        // this area: front facing when it is positive.
        Some(det > 0.0)
    }

    /// The groups (bits) whose box meets the triangle's `image` grown by
    /// `pad`; every group when the image is not finite.
    #[inline]
    fn groups_near(&self, image: &TriangleImage, boxes: &[[f32; 4]], pad: f32) -> u64 {
        let pad = f64::from(pad);
        let [x0, y0, x1, y1] = image.bounds;
        let (x0, y0, x1, y1) = (x0 - pad, y0 - pad, x1 + pad, y1 + pad);
        let finite = x0.is_finite() && x1.is_finite() && y0.is_finite() && y1.is_finite();
        if !finite || boxes.len() > 64 {
            return ALL_GROUPS;
        }
        let mut near = 0;
        for (g, b) in boxes.iter().enumerate() {
            let [bx0, by0, bx1, by1] = b.map(f64::from);
            if bx0 <= x1 && bx1 >= x0 && by0 <= y1 && by1 >= y0 {
                near |= 1 << g;
            }
        }
        near
    }

    /// The image of `tri` in the plane, in f64 (the products of f32 are
    /// exact there, so it is nearer the truth than [`Self::point`]'s, which
    /// the pads bound).
    #[inline]
    fn triangle_image(&self, tri: &TraceTriangle) -> TriangleImage {
        let [kx, ky, kz] = self.axes;
        let (sx, sy) = (f64::from(self.sx), f64::from(self.sy));
        let points = tri.vertices.map(|v| {
            let a = v.to_array().map(f64::from);
            (a[kx] - sx * a[kz], a[ky] - sy * a[kz])
        });
        let [a, b, c] = points;
        TriangleImage {
            points,
            bounds: [
                a.0.min(b.0).min(c.0),
                a.1.min(b.1).min(c.1),
                a.0.max(b.0).max(c.0),
                a.1.max(b.1).max(c.1),
            ],
        }
    }
}

/// A triangle's image in a [`ShearPlane`] and its box `[x0, y0, x1, y1]`:
/// made once per triangle, read by the facing and the groups tests.
struct TriangleImage {
    points: [(f64, f64); 3],
    bounds: [f64; 4],
}

impl Frame {
    /// Refills the frame with `rays` (lane, ray in this frame), keeping
    /// those the triangle test can hit with.
    /// `magnitude`: the largest absolute coordinate of the geometry the
    /// rays will be tested against in this frame.
    fn fill(&mut self, rays: impl Iterator<Item = (u8, TraceRay)>, magnitude: f32) {
        self.magnitude = magnitude;
        self.rays.clear();
        self.prepared.clear();
        self.lanes.clear();
        let mut last: Option<(Vec3, PreparedRay)> = None;
        let mut shared = true;
        for (lane, ray) in rays {
            let prepared = match last {
                Some((direction, like)) if same_bits(direction, ray.direction) => {
                    like.with_direction_of(&ray)
                }
                _ => {
                    shared &= last.is_none();
                    PreparedRay::new(&ray)
                }
            };
            last = Some((ray.direction, prepared));
            if prepared.is_valid() {
                self.rays.push(ray);
                self.prepared.push(prepared);
                self.lanes.push(lane);
            }
        }
        self.plane = match self.prepared.first() {
            Some(first) if shared => Some(ShearPlane {
                axes: Lanes::axes_of(first),
                sx: first.sx(),
                sy: first.sy(),
            }),
            _ => None,
        };
        self.group();
    }

    /// Drops the rays whose running t_max fell below their t_min; true if
    /// any did.
    fn retain_live(&mut self, t_max: &[f32]) -> bool {
        self.retain_where(|ray, lane| ray.t_min <= t_max[lane as usize])
    }

    /// Keeps the rays (this frame's copy, and their lane) `keep` accepts;
    /// true if it dropped any.
    fn retain_where(&mut self, keep: impl Fn(&TraceRay, u8) -> bool) -> bool {
        // Rays seldom go, and this runs after every entry that reported a
        // hit: read before moving anything.
        let Some(first_dropped) =
            (0..self.rays.len()).position(|i| !keep(&self.rays[i], self.lanes[i]))
        else {
            return false;
        };
        let mut kept = first_dropped;
        for i in first_dropped + 1..self.rays.len() {
            if keep(&self.rays[i], self.lanes[i]) {
                self.rays.swap(kept, i);
                self.prepared.swap(kept, i);
                self.lanes.swap(kept, i);
                kept += 1;
            }
        }
        self.rays.truncate(kept);
        self.prepared.truncate(kept);
        self.lanes.truncate(kept);
        self.group();
        true
    }

    fn group(&mut self) {
        self.groups.clear();
        self.group_boxes.clear();
        self.members.clear();
        self.origin_max = 0.0;
        let first = self.prepared.first().map(Lanes::axes_of);
        // Rays sharing a direction share a permutation; a spot or point
        // light's mostly do too.
        if self.plane.is_some()
            || self
                .prepared
                .iter()
                .all(|p| Some(Lanes::axes_of(p)) == first)
        {
            self.group_consecutive();
        } else {
            self.group_by_axes();
        }
        self.masks.resize(self.groups.len(), 0);
        if let Some(plane) = self.plane {
            self.plane_pad = plane.pad(self.magnitude.max(self.origin_max));
        }
    }

    /// Rays sharing one permutation: groups of consecutive rays (with, for
    /// parallel rays, the box of each group's origins' images), in one pass
    /// (this runs for every instance a packet enters).
    fn group_consecutive(&mut self) {
        for start in (0..self.rays.len()).step_by(LANES) {
            let end = (start + LANES).min(self.rays.len());
            self.groups
                .push(Lanes::new(self.prepared[start..end].iter()));
            let mut b = [
                f32::INFINITY,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::NEG_INFINITY,
            ];
            let mut slots = [0u8; LANES];
            for (slot, i) in slots.iter_mut().zip(start..end) {
                let origin = self.rays[i].origin;
                if let Some(plane) = self.plane {
                    let (x, y) = plane.point(origin);
                    b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
                }
                self.origin_max = self.origin_max.max(origin.abs().max_element());
                *slot = i as u8;
            }
            if self.plane.is_some() {
                self.group_boxes.push(b);
            }
            self.members.push(slots);
        }
    }

    /// Rays of several permutations (a spot or point light's tile across
    /// a diagonal): sorted by permutation, then grouped.
    fn group_by_axes(&mut self) {
        self.order.clear();
        self.order.extend((0..self.rays.len()).map(|i| i as u8));
        let prepared = &self.prepared;
        let key = |i: &u8| Lanes::axes_of(&prepared[*i as usize]);
        self.order.sort_by_key(key);
        let mut start = 0;
        while start < self.order.len() {
            let axes = key(&self.order[start]);
            let mut end = start;
            while end < self.order.len() && end - start < LANES && key(&self.order[end]) == axes {
                end += 1;
            }
            let members = &self.order[start..end];
            self.groups
                .push(Lanes::new(members.iter().map(|&i| &prepared[i as usize])));
            let mut slots = [0u8; LANES];
            slots[..members.len()].copy_from_slice(members);
            self.members.push(slots);
            start = end;
        }
        self.origin_max = self
            .rays
            .iter()
            .fold(0.0, |m, r| m.max(r.origin.abs().max_element()));
    }

    fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// The beam of the live rays with their running t_max.
    fn beam(&self, t_max: &[f32], magnitude: f32) -> Option<Beam> {
        let rays = self.rays.iter().zip(&self.lanes).map(|(r, &l)| TraceRay {
            t_max: t_max[l as usize],
            ..*r
        });
        Beam::new(rays, magnitude)
    }

    /// A representative direction for the traversal order.
    fn direction(&self) -> Vec3 {
        self.rays.first().map_or(Vec3::Y, |r| r.direction)
    }

    /// `tri` against every live ray: the lane filter, then the single-ray
    /// test for the rays it keeps.
    #[inline]
    fn triangle(
        &mut self,
        tri: &TraceTriangle,
        index: u32,
        t_max: &mut [f32],
        cull: &Culled,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        let selected = match &self.plane {
            Some(plane) => {
                let image = plane.triangle_image(tri);
                let magnitude = self.magnitude.max(self.origin_max);
                let facing = plane.facing(&image, magnitude, self.plane_pad);
                if facing.is_some_and(|back| cull.drops(tri.caster, back)) {
                    return;
                }
                plane.groups_near(&image, &self.group_boxes, self.plane_pad)
            }
            None => ALL_GROUPS,
        };
        Lanes::candidates(&self.groups, tri, &mut self.masks, selected);
        for (g, &mask) in self.masks.iter().enumerate() {
            let mut mask = mask;
            while mask != 0 {
                let l = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let i = self.members[g][l] as usize;
                let lane = self.lanes[i] as usize;
                t_max[lane] = report_hit(&self.prepared[i], tri, index, t_max[lane], &mut |hit| {
                    on_hit(lane, hit)
                });
            }
        }
    }
}

/// The caller's face culling for the triangles of one frame, whose caster
/// ids are `first_caster` plus the triangle's own.
struct Culled<'c, 'a> {
    cull: &'c FaceCull<'a>,
    first_caster: u32,
}

impl Culled<'_, '_> {
    #[inline]
    fn drops(&self, caster: u32, back_facing: bool) -> bool {
        self.cull.drops(self.first_caster + caster, back_facing)
    }
}

/// How many entries with an unsettled caster a packet's beam reaches
/// ([`TopLevel::rays_reaching`]): none (no ray of it can prove anything
/// new), few (each ray is worth testing against them) or more than
/// [`MOST_OPEN_ENTRIES`] (every ray is traced).
enum OpenEntries {
    None,
    Few,
    Many,
}

/// Scratch of packet traversals (the light-relative and the model-space
/// frames), reused from packet to packet by one thread.
#[derive(Default)]
pub struct PacketScratch {
    light: Frame,
    model: ModelScratch,
    t_max: Vec<f32>,
    /// The entries with an unsettled caster a packet's beam reaches
    /// ([`PacketRays::MeetingUnsettled`], [`TopLevel::rays_reaching`]).
    open: Vec<u32>,
    /// What the latest [`TopLevel::gate_packet`] found, for
    /// [`PacketRays::Gated`]: `open` holds the entries when few.
    gate: Option<(OpenEntries, Beam)>,
}

/// A packet's scratch inside one placed part: its rays in model space,
/// and the hits of the part's first placement when it has coincident
/// copies (`Placements::replay`), with their lanes.
#[derive(Default)]
struct ModelScratch {
    frame: Frame,
    found: Vec<(usize, Hit)>,
}

impl PacketScratch {
    pub(crate) fn open_entries(&mut self) -> &mut Vec<u32> {
        &mut self.open
    }
}

impl TopLevel {
    /// Every hit of every ray of `rays` (at most [`PACKET_RAYS`]), as
    /// [`TopLevel::for_each_hit`] through the trees finds them, ray by ray:
    /// `on_hit(lane, hit)` returns that ray's new t_max.
    pub(crate) fn for_each_packet_hit(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        cull: &FaceCull,
        which: PacketRays,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        assert!(
            rays.len() <= PACKET_RAYS,
            "a packet holds at most {PACKET_RAYS} rays"
        );
        let PacketScratch {
            light,
            model,
            t_max,
            open,
            gate,
        } = scratch;
        t_max.clear();
        t_max.extend(rays.iter().map(|r| r.t_max));
        let magnitude = self.tree.magnitude;
        // Whether the packet may meet an unsettled caster is asked of the
        // beam of its live rays before the frame is made: most packets
        // left out are left out whole, and then need no frame.
        let live_rays = || rays.iter().copied().filter(|r| r.t_min <= r.t_max);
        // The open entries and the beam they were found with, from the
        // gate (whose corners' beam holds the packet's rays and serves the
        // traversal too unless rays are dropped) or from the rays' own.
        let found = match which {
            PacketRays::All => None,
            PacketRays::Gated(unsettled) => {
                gate.take().map(|(found, beam)| (found, beam, unsettled))
            }
            PacketRays::MeetingUnsettled(unsettled) => {
                Beam::new(live_rays(), magnitude).map(|beam| {
                    let direction = live_rays().next().map_or(Vec3::Y, |r| r.direction);
                    let found = self.open_entries(bottom, &beam, direction, unsettled, open);
                    (found, beam, unsettled)
                })
            }
        };
        let mut few = None;
        let mut open_beam = None;
        if let Some((found, beam, unsettled)) = found {
            match found {
                OpenEntries::None => return,
                OpenEntries::Few => few = Some(unsettled),
                OpenEntries::Many => {}
            }
            open_beam = Some(beam);
        }
        light.fill(live(rays.iter().copied().enumerate(), t_max), magnitude);
        if let Some(unsettled) = few {
            // Fewer rays, a narrower beam.
            if light.retain_where(|ray, _| self.may_meet_open(bottom, open, ray, unsettled)) {
                open_beam = None;
            }
        }
        if light.is_empty() {
            return;
        }
        let beam = open_beam.or_else(|| light.beam(t_max, magnitude));
        let Some(mut beam) = beam else {
            return self.ray_by_ray(bottom, rays, cull, on_hit);
        };
        let direction = light.direction();
        let mut widest = reach_of(light, t_max);
        self.tree.visit_beam(&mut beam, direction, |slot, beam| {
            let entry = &self.entries[slot];
            // Only a hit moves a ray's t_max: without one, the frame and
            // the beam stay as they are.
            let mut reported = false;
            let mut noting = |lane: usize, hit: Hit| {
                reported = true;
                on_hit(lane, hit)
            };
            self.entry_packet(bottom, entry, beam, light, model, t_max, cull, &mut noting);
            if !reported {
                return true;
            }
            // Settled rays leave; the beam shrinks with the rays' reach.
            let settled = light.retain_live(t_max);
            // Rebuilding costs a pass over the rays: only when the reach
            // shrank by a tenth.
            let reach = reach_of(light, t_max);
            if settled || reach < 0.9 * widest {
                if light.is_empty() {
                    return false;
                }
                widest = reach;
                if let Some(narrower) = light.beam(t_max, magnitude) {
                    *beam = narrower;
                }
            }
            true
        });
    }

    /// Whether any ray of a packet of grid texels, known by its corner
    /// rays (see [`Beam::of_grid_corners`]), may meet a caster `unsettled`
    /// accepts: false when the corners' beam reaches no part or block
    /// holding one. Otherwise the entries it reaches are kept in `scratch`
    /// for the packet's [`PacketRays::Gated`] traversal, which follows:
    /// they hold every entry any ray of the packet may enter, so testing
    /// the rays against them is exact. Only the top level is walked, and
    /// no ray of the packet need be made when the answer is false.
    pub(crate) fn gate_packet(
        &self,
        bottom: &BottomLevels,
        corners: &[TraceRay; 4],
        scratch: &mut PacketScratch,
        unsettled: &dyn Fn(u32) -> bool,
    ) -> bool {
        let Some(beam) = Beam::of_grid_corners(corners, self.tree.magnitude) else {
            scratch.gate = None;
            return true;
        };
        let open = &mut scratch.open;
        let found = self.open_entries(bottom, &beam, corners[0].direction, unsettled, open);
        let meets = !matches!(found, OpenEntries::None);
        scratch.gate = Some((found, beam));
        meets
    }

    /// [`Self::rays_reaching`] against the entries the latest
    /// [`Self::gate_packet`] on `scratch` found (every live ray when it
    /// found many or was not asked): no second walk of the top level.
    pub(crate) fn rays_reaching_gated(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        scratch: &mut PacketScratch,
        unsettled: &dyn Fn(u32) -> bool,
        keep: &mut Vec<bool>,
    ) -> usize {
        let found = scratch.gate.take().map(|(found, _)| found);
        self.keep_reaching(bottom, rays, found, &scratch.open, unsettled, keep)
    }

    /// Marks in `keep` the live rays of `rays` that `found` (what a walk
    /// found, `None`: not asked) lets through: none, all, or with few open
    /// entries those that may meet a caster `unsettled` accepts in one of
    /// `open`; returns how many.
    fn keep_reaching(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        found: Option<OpenEntries>,
        open: &[u32],
        unsettled: &dyn Fn(u32) -> bool,
        keep: &mut Vec<bool>,
    ) -> usize {
        keep.clear();
        keep.extend(rays.iter().map(|ray| ray.t_min <= ray.t_max));
        match found {
            Some(OpenEntries::None) => keep.fill(false),
            Some(OpenEntries::Few) => {
                for (k, ray) in keep.iter_mut().zip(rays) {
                    *k = *k && self.may_meet_open(bottom, open, ray, unsettled);
                }
            }
            Some(OpenEntries::Many) | None => {}
        }
        keep.iter().filter(|&&k| k).count()
    }

    /// Marks in `keep` the rays of `rays` (at most [`PACKET_RAYS`]) that
    /// may meet a caster `unsettled` accepts, and returns how many: 0 when
    /// the packet's beam reaches no part or block holding one. Against up
    /// to [`MOST_OPEN_ENTRIES`] such entries each ray gets a box test
    /// padded as the single-ray node test pads (up to `node_t_max`), which
    /// a ray hitting anything inside the box passes: a part's, the ray
    /// mapped into model space against the box of each unsettled group's
    /// triangles (`ModelGroup`); a block's, the ray against its box. With
    /// more entries, every live ray is kept. Only the top level is walked.
    pub(crate) fn rays_reaching(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        open: &mut Vec<u32>,
        unsettled: &dyn Fn(u32) -> bool,
        keep: &mut Vec<bool>,
    ) -> usize {
        let live = |ray: &TraceRay| ray.t_min <= ray.t_max;
        let live_rays = rays.iter().copied().filter(live);
        let found = match (
            rays.iter().find(|r| live(r)),
            Beam::new(live_rays, self.tree.magnitude),
        ) {
            (Some(first), Some(beam)) => {
                Some(self.open_entries(bottom, &beam, first.direction, unsettled, open))
            }
            _ => None,
        };
        self.keep_reaching(bottom, rays, found, open, unsettled, keep)
    }

    /// The entries `beam` reaches that hold a caster `unsettled` accepts,
    /// into `open` (up to one more than [`MOST_OPEN_ENTRIES`]).
    fn open_entries(
        &self,
        bottom: &BottomLevels,
        beam: &Beam,
        direction: Vec3,
        unsettled: &dyn Fn(u32) -> bool,
        open: &mut Vec<u32>,
    ) -> OpenEntries {
        open.clear();
        let mut beam = beam.clone();
        self.tree.visit_beam(&mut beam, direction, |slot, _| {
            let reaches = match self.entries[slot] {
                Entry::Part {
                    model,
                    first_caster,
                    copies,
                    ..
                } => {
                    let placements = self.placements(first_caster, copies);
                    bottom.model_groups[model as usize]
                        .iter()
                        .any(|g| placements.iter().any(|first| unsettled(first + g.group)))
                }
                Entry::Block { caster, .. } => unsettled(caster),
            };
            if reaches {
                open.push(slot as u32);
            }
            open.len() <= MOST_OPEN_ENTRIES
        });
        match open.len() {
            0 => OpenEntries::None,
            n if n <= MOST_OPEN_ENTRIES => OpenEntries::Few,
            _ => OpenEntries::Many,
        }
    }

    /// Whether `ray` may meet a caster `unsettled` accepts in one of the
    /// entries `open` holds.
    fn may_meet_open(
        &self,
        bottom: &BottomLevels,
        open: &[u32],
        ray: &TraceRay,
        unsettled: &dyn Fn(u32) -> bool,
    ) -> bool {
        open.iter()
            .any(|&slot| self.ray_may_meet(bottom, &self.entries[slot as usize], ray, unsettled))
    }

    /// Whether `ray` may hit a caster `unsettled` accepts in `entry`: a
    /// part's, the ray mapped into model space against the box of each
    /// such group's triangles; a block's, against its box; both padded as
    /// the single-ray node test pads, up to `node_t_max` (see
    /// [`Self::rays_reaching`]), so a ray they turn away hits none of them.
    fn ray_may_meet(
        &self,
        bottom: &BottomLevels,
        entry: &Entry,
        ray: &TraceRay,
        unsettled: &dyn Fn(u32) -> bool,
    ) -> bool {
        match *entry {
            Entry::Part {
                model,
                first_caster,
                to_model,
                copies,
            } => {
                let bvh = &bottom.models[model as usize];
                let model_ray = to_model.ray(ray);
                let test = BoxRay::new(&model_ray, bvh.tree.magnitude);
                let t_max = test.node_t_max(model_ray.t_max);
                let placements = self.placements(first_caster, copies);
                bottom.model_groups[model as usize].iter().any(|g| {
                    test.touches(g.lo, g.hi, model_ray.t_min, t_max)
                        && placements.iter().any(|first| unsettled(first + g.group))
                })
            }
            Entry::Block { block, .. } => {
                let level = &bottom.terrain[block as usize];
                let Some((lo, hi)) = block_box(&level.grid, level.height_range(), self.reference)
                else {
                    return true;
                };
                let test = BoxRay::new(ray, self.tree.magnitude);
                test.touches(lo, hi, ray.t_min, test.node_t_max(ray.t_max))
            }
        }
    }

    /// The packet's rays one at a time through the single-ray traversal,
    /// which leaves out the repeats `cull` drops as the packet's would.
    fn ray_by_ray(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        cull: &FaceCull,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        for (lane, ray) in rays.iter().enumerate() {
            self.for_each_hit_dropping(bottom, ray, cull.repeats, |hit| on_hit(lane, hit));
        }
    }

    /// A packet's rays against one entry of the top level: a placed part's
    /// bottom level, or a terrain block's height field.
    #[allow(clippy::too_many_arguments)]
    fn entry_packet(
        &self,
        bottom: &BottomLevels,
        entry: &Entry,
        beam: &Beam,
        light: &mut Frame,
        model: &mut ModelScratch,
        t_max: &mut [f32],
        cull: &FaceCull,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        match *entry {
            Entry::Part {
                model: index,
                first_caster,
                to_model,
                copies,
            } => {
                let placements = self.placements(first_caster, copies);
                let groups = &bottom.model_groups[index as usize];
                let part = PlacedPart {
                    bvh: &bottom.models[index as usize],
                    groups,
                    placements,
                    to_model,
                };
                let none = FaceCull::default();
                let cull = if culled_alike(cull, &placements, groups) {
                    cull
                } else {
                    &none
                };
                part.packet(beam, light, model, t_max, cull, on_hit);
            }
            Entry::Block { block, caster } => {
                self.block_packet(bottom, block, caster, beam, light, t_max, cull, on_hit);
            }
        }
    }

    /// A terrain block's cells under the packet's beam, their triangles
    /// tested in the light's frame.
    #[allow(clippy::too_many_arguments)]
    fn block_packet(
        &self,
        bottom: &BottomLevels,
        block: u32,
        caster: u32,
        beam: &Beam,
        light: &mut Frame,
        t_max: &mut [f32],
        cull: &FaceCull,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        // The top level's beam: its padding covers the tile
        // corners' rounding, as the single-ray node test's does.
        let level = &bottom.terrain[block as usize];
        let (grid, field) = (&level.grid, level.field());
        let reference = self.reference;
        field.walk(grid, reference, light.direction(), |step| match step {
            Step::Tile(min, max) => beam.touches(min, max),
            Step::Cell(cell, min, max) => {
                if beam.touches(min, max) {
                    for (tri, index) in grid
                        .cell_trace_triangles(cell, reference, caster)
                        .into_iter()
                        .flatten()
                    {
                        let cull = Culled {
                            cull,
                            first_caster: 0,
                        };
                        light.triangle(&tri, index, t_max, &cull, on_hit);
                    }
                }
                true
            }
        });
    }
}

/// Whether `cull` drops the hits of each of `placements`' groups as it
/// drops the first placement's (it drops by a caster's double-sided bit),
/// so the packet may skip a triangle by the first placement's ids.
fn culled_alike(cull: &FaceCull, placements: &Placements, groups: &[ModelGroup]) -> bool {
    let first = placements.first;
    cull.drops_back.is_none()
        || placements.copies.iter().all(|&copy| {
            groups.iter().all(|g| {
                [false, true].iter().all(|&back| {
                    cull.drops(copy + g.group, back) == cull.drops(first + g.group, back)
                })
            })
        })
}

/// One placed part of the top level (and its coincident copies): its
/// model's bottom level, the caster ids of its placements' first groups,
/// and the map into its model space.
struct PlacedPart<'b> {
    bvh: &'b Bvh,
    groups: &'b [ModelGroup],
    placements: Placements<'b>,
    to_model: ToModel,
}

impl PlacedPart<'_> {
    /// The packet's rays through the part's bottom level in model space,
    /// under the packet's beam mapped there; each hit is reported for
    /// every placement, with its caster ids.
    fn packet(
        &self,
        beam: &Beam,
        light: &mut Frame,
        model: &mut ModelScratch,
        t_max: &mut [f32],
        cull: &FaceCull,
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        let ModelScratch {
            frame: model,
            found,
        } = model;
        let (bvh, placements, to_model) = (self.bvh, self.placements, self.to_model);
        let world = to_model.world_linear();
        let image = self.origin_image(light, t_max, world);
        // The rays enter the model's frame only once the beam reaches one
        // of its triangles (it reaches none of many of a spot or point
        // packet's instances): the model beam's padding takes a bound on
        // the mapped origins instead of their largest.
        let light: &Frame = light;
        let fill = |model: &mut Frame| self.fill_model_frame(model, light, image);
        let origin_bound = to_model.origin_bound(light.origin_max);
        let model_beam = beam.to_model(&to_model, world, bvh.tree.magnitude, origin_bound);
        let direction = to_model.direction(light.direction());
        let copies = !placements.copies.is_empty();
        found.clear();
        let mut relay = |lane: usize, hit: Hit| {
            if copies {
                found.push((lane, hit));
            }
            on_hit(lane, placements.first_hit(hit))
        };
        let cull = Culled {
            cull,
            first_caster: placements.first,
        };
        let lazy = LazyFrame {
            frame: model,
            fill: Some(fill),
            direction,
        };
        bvh_packet(bvh, lazy, model_beam, t_max, &cull, &mut relay);
        if !found.is_empty() {
            let repeated = repeated_groups(cull.cull.repeats, &placements, self.groups);
            placements.replay(found, t_max, repeated, on_hit);
        }
    }

    /// Parallel rays: only those whose origin lies in the image of the
    /// instance's box in the shear plane can hit it. `None`: no such
    /// image (rays not parallel, or not bounded), every ray may.
    fn origin_image(
        &self,
        light: &Frame,
        t_max: &[f32],
        world: glam::DMat3,
    ) -> Option<([f32; 4], ShearPlane)> {
        let image = light
            .plane
            .zip(self.bvh.bounds())
            .and_then(|(plane, bounds)| {
                // The longest stretch of a ray from its origin.
                let behind = light.rays.iter().fold(0.0f32, |m, r| m.max(-r.t_min));
                let reach = reach_of(light, t_max).max(behind);
                plane.instance_image(&self.to_model, world, bounds, light.origin_max, reach)
            });
        image.zip(light.plane)
    }

    /// `model` filled with the light frame's rays in model space, those
    /// whose origin lies outside `image` left out; a run of rays sharing
    /// a direction maps it once.
    fn fill_model_frame(
        &self,
        model: &mut Frame,
        light: &Frame,
        image: Option<([f32; 4], ShearPlane)>,
    ) {
        let inside = |r: &TraceRay| {
            let Some(([x0, y0, x1, y1], plane)) = image else {
                return true;
            };
            let (x, y) = plane.point(r.origin);
            x >= x0 && x <= x1 && y >= y0 && y <= y1
        };
        let to_model = &self.to_model;
        let mut last: Option<(Vec3, Vec3)> = None;
        let rays = light
            .rays
            .iter()
            .zip(&light.lanes)
            .filter(|(r, _)| inside(r));
        model.fill(
            rays.map(|(r, &l)| {
                let direction = match last {
                    Some((light_direction, mapped)) if same_bits(light_direction, r.direction) => {
                        mapped
                    }
                    _ => to_model.direction(r.direction),
                };
                last = Some((r.direction, direction));
                (l, to_model.ray_with(r, direction))
            }),
            self.bvh.tree.magnitude,
        );
    }
}

/// Bit-for-bit equality (so +0 and -0 differ, as they may in a shear).
fn same_bits(a: Vec3, b: Vec3) -> bool {
    a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits)
}

/// The rays (lane, ray) that can still be hit: t_min <= running t_max.
fn live<'a>(
    rays: impl Iterator<Item = (usize, TraceRay)> + 'a,
    t_max: &'a [f32],
) -> impl Iterator<Item = (u8, TraceRay)> + 'a {
    rays.filter(move |(l, r)| r.t_min <= t_max[*l])
        .map(|(l, r)| (l as u8, r))
}

/// The largest running t_max of the frame's rays.
fn reach_of(frame: &Frame, t_max: &[f32]) -> f32 {
    frame
        .lanes
        .iter()
        .map(|&l| t_max[l as usize])
        .fold(f32::NEG_INFINITY, f32::max)
}

/// A model's frame of rays, filled when first needed, and the direction
/// the traversal orders its children by until then.
struct LazyFrame<'m, F: FnOnce(&mut Frame)> {
    frame: &'m mut Frame,
    fill: Option<F>,
    direction: Vec3,
}

impl<F: FnOnce(&mut Frame)> LazyFrame<'_, F> {
    fn get(&mut self) -> &mut Frame {
        if let Some(fill) = self.fill.take() {
            fill(self.frame);
        }
        self.frame
    }
}

/// A model's bottom level for the packet's rays in model space, culled by
/// `beam` (the packet's beam mapped into model space).
fn bvh_packet<F: FnOnce(&mut Frame)>(
    bvh: &Bvh,
    mut model: LazyFrame<'_, F>,
    beam: Option<Beam>,
    t_max: &mut [f32],
    cull: &Culled,
    on_hit: &mut impl FnMut(usize, Hit) -> f32,
) {
    let Some(mut beam) = beam else {
        let model = model.get();
        for (i, ray) in model.rays.iter().enumerate() {
            let lane = model.lanes[i] as usize;
            t_max[lane] = bvh.hits_within(ray, t_max[lane], &mut |hit| on_hit(lane, hit));
        }
        return;
    };
    let direction = model.direction;
    bvh.tree.visit_beam(&mut beam, direction, |slot, _| {
        let model = model.get();
        if model.is_empty() {
            return false;
        }
        let (tri, index) = bvh.slot(slot);
        model.triangle(tri, index, t_max, cull, on_hit);
        true
    });
}
