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

use super::beam::Beam;
use super::blas::BottomLevels;
use super::heightfield::Step;
use super::tlas::{Entry, TopLevel};
use super::triangle::{report_hit, Lanes, PreparedRay, LANES};
use super::{Bvh, Hit, TraceRay, TraceTriangle};
use glam::Vec3;

/// Rays of one packet at most (lane numbers are u8).
pub const PACKET_RAYS: usize = 256;

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
}

impl Frame {
    /// Refills the frame with `rays` (lane, ray in this frame), keeping
    /// those the triangle test can hit with.
    fn fill(&mut self, rays: impl Iterator<Item = (u8, TraceRay)>) {
        self.rays.clear();
        self.prepared.clear();
        self.lanes.clear();
        let mut last: Option<(Vec3, PreparedRay)> = None;
        for (lane, ray) in rays {
            let prepared = match last {
                Some((direction, like)) if same_bits(direction, ray.direction) => {
                    like.with_direction_of(&ray)
                }
                _ => PreparedRay::new(&ray),
            };
            last = Some((ray.direction, prepared));
            if prepared.is_valid() {
                self.rays.push(ray);
                self.prepared.push(prepared);
                self.lanes.push(lane);
            }
        }
        self.group();
    }

    /// Drops the rays whose running t_max fell below their t_min; true if
    /// any did.
    fn retain_live(&mut self, t_max: &[f32]) -> bool {
        let before = self.rays.len();
        let mut kept = 0;
        for i in 0..before {
            if self.rays[i].t_min <= t_max[self.lanes[i] as usize] {
                self.rays.swap(kept, i);
                self.prepared.swap(kept, i);
                self.lanes.swap(kept, i);
                kept += 1;
            }
        }
        if kept == before {
            return false;
        }
        self.rays.truncate(kept);
        self.prepared.truncate(kept);
        self.lanes.truncate(kept);
        self.group();
        true
    }

    fn group(&mut self) {
        self.groups.clear();
        self.members.clear();
        self.order.clear();
        self.order.extend((0..self.rays.len()).map(|i| i as u8));
        let prepared = &self.prepared;
        let key = |i: &u8| Lanes::axes_of(&prepared[*i as usize]);
        let first = prepared.first().map(Lanes::axes_of);
        if prepared.iter().any(|p| Some(Lanes::axes_of(p)) != first) {
            self.order.sort_by_key(key);
        }
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
        self.masks.resize(self.groups.len(), 0);
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
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        Lanes::candidates(&self.groups, tri, &mut self.masks);
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

/// Scratch of packet traversals (the light-relative and the model-space
/// frames), reused from packet to packet by one thread.
#[derive(Default)]
pub struct PacketScratch {
    light: Frame,
    model: Frame,
    t_max: Vec<f32>,
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
        } = scratch;
        t_max.clear();
        t_max.extend(rays.iter().map(|r| r.t_max));
        light.fill(live(rays.iter().copied().enumerate(), t_max));
        if light.is_empty() {
            return;
        }
        let magnitude = self.tree.magnitude;
        let Some(mut beam) = light.beam(t_max, magnitude) else {
            return self.ray_by_ray(bottom, rays, on_hit);
        };
        let direction = light.direction();
        let mut widest = reach_of(light, t_max);
        self.tree.visit_beam(&mut beam, direction, |slot, beam| {
            let entry = &self.entries[slot];
            self.entry_packet(bottom, entry, beam, light, model, t_max, on_hit);
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

    /// The packet's rays one at a time through the single-ray traversal.
    fn ray_by_ray(
        &self,
        bottom: &BottomLevels,
        rays: &[TraceRay],
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        for (lane, ray) in rays.iter().enumerate() {
            self.for_each_hit(bottom, ray, false, |hit| on_hit(lane, hit));
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn entry_packet(
        &self,
        bottom: &BottomLevels,
        entry: &Entry,
        beam: &Beam,
        light: &mut Frame,
        model: &mut Frame,
        t_max: &mut [f32],
        on_hit: &mut impl FnMut(usize, Hit) -> f32,
    ) {
        match *entry {
            Entry::Part {
                model: index,
                first_caster,
                to_model,
            } => {
                let bvh = &bottom.models[index as usize];
                let mut last: Option<(Vec3, Vec3)> = None;
                model.fill(light.rays.iter().zip(&light.lanes).map(|(r, &l)| {
                    let direction = match last {
                        Some((light_direction, mapped))
                            if same_bits(light_direction, r.direction) =>
                        {
                            mapped
                        }
                        _ => to_model.direction(r.direction),
                    };
                    last = Some((r.direction, direction));
                    (l, to_model.ray_with(r, direction))
                }));
                let origin_max = model
                    .rays
                    .iter()
                    .fold(0.0f32, |m, r| m.max(r.origin.abs().max_element()));
                let model_beam = beam.to_model(&to_model, bvh.tree.magnitude, origin_max);
                let mut relay = |lane: usize, hit: Hit| {
                    on_hit(
                        lane,
                        Hit {
                            caster: first_caster + hit.caster,
                            ..hit
                        },
                    )
                };
                bvh_packet(bvh, model, model_beam, t_max, &mut relay);
            }
            Entry::Block { block, caster } => {
                // The top level's beam: its padding covers the tile
                // corners' rounding, as the single-ray node test's does.
                let (grid, field) = &bottom.terrain[block as usize];
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
                                light.triangle(&tri, index, t_max, on_hit);
                            }
                        }
                        true
                    }
                });
            }
        }
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

/// A model's bottom level for the packet's rays in model space, culled by
/// `beam` (the packet's beam mapped into model space).
fn bvh_packet(
    bvh: &Bvh,
    model: &mut Frame,
    beam: Option<Beam>,
    t_max: &mut [f32],
    on_hit: &mut impl FnMut(usize, Hit) -> f32,
) {
    if model.is_empty() {
        return;
    }
    let Some(mut beam) = beam else {
        for (i, ray) in model.rays.iter().enumerate() {
            let lane = model.lanes[i] as usize;
            t_max[lane] = bvh.hits_within(ray, t_max[lane], &mut |hit| on_hit(lane, hit));
        }
        return;
    };
    bvh.tree
        .visit_beam(&mut beam, model.direction(), |slot, _| {
            let (tri, index) = bvh.slot(slot);
            model.triangle(tri, index, t_max, on_hit);
            true
        });
}
