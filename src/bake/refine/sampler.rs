//! The sampler: every refinement ray of one caster goes through it, so
//! what the rays prove, how many were traced and which occluders they met
//! are kept in one place, and the rays those occluders surely hide are
//! left out before they are traced (`bake::occlusion`; a model under a
//! directional light only).

use super::lattice::{footprint_block, Mask};
use crate::bake::casters::CasterTable;
use crate::bake::occlusion::{CasterImage, Occlusion};
use crate::bake::texel_beam::Point;
use crate::bake::trace_light::{CasterSet, LightRays, PacketState};
use crate::classify::{self, RayHit};
use crate::light::{ProjectedPolygon, TexelGrid, TexelRay};
use crate::trace::TraceTriangle;
use glam::DVec3;
use std::cell::OnceCell;
use std::collections::HashMap;

/// Rays traced together ([`Sampler::trace_batch`]): a packet's worth.
pub(super) const BATCH: usize = 64;

/// Rays of a batch that go without the occlusion test (its cost would
/// not pay).
pub(super) const FEW_POINTS: usize = 4;

/// Most occluders a caster's refinement keeps (the latest met): each costs
/// a test per point.
const MOST_OCCLUDERS: usize = 8;

/// Occluders' images by caster, kept across the casters a thread refines
/// (neighbours in id order, so mostly neighbours in the world) and dropped
/// whole when [`MOST_IMAGES`] are held.
type Images = HashMap<u32, CasterImage>;

/// Most occluder images one refining thread keeps.
const MOST_IMAGES: usize = 512;

/// What a batch of a caster's rays is traced for.
#[derive(Clone, Copy)]
enum Aim {
    /// Proving the caster (and any other caster its rays prove).
    Caster,
    /// Proving other casters only: rays that can meet none not yet proven
    /// may be left out.
    Others,
}

/// The casters already proven, which a sampler's rays for others need not
/// prove again ([`Sampler::trace_batch_for_others`]).
#[derive(Clone, Copy)]
pub(super) enum Known<'r> {
    /// A set: the grid's answer, and what refinement proved before.
    Set(&'r CasterSet),
    /// Sorted lists of ids (a caster refined on its own for the bake
    /// cache: its cells' answers and its own proofs).
    Lists(&'r [Vec<u32>]),
}

impl Known<'_> {
    fn contains(&self, caster: u32) -> bool {
        match self {
            Known::Set(set) => set.contains(caster),
            Known::Lists(lists) => lists.iter().any(|l| l.binary_search(&caster).is_ok()),
        }
    }
}

/// The casters a refining thread's rays proved; with a log, also each one
/// in the order first proven, so one caster's proofs can be taken out
/// (the bake cache refines each caster on its own).
#[derive(Debug, Clone)]
pub(super) struct Proven {
    pub(super) set: CasterSet,
    log: Option<Vec<u32>>,
}

impl Proven {
    pub(super) fn new(casters: usize, logged: bool) -> Proven {
        Proven {
            set: CasterSet::new(casters),
            log: logged.then(Vec::new),
        }
    }

    pub(super) fn insert(&mut self, caster: u32) {
        if let Some(log) = &mut self.log {
            if !self.set.contains(caster) {
                log.push(caster);
            }
        }
        self.set.insert(caster);
    }

    /// The casters logged since the last take, ascending, taken out of the
    /// set too (empty without a log).
    pub(super) fn take_logged(&mut self) -> Vec<u32> {
        let mut taken = self.log.as_mut().map(std::mem::take).unwrap_or_default();
        taken.sort_unstable();
        self.set.remove_all(&taken);
        taken
    }

    /// Both threads' proofs in `self`.
    pub(super) fn merge(&mut self, other: Proven) {
        for c in other.log.into_iter().flatten() {
            self.insert(c);
        }
        self.set = std::mem::replace(&mut self.set, CasterSet::new(0)).union(&other.set);
    }

    /// The casters logged so far, ascending (left in the set).
    pub(super) fn logged(&self) -> Vec<u32> {
        let mut logged = self.log.clone().unwrap_or_default();
        logged.sort_unstable();
        logged
    }
}

/// A refining thread's buffers, reused by each sampler it makes (the
/// occluders' images stay warm from caster to caster).
#[derive(Default)]
pub(super) struct SamplerBuffers {
    hits: Vec<RayHit>,
    packet: PacketState,
    images: Images,
    occluders: Vec<u32>,
}

impl SamplerBuffers {
    /// A sampler of `caster`'s rays writing into these buffers and the
    /// casters it proves into `useful`: `known` the casters already
    /// proven (its rays for others leave out those that can meet only
    /// these), `occlusion` when its rays where occluders surely hide it
    /// are left out (a model under a directional light).
    pub(super) fn sampler<'r, 'a>(
        &'r mut self,
        rays: &'r LightRays<'a>,
        known: Known<'r>,
        useful: &'r mut Proven,
        caster: u32,
        occlusion: Option<&'r Occlusion<'r, 'r>>,
    ) -> Sampler<'r, 'a> {
        self.occluders.clear();
        let alpha_tested = rays.casters.casters[caster as usize].alpha_tested;
        Sampler {
            rays,
            known,
            caster,
            useful,
            hits: &mut self.hits,
            packet: &mut self.packet,
            hidden: occlusion.map(|occlusion| Hidden {
                occlusion,
                images: &mut self.images,
                occluders: &mut self.occluders,
                alpha_tested,
                least_depth: OnceCell::new(),
                mask: None,
            }),
            traced: 0,
        }
    }
}

/// Traces refinement rays for one caster, recording what they prove.
pub(super) struct Sampler<'r, 'a> {
    pub(super) rays: &'r LightRays<'a>,
    /// The casters already proven useful: the grid's, and for deferred
    /// surface points also those refinement proved before they go.
    known: Known<'r>,
    pub(super) caster: u32,
    useful: &'r mut Proven,
    hits: &'r mut Vec<RayHit>,
    packet: &'r mut PacketState,
    /// Under a directional light, for a model: how rays its occluders
    /// surely hide are left out (`bake::occlusion`).
    hidden: Option<Hidden<'r>>,
    /// Rays traced so far.
    pub(super) traced: u64,
}

/// A caster's occlusion state while it is refined.
struct Hidden<'r> {
    occlusion: &'r Occlusion<'r, 'r>,
    images: &'r mut Images,
    /// The casters its traced rays met in front of it, latest last.
    occluders: &'r mut Vec<u32>,
    /// Whether the caster is alpha-tested (in no Opaque pass).
    alpha_tested: bool,
    /// [`nearest_depth`] of the caster, worked out when first asked.
    least_depth: OnceCell<Option<f64>>,
    /// The lattice points its occluders surely hide at its least depth
    /// ([`Sampler::mask_lattice`]), once asked.
    mask: Option<Mask>,
}

impl Hidden<'_> {
    /// Adds the casters among `hits` (one ray's, or a packet's) other than
    /// `caster`, receiver-only ones and terrain blocks to the occluders;
    /// returns whether any was not among them.
    fn note<'h>(
        &mut self,
        caster: u32,
        casters: &CasterTable,
        hits: impl Iterator<Item = &'h RayHit>,
    ) -> bool {
        let mut met_new = false;
        for hit in hits {
            let info = &casters.casters[hit.caster as usize];
            if hit.caster == caster || info.receiver_only || info.is_terrain() {
                continue;
            }
            let before = self.occluders.len();
            self.occluders.retain(|&c| c != hit.caster);
            met_new |= self.occluders.len() == before;
            if self.occluders.len() == MOST_OCCLUDERS {
                self.occluders.remove(0);
            }
            self.occluders.push(hit.caster);
        }
        met_new
    }

    /// [`nearest_depth`] of the caster (its triangles `run`), worked out
    /// once.
    fn least_depth(&self, run: &[TraceTriangle], grid: &TexelGrid) -> Option<f64> {
        *self
            .least_depth
            .get_or_init(|| nearest_depth(run, grid.direction(), grid.reference_point()))
    }

    /// Which of `points` (texel units of the light's one face; the refined
    /// caster's nearest depth at each `near`) the occluders surely hide
    /// (`Occlusion::hidden`).
    fn hidden(&mut self, points: &[Point], near: &[f64]) -> Vec<bool> {
        if self.occluders.is_empty() {
            return vec![false; points.len()];
        }
        let (occlusion, alpha_tested) = (self.occlusion, self.alpha_tested);
        occlusion.hidden(points, near, alpha_tested, &self.images())
    }

    /// The occluders' images, each made when first needed.
    fn images(&mut self) -> Vec<&CasterImage> {
        let occlusion = self.occlusion;
        if self.images.len() + self.occluders.len() > MOST_IMAGES {
            self.images.clear();
        }
        for &c in self.occluders.iter() {
            self.images
                .entry(c)
                .or_insert_with(|| occlusion.image(0, c));
        }
        self.occluders.iter().map(|c| &self.images[c]).collect()
    }
}

impl<'r> Sampler<'r, '_> {
    /// Whether rays its occluders surely hide are left out (a model under
    /// a directional light).
    pub(super) fn has_occlusion(&self) -> bool {
        self.hidden.is_some()
    }

    /// The occlusion test's depth margin (`Occlusion::margin`), if there
    /// is one.
    pub(super) fn occlusion_margin(&self) -> Option<f64> {
        self.hidden.as_ref().map(|h| h.occlusion.margin())
    }

    /// The caster's mask of surely hidden lattice points, if it has one.
    pub(super) fn mask(&self) -> Option<&Mask> {
        self.hidden.as_ref()?.mask.as_ref()
    }

    /// Traces `rays` (at most a packet's worth, near each other: one
    /// caster's surface points or a patch of its footprint) together, each
    /// with the answer it gets alone; returns whether any proves the caster
    /// useful.
    pub(super) fn trace_batch(&mut self, rays: &[TexelRay]) -> bool {
        self.trace_aimed(rays, Aim::Caster)
    }

    /// The hits of each of the last batch's first `rays` rays.
    pub(super) fn batch_hits(&self, rays: usize) -> &[Vec<RayHit>] {
        self.packet.hits(rays)
    }

    /// [`Self::trace_batch`] of the caster's surface points `rays`, but
    /// ray by ray for a terrain block: its points lie scattered over a
    /// chunk, and a packet's beam over them walks the block's whole
    /// heightfield, which costs more than the rays alone. Each ray gets
    /// the answer it gets alone either way, and its hits are noted in the
    /// same order.
    pub(super) fn trace_surface_points(&mut self, rays: &[TexelRay]) -> bool {
        if !self.rays.casters.casters[self.caster as usize].is_terrain() {
            return self.trace_batch(rays);
        }
        rays.iter().fold(false, |proven, ray| {
            self.trace_batch(std::slice::from_ref(ray)) | proven
        })
    }

    /// Traces `rays`, which cannot prove the caster (it is proven, or they
    /// are surely hidden from it), as [`Self::trace_batch`] does: only
    /// those that may meet a caster neither known (`known`), nor this one,
    /// nor receiver-only are traced (the others could prove nothing new).
    pub(super) fn trace_batch_for_others(&mut self, rays: &[TexelRay]) {
        self.trace_aimed(rays, Aim::Others);
    }

    /// [`Self::trace_batch`] or [`Self::trace_batch_for_others`], as `aim`
    /// says; returns whether a ray proves the caster.
    fn trace_aimed(&mut self, rays: &[TexelRay], aim: Aim) -> bool {
        self.traced += rays.len() as u64;
        self.packet.rays.clear();
        self.packet.rays.extend_from_slice(rays);
        let (caster, known, casters) = (self.caster, self.known, self.rays.casters);
        let mut proven = false;
        let useful = &mut *self.useful;
        let on_useful = |c: u32| {
            proven |= c == caster;
            useful.insert(c);
        };
        match aim {
            Aim::Caster => self.rays.trace_packet(self.packet, on_useful),
            Aim::Others => {
                let unsettled = |c: u32| {
                    c != caster && !known.contains(c) && !casters.casters[c as usize].receiver_only
                };
                self.rays
                    .trace_packet_meeting(self.packet, &unsettled, on_useful)
            }
        }
        if let Some(hidden) = &mut self.hidden {
            let hits = self.packet.hits(rays.len()).iter().flatten();
            hidden.note(caster, casters, hits);
        }
        proven
    }

    /// Counts `traced` rays traced on the sampler's behalf (a wave of
    /// outline cells, in parallel) and the casters `found` useful by them.
    pub(super) fn record(&mut self, found: Vec<u32>, traced: usize) {
        for c in found {
            self.useful.insert(c);
        }
        self.traced += traced as u64;
    }

    /// The occlusion state and the caster's least depth anywhere (its
    /// triangles `run`), when there is an occlusion test (a model under a
    /// directional light) and that depth is finite.
    fn hidden_at_least_depth(&mut self, run: &[TraceTriangle]) -> Option<(&mut Hidden<'r>, f64)> {
        let grid = self.rays.grid;
        let hidden = self.hidden.as_mut()?;
        let nearest = hidden.least_depth(run, grid)?;
        Some((hidden, nearest))
    }

    /// The caster's surface rays `rays` (through the points `at`; `run`
    /// its triangles) split into those that may prove it and those its
    /// occluders so far surely hide from it (`Occlusion::hidden`, taking
    /// its least depth anywhere as its depth at every point), which can
    /// prove only other casters. Everything may prove it without the
    /// occlusion test (a spot or point light, a terrain block).
    pub(super) fn split_hidden(
        &mut self,
        rays: &[TexelRay],
        at: &[DVec3],
        run: &[TraceTriangle],
    ) -> (Vec<TexelRay>, Vec<TexelRay>) {
        let grid = self.rays.grid;
        let Some((hidden, nearest)) = self.hidden_at_least_depth(run) else {
            return (rays.to_vec(), Vec::new());
        };
        if rays.len() <= FEW_POINTS {
            return (rays.to_vec(), Vec::new());
        }
        // A point off the face is never hidden (NaN lies in no region).
        let points: Vec<Point> = at
            .iter()
            .map(|&p| grid.project_point(0, p).unwrap_or((f64::NAN, f64::NAN)))
            .collect();
        let near = vec![nearest; points.len()];
        let hidden = hidden.hidden(&points, &near);
        let (mut open, mut surely_hidden) = (Vec::new(), Vec::new());
        for (&ray, hidden) in rays.iter().zip(hidden) {
            match hidden {
                true => surely_hidden.push(ray),
                false => open.push(ray),
            }
        }
        (open, surely_hidden)
    }

    /// Under a directional light, for a model: which lattice points
    /// (`density` per texel side) in the box of its footprint (its
    /// triangles `run`, `projected` on the face; `None`: a vertex not
    /// finite) its occluders so far surely hide from it, taking its least
    /// depth anywhere as its depth at each (as [`Self::split_hidden`]);
    /// kept as its [`Mask`], whose points its lattice leaves out (no ray
    /// there can prove it). True when the mask holds every point: then no
    /// lattice ray can prove it. Only a box [`footprint_block`] answers
    /// for is asked.
    pub(super) fn mask_lattice(
        &mut self,
        run: &[TraceTriangle],
        projected: &[Option<ProjectedPolygon>],
        density: u32,
    ) -> bool {
        let Some((hidden, nearest)) = self.hidden_at_least_depth(run) else {
            return false;
        };
        let Some(block) = footprint_block(projected, density) else {
            return false;
        };
        if hidden.occluders.is_empty() {
            return false;
        }
        let alpha_tested = hidden.alpha_tested;
        let occlusion = hidden.occlusion;
        let mask = Mask::new(
            block,
            occlusion.hidden_block(block, nearest, alpha_tested, &hidden.images()),
        );
        let all = mask.holds_all();
        hidden.mask = Some(mask);
        all
    }

    /// `points` (a whole cell's, texel units, each with the caster's
    /// nearest depth there) less those the caster's occluders so far
    /// surely hide.
    pub(super) fn unhidden(&mut self, mut points: Vec<(Point, f64)>) -> Vec<(Point, f64)> {
        let Some(hidden) = &mut self.hidden else {
            return points;
        };
        let (at, near): (Vec<Point>, Vec<f64>) = points.iter().copied().unzip();
        let mut hidden = hidden.hidden(&at, &near).into_iter();
        points.retain(|_| hidden.next() == Some(false));
        points
    }

    /// Per pass, whether the caster is in the front set of a ray with
    /// `hits` (bit 0: All, bit 1: Opaque).
    pub(super) fn front_passes(&self, hits: &[RayHit]) -> u8 {
        let rules = self.rays.rules;
        let mut front = 0u8;
        for pass in 0..classify::pass_count(rules.passes) {
            classify::pass_depths(hits, rules.passes, pass, rules.tie_epsilon, |c| {
                if c == self.caster {
                    front |= 1 << pass;
                }
            });
        }
        front
    }

    /// Traces `ray`; returns whether it proves the caster useful and, per
    /// pass, whether the caster is in the ray's front set (bit 0: All,
    /// bit 1: Opaque).
    pub(super) fn trace(&mut self, ray: &TexelRay) -> (bool, u8) {
        self.traced += 1;
        let mut proven = false;
        let (caster, useful) = (self.caster, &mut *self.useful);
        self.rays.trace(ray, self.hits, |c| {
            proven |= c == caster;
            useful.insert(c);
        });
        (proven, self.front_passes(self.hits))
    }

    /// Adds the casters the last ray [`Self::trace`] traced met to the
    /// occluders; returns whether any was new (never, without an occlusion
    /// test).
    pub(super) fn note_last_hits(&mut self) -> bool {
        let (caster, casters) = (self.caster, self.rays.casters);
        self.hidden
            .as_mut()
            .is_some_and(|hidden| hidden.note(caster, casters, self.hits.iter()))
    }
}

/// The least depth (as the occlusion test's: `p·direction`) of any vertex
/// of `run` (light-relative to `reference`) under a directional light: no
/// deeper than the caster's nearest depth on any ray. `None` for a spot or
/// point light, or when it is not finite.
fn nearest_depth(run: &[TraceTriangle], direction: Option<DVec3>, reference: DVec3) -> Option<f64> {
    let direction = direction?;
    let depths = run
        .iter()
        .flat_map(|t| t.vertices)
        .map(|v| (reference + v.as_dvec3()).dot(direction));
    Some(depths.fold(f64::INFINITY, f64::min)).filter(|d| d.is_finite())
}
