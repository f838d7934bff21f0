//! Refinement (`--refine`): after the texel grid, every caster not yet
//! useful for a light gets extra rays where it actually is. The grid
//! samples the light's view at texel centres, so a caster smaller than a
//! texel, or one that shows only in a sliver between centres, can be
//! missed.
//!
//! Two kinds of rays, both fixed before tracing and OR-ed (the outcome does
//! not depend on order or threads):
//! - area-weighted points of the caster's own surface (`refine_samples`
//!   per caster, deterministic per (light, caster));
//! - its light-space footprint on the lattice of a grid `refine_density`
//!   times denser per side (the rays of that denser grid). The footprint is
//!   cut into cells; cells its hittable triangles miss are dropped whole and
//!   the caster's rays stop at the first that proves it useful. For a model
//!   under a directional light every lattice point on the footprint is
//!   traced, so at density 8 refinement finds every model caster the ×8
//!   grid finds among those it refines (the footprint is bounded by the
//!   model's size over the texel size). Terrain blocks (as large as a chunk)
//!   and every caster of a spot or point light (a wall a metre from a point
//!   light fills most of a face: a million lattice points) are not bounded
//!   so: there a cell that the outline of the caster's union of hittable
//!   triangles does not cross is probed at its corners and split only where
//!   the probes disagree on whether the caster is front-most (in either
//!   pass); outline cells go down to at most [`BATCH`] lattice points, each
//!   of which on the footprint is then traced. Probing is a sample: on
//!   `bench`, probing models too lost five sun casters the ×8 grid keeps
//!   (walls and a pillar useful only inside probed cells); the whole
//!   lattice for terrain cost 3.6× the plain bake on `village`.
//!
//! Whole-lattice cells leave out the lattice rays that cannot prove the
//! caster: the casters the caster's rays met so far are its occluders, a
//! point where they surely keep the caster out of the front set is not
//! traced (`bake::occlusion`), and each cell's middle point among the rest
//! is traced alone first (a probe, for more occluders). On `bench` most
//! remaining casters lie under trees and stay culled: this cut the sun's
//! refinement rays from 1.0 M to 0.49 M with the same masks. Before the
//! lattice, the occluders are asked once for every lattice point in the
//! box of the footprint, taking the caster's least depth anywhere (a
//! [`Mask`], found triangle by triangle: `Occlusion::hidden_block`): when
//! they hide all of them the lattice is skipped whole, and else its
//! polygons, top cells and points the mask hides are left out before any
//! work on them (on `bench` the mask hides 79 % of the lattice points on
//! the remaining footprints). A whole-lattice top cell works out which of
//! its points lie on the footprint, and the caster's depth at each, once
//! ([`LatticeCell`]); its cells of at most [`BATCH`] points read them.
//!
//! Surface points that cannot prove their caster (once it is proven, and
//! before that those its occluders surely hide from it) may still prove
//! others, so they are traced, but later and only where they may meet a
//! caster not yet proven. Candidates are refined in chunks (fixed by the
//! settings); a chunk's deferred points go after every caster of the chunk
//! has traced its own rays, gated by the casters proven so far: a set
//! fixed before they go, so which rays go does not depend on threads. On
//! `bench` (one thread, nine alternating rounds) refinement took 0.653 s
//! with this smaller set, 0.707 s with the grid's proofs alone.
//!
//! Rays go as packets wherever they lie near each other (surface points,
//! a cell's corner probes, a small outline cell, a whole-lattice cell
//! after its probe): a packet gives each ray the answer it gets alone. A
//! terrain block's surface points, scattered over a chunk, go ray by ray.
//!
//! Threads share the casters out a few at a time, and a large caster's
//! outline cells a wave at a time (`Footprint::outline_cells`); what is
//! proven and every ray counted are the same for any number of threads.

use super::casters::CasterTable;
use super::conservative::Affine;
use super::occlusion::{CasterImage, LatticeBlock, Occlusion};
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays, PacketState};
use super::BakeConfig;
use crate::classify::{self, RayHit};
use crate::formats::bake_settings::FaceCulling;
use crate::light::{FacePolygon, ProjectedPolygon, TexelGrid, TexelRay};
use crate::progress::{Counter, Phase, Progress};
use crate::rng::{mix, Rng};
use super::texel_beam::{self as beam, bounds, ConvexRegion, Point, Rect};
use crate::trace::TraceTriangle;
use glam::DVec3;
use rayon::prelude::*;
use std::cell::OnceCell;
use std::collections::HashMap;
use std::sync::Mutex;

/// Barycentric coordinates stay this far from the edges, so a sample lies
/// inside its triangle and its ray crosses that triangle, not a neighbour.
const EDGE_MARGIN: f64 = 0.02;

/// Extra rays for every caster in the light's reach that is neither useful
/// yet nor receiver-only: `config.refine_samples` surface points and the
/// footprint lattice at `config.refine_density` (see the module docs).
/// Returns the casters the rays prove useful and how many rays were traced.
/// Each caster refined is counted in [`Phase::Refining`] of `progress`.
pub fn refine(
    world: &BakeWorld,
    setup: &LightSetup,
    rays_of_light: &LightRays<'_>,
    already_useful: &CasterSet,
    config: &BakeConfig,
    progress: &dyn Progress,
) -> (CasterSet, u64) {
    let candidates = candidates(world, setup, already_useful);
    let light = Some(config.lights[setup.index].name.as_str());
    let occlusion = Occlusion::new(world, setup, rays_of_light, config);
    let counter = Counter::begin(progress, Phase::Refining, light, candidates.len() as u64);
    let refining = Refining {
        world,
        setup,
        rays: rays_of_light,
        config,
        occlusion: occlusion.as_ref(),
    };
    let scratches = Scratches::new(world.casters.len());
    let chunk = (DEFERRED_RAYS / config.refine_samples.max(1) as usize).max(1);
    for candidates in candidates.chunks(chunk) {
        refining.own_rays(candidates, already_useful, &scratches, &counter);
        // The deferred points go only where they may meet a caster still
        // unproven now that the chunk's own rays are traced: a set fixed
        // before they go, so which rays go does not depend on threads.
        let (deferred, settled) = scratches.deferred_and_proven();
        let settled = settled.union(already_useful);
        refining.deferred_rays(&deferred, &settled, &scratches);
    }
    counter.finish();
    scratches.answer()
}

/// The casters in the light's reach neither useful yet nor receiver-only,
/// terrain blocks first: the costliest to refine (each as large as a
/// chunk), so the threads share them out early instead of waiting on them
/// at the end.
fn candidates(world: &BakeWorld, setup: &LightSetup, already_useful: &CasterSet) -> Vec<u32> {
    let casters = &world.casters;
    let mut candidates: Vec<u32> = setup
        .reach
        .blocks
        .iter()
        .map(|&b| casters.of_block[b as usize])
        .collect();
    for &p in &setup.reach.parts {
        let part = &world.parts[p as usize];
        let groups = world.scene.models[part.model].groups.len() as u32;
        candidates.extend(part.first_caster..part.first_caster + groups);
    }
    candidates.retain(|&caster| {
        !already_useful.contains(caster) && !casters.casters[caster as usize].receiver_only
    });
    candidates
}

/// One light's refinement: what its threads share.
struct Refining<'r, 'a> {
    world: &'r BakeWorld<'a>,
    setup: &'r LightSetup,
    rays: &'r LightRays<'a>,
    config: &'r BakeConfig,
    /// A directional light's occlusion test (`None`: a spot or point
    /// light).
    occlusion: Option<&'r Occlusion<'r, 'r>>,
}

impl Refining<'_, '_> {
    /// Each of `candidates`' own rays, in parallel: its surface points
    /// that may prove it, then its footprint lattice unless they did. The
    /// points that cannot prove it are deferred (`Scratch::deferred`).
    /// Whether a caster goes on is decided by its own rays only (not by
    /// what its thread's other casters proved), so the rays traced, and
    /// what they prove, do not depend on threads.
    fn own_rays(
        &self,
        candidates: &[u32],
        known: &CasterSet,
        scratches: &Scratches,
        counter: &Counter,
    ) {
        let casters = &self.world.casters;
        candidates
            .par_iter()
            .with_max_len(MOST_CASTERS_A_TASK)
            .for_each(|&caster| {
                let run = self.setup.caster_triangles(self.world, caster);
                let is_terrain = casters.casters[caster as usize].is_terrain();
                let hidden = self.occlusion.filter(|_| !is_terrain);
                scratches.with(|scratch| {
                    let mut sampler = scratch.sampler(self.rays, known, caster, hidden);
                    let samples = self.config.refine_samples;
                    let (proven, deferred) =
                        surface_points(&mut sampler, &run, self.setup.index, samples);
                    if self.config.refine_density > 0 && !proven {
                        footprint_lattice(&mut sampler, &run, self.config);
                    }
                    scratch.rays += sampler.traced;
                    if !deferred.is_empty() {
                        scratch.deferred.push((caster, deferred));
                    }
                });
                counter.add(1);
            });
    }

    /// The `deferred` surface points (per caster), in parallel, each only
    /// where it may meet a caster not in `settled`.
    fn deferred_rays(
        &self,
        deferred: &[(u32, Vec<TexelRay>)],
        settled: &CasterSet,
        scratches: &Scratches,
    ) {
        deferred
            .par_iter()
            .with_max_len(MOST_CASTERS_A_TASK)
            .for_each(|(caster, rays)| {
                scratches.with(|scratch| {
                    let mut sampler = scratch.sampler(self.rays, settled, *caster, None);
                    for batch in rays.chunks(BATCH) {
                        sampler.trace_batch_for_others(batch);
                    }
                    scratch.rays += sampler.traced;
                })
            });
    }
}

/// Casters one task refines at most: small tasks share the casters out
/// evenly between threads to the end of each chunk (on `bench`, two
/// threads, 5 % faster than rayon's own split).
const MOST_CASTERS_A_TASK: usize = 16;

/// Each thread's scratch, kept for the whole light (its occluder images
/// stay warm from chunk to chunk and task to task), the thread's by its
/// index in the pool. What the scratches hold is a set and a count, the
/// same whichever thread refined which caster.
struct Scratches {
    slots: Vec<Mutex<Option<Scratch>>>,
    casters: usize,
}

impl Scratches {
    fn new(casters: usize) -> Scratches {
        // One more, for a caller outside the pool.
        let threads = rayon::current_num_threads() + 1;
        Scratches {
            slots: (0..threads).map(|_| Mutex::new(None)).collect(),
            casters,
        }
    }

    fn slot(&self, index: usize) -> std::sync::MutexGuard<'_, Option<Scratch>> {
        self.slots[index]
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// `work` with the calling thread's scratch. The scratch is taken out
    /// of its slot meanwhile, not locked: a thread waiting on nested
    /// parallel work (`Footprint::outline_cells`) may run another caster's
    /// task, which then starts a scratch of its own, merged back after.
    fn with<R>(&self, work: impl FnOnce(&mut Scratch) -> R) -> R {
        let last = self.slots.len() - 1;
        let index = rayon::current_thread_index().map_or(last, |i| i.min(last));
        let taken = self.slot(index).take();
        let mut scratch = taken.unwrap_or_else(|| Scratch::new(self.casters));
        let answer = work(&mut scratch);
        let mut slot = self.slot(index);
        *slot = Some(match slot.take() {
            None => scratch,
            Some(other) => scratch.merge(other),
        });
        answer
    }

    /// The surface points deferred so far (taken; by caster id), and the
    /// casters proven so far.
    fn deferred_and_proven(&self) -> (Vec<(u32, Vec<TexelRay>)>, CasterSet) {
        let mut deferred = Vec::new();
        let mut proven = CasterSet::new(self.casters);
        for index in 0..self.slots.len() {
            if let Some(scratch) = self.slot(index).as_mut() {
                deferred.append(&mut scratch.deferred);
                proven = proven.union(&scratch.useful);
            }
        }
        deferred.sort_unstable_by_key(|&(caster, _)| caster);
        (deferred, proven)
    }

    /// The casters proven and the rays traced, over every thread.
    fn answer(&self) -> (CasterSet, u64) {
        let (_, proven) = self.deferred_and_proven();
        let rays = (0..self.slots.len())
            .filter_map(|index| self.slot(index).as_ref().map(|s| s.rays))
            .sum();
        (proven, rays)
    }
}

/// Surface points deferred (see [`surface_points`]) are held for at most
/// about this many rays (4 MiB) before they are traced: candidates are
/// refined in chunks of this over `refine_samples`.
const DEFERRED_RAYS: usize = 1 << 16;

/// One refining thread's answer so far and its reused buffers.
struct Scratch {
    useful: CasterSet,
    /// Surface points deferred by their caster ([`surface_points`]).
    deferred: Vec<(u32, Vec<TexelRay>)>,
    hits: Vec<RayHit>,
    packet: PacketState,
    images: Images,
    occluders: Vec<u32>,
    rays: u64,
}

/// Occluders' images by caster, kept across the casters a thread refines
/// (neighbours in id order, so mostly neighbours in the world) and dropped
/// whole when [`MOST_IMAGES`] are held.
type Images = HashMap<u32, CasterImage>;

/// Most occluder images one refining thread keeps.
const MOST_IMAGES: usize = 512;

impl Scratch {
    fn new(casters: usize) -> Scratch {
        Scratch {
            useful: CasterSet::new(casters),
            deferred: Vec::new(),
            hits: Vec::new(),
            packet: PacketState::default(),
            images: Images::new(),
            occluders: Vec::new(),
            rays: 0,
        }
    }

    /// Two threads' answers as one (the buffers of `self` kept).
    fn merge(mut self, mut other: Scratch) -> Scratch {
        self.deferred.append(&mut other.deferred);
        Scratch {
            useful: self.useful.union(&other.useful),
            rays: self.rays + other.rays,
            ..self
        }
    }

    /// A sampler of `caster`'s rays writing into these buffers: `known`
    /// the casters already proven (its rays for others leave out those
    /// that can meet only these), `occlusion` when its rays where
    /// occluders surely hide it are left out (a model under a directional
    /// light).
    fn sampler<'r, 'a>(
        &'r mut self,
        rays: &'r LightRays<'a>,
        known: &'r CasterSet,
        caster: u32,
        occlusion: Option<&'r Occlusion<'r, 'r>>,
    ) -> Sampler<'r, 'a> {
        self.occluders.clear();
        let alpha_tested = rays.casters.casters[caster as usize].alpha_tested;
        Sampler {
            rays,
            known,
            caster,
            useful: &mut self.useful,
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

/// Rays traced together ([`Sampler::trace_batch`]): a packet's worth.
const BATCH: usize = 64;

/// What a batch of a caster's rays is traced for.
#[derive(Clone, Copy)]
enum Aim {
    /// Proving the caster (and any other caster its rays prove).
    Caster,
    /// Proving other casters only: rays that can meet none not yet proven
    /// may be left out.
    Others,
}

/// Traces refinement rays for one caster, recording what they prove.
struct Sampler<'r, 'a> {
    rays: &'r LightRays<'a>,
    /// The casters already proven useful: the grid's, and for deferred
    /// surface points also those refinement proved before they go.
    known: &'r CasterSet,
    caster: u32,
    useful: &'r mut CasterSet,
    hits: &'r mut Vec<RayHit>,
    packet: &'r mut PacketState,
    /// Under a directional light, for a model: how rays its occluders
    /// surely hide are left out (`bake::occlusion`).
    hidden: Option<Hidden<'r>>,
    traced: u64,
}

/// Most occluders a caster's refinement keeps (the latest met): each costs
/// a test per point.
const MOST_OCCLUDERS: usize = 8;

/// Rays of a batch that go without the occlusion test (its cost would
/// not pay).
const FEW_POINTS: usize = 4;

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

/// Which lattice points of the box of a caster's footprint its occluders
/// surely hide from it ([`Occlusion::hidden_block`] at its least depth
/// anywhere). Points outside the box are not on the footprint.
struct Mask {
    block: LatticeBlock,
    hidden: Vec<bool>,
}

impl Mask {
    /// Whether lattice point `(i, j)` is surely hidden.
    fn holds(&self, i: i64, j: i64) -> bool {
        self.block.index(i, j).is_some_and(|at| self.hidden[at])
    }

    /// Whether every point of `cell` (lattice points) in the box is surely
    /// hidden: then none of the cell that may be on the footprint is
    /// traced.
    fn holds_cell(&self, (i0, j0, ni, nj): (i64, i64, i64, i64)) -> bool {
        let b = &self.block;
        let (i1, j1) = ((i0 + ni).min(b.i0 + b.ni), (j0 + nj).min(b.j0 + b.nj));
        (j0.max(b.j0)..j1).all(|j| (i0.max(b.i0)..i1).all(|i| self.holds(i, j)))
    }

    /// Whether every lattice point within `reach` of the box of polygon
    /// `p` is surely hidden: where its region (grown by [`TOUCH`]) and its
    /// depth margin may reach, when `reach` is at least the margin and
    /// the lattice step (a mask is made only when `footprint_box` found
    /// every region within a step of its box). Then the polygon changes
    /// no point that is traced.
    fn holds_polygon(&self, p: &ProjectedPolygon, reach: f64) -> bool {
        let (lo, hi) = bounds(p.iter().map(|&(x, y, _)| (x, y)));
        let columns = self.block.columns(lo.0 - reach, hi.0 + reach);
        let mut rows = self.block.rows(lo.1 - reach, hi.1 + reach);
        rows.all(|j| columns.clone().all(|i| self.holds(i, j)))
    }
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
    fn least_depth(&self, run: &[TraceTriangle], grid: &crate::light::TexelGrid) -> Option<f64> {
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
    /// The caster's mask of surely hidden lattice points, if it has one.
    fn mask(&self) -> Option<&Mask> {
        self.hidden.as_ref()?.mask.as_ref()
    }

    /// Traces `rays` (at most a packet's worth, near each other: one
    /// caster's surface points or a patch of its footprint) together, each
    /// with the answer it gets alone; returns whether any proves the caster
    /// useful.
    fn trace_batch(&mut self, rays: &[TexelRay]) -> bool {
        self.trace_aimed(rays, Aim::Caster)
    }

    /// [`Self::trace_batch`] of the caster's surface points `rays`, but
    /// ray by ray for a terrain block: its points lie scattered over a
    /// chunk, and a packet's beam over them walks the block's whole
    /// heightfield (on `bench`, one thread, 25 µs a ray; refinement 4 %
    /// faster ray by ray, no faster for a perspective light's casters).
    /// Each ray gets the answer it gets alone either way, and its hits are
    /// noted in the same order.
    fn trace_surface_points(&mut self, rays: &[TexelRay]) -> bool {
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
    fn trace_batch_for_others(&mut self, rays: &[TexelRay]) {
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
    fn split_hidden(
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
    /// kept as its [`Mask`], whose points its lattice
    /// leaves out (no ray there can prove it). True when the mask holds
    /// every point: then no lattice ray can prove it. Only boxes of at
    /// most [`MOST_BOX_POINTS`] points are asked.
    fn mask_lattice(
        &mut self,
        run: &[TraceTriangle],
        projected: &[Option<ProjectedPolygon>],
        density: u32,
    ) -> bool {
        let Some((hidden, nearest)) = self.hidden_at_least_depth(run) else {
            return false;
        };
        let d = f64::from(density);
        let projected = projected.iter().map(|p| match p.as_deref() {
            Some(&[a, b, c]) => Some([a, b, c].map(|(x, y, _)| (x, y))),
            _ => None,
        });
        let Some((lo, hi)) = footprint_box(projected, 1.0 / d) else {
            return false;
        };
        // Lattice point i lies at (i + 0.5) / d.
        let index = |x: f64, round: fn(f64) -> f64| round(x * d - 0.5);
        let (i0, i1) = (index(lo.0, f64::ceil), index(hi.0, f64::floor));
        let (j0, j1) = (index(lo.1, f64::ceil), index(hi.1, f64::floor));
        let (ni, nj) = (i1 - i0 + 1.0, j1 - j0 + 1.0);
        if density == 0 || ni < 1.0 || nj < 1.0 || ni * nj > MOST_BOX_POINTS {
            return false;
        }
        if hidden.occluders.is_empty() {
            return false;
        }
        let block = LatticeBlock {
            i0: i0 as i64,
            j0: j0 as i64,
            ni: ni as i64,
            nj: nj as i64,
            density,
        };
        let alpha_tested = hidden.alpha_tested;
        let occlusion = hidden.occlusion;
        let mask = Mask {
            block,
            hidden: occlusion.hidden_block(block, nearest, alpha_tested, &hidden.images()),
        };
        let all = mask.hidden.iter().all(|&h| h);
        hidden.mask = Some(mask);
        all
    }

    /// `points` (a whole cell's, texel units, each with the caster's
    /// nearest depth there) less those the caster's occluders so far
    /// surely hide.
    fn unhidden(&mut self, mut points: Vec<(Point, f64)>) -> Vec<(Point, f64)> {
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
    fn front_passes(&self, hits: &[RayHit]) -> u8 {
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
    fn trace(&mut self, ray: &TexelRay) -> (bool, u8) {
        self.traced += 1;
        let mut proven = false;
        let (caster, useful) = (self.caster, &mut *self.useful);
        self.rays.trace(ray, self.hits, |c| {
            proven |= c == caster;
            useful.insert(c);
        });
        (proven, self.front_passes(self.hits))
    }
}

/// Surface points traced before the others: once they prove the caster,
/// the others are deferred. On `bench` (one thread, five alternating
/// rounds) 1 and 2 were alike and 4 and 8 slower.
const FIRST_POINTS: usize = 2;

/// The area-weighted surface points of `run` (the caster's triangles) that
/// may prove it, traced until one does; returns whether one did, and the
/// rays of the points deferred: those that cannot prove it (after a
/// proof, and before one those its occluders so far surely hide from it),
/// which may still prove others.
///
/// Every point is traced, even once one proves the caster: the others may
/// prove other casters, which their own rays can miss. (Tracing the first
/// 8 alone, and the rest only when they proved nothing, saved 5 % of a
/// refined bake on `bench` but left 3 casters of `village` culled at ×¼
/// that the ×8 reference keeps; leaving out the points occluders hide lost
/// one of `bench`'s.) The deferred ones go after the caster's chunk of
/// candidates, only where they may meet a caster not proven by then
/// ([`Sampler::trace_batch_for_others`]).
fn surface_points(
    sampler: &mut Sampler<'_, '_>,
    run: &[TraceTriangle],
    light: usize,
    samples: u32,
) -> (bool, Vec<TexelRay>) {
    // The running sums of the triangles' areas, so a pick is a binary
    // search, not a walk of every triangle (a tree's canopy has hundreds).
    let running = running_sums(run.iter().map(area));
    let total = running.last().copied().unwrap_or(0.0);
    if samples == 0 || run.is_empty() || total.is_nan() || total <= 0.0 {
        return (false, Vec::new());
    }
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let mut rng = Rng::new(mix(((light as u64) << 32) | sampler.caster as u64));
    let mut points = Vec::with_capacity(samples as usize);
    let mut at = Vec::with_capacity(samples as usize);
    for _ in 0..samples {
        let chosen = pick_triangle(&running, rng.unit() * total);
        let p = reference + sample_point(&run[chosen], &mut rng);
        if let Some(ray) = grid.ray_toward(p) {
            points.push(ray);
            at.push(p);
        }
    }
    let first = points.len().min(FIRST_POINTS);
    if sampler.trace_surface_points(&points[..first]) {
        points.drain(..first);
        return (true, points);
    }
    let (open, mut deferred) = sampler.split_hidden(&points[first..], &at[first..], run);
    for (k, batch) in open.chunks(BATCH).enumerate() {
        if sampler.trace_surface_points(batch) {
            deferred.extend_from_slice(&open[k * BATCH + batch.len()..]);
            return (true, deferred);
        }
    }
    (false, deferred)
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

/// The box (texel units) of every point the lattice may take as on the
/// footprint of `triangles` (projected on a directional light's face;
/// `None`: a corner not finite): their box grown by `grow`, which holds
/// each triangle grown by [`TOUCH`] (as [`ConvexRegion`] grows it, with
/// its box's slack for rounding) when no corner is so sharp that the
/// grown triangle reaches further than half of it (`TOUCH /
/// sin(angle / 2)`); `None` then, or for a corner not finite.
fn footprint_box(
    triangles: impl Iterator<Item = Option<[Point; 3]>>,
    grow: f64,
) -> Option<(Point, Point)> {
    let (mut lo, mut hi) = (
        (f64::INFINITY, f64::INFINITY),
        (f64::NEG_INFINITY, f64::NEG_INFINITY),
    );
    for triangle in triangles {
        let [a, b, c] = triangle?;
        for v in [a, b, c] {
            if !(v.0.is_finite() && v.1.is_finite()) {
                return None;
            }
            lo = (lo.0.min(v.0), lo.1.min(v.1));
            hi = (hi.0.max(v.0), hi.1.max(v.1));
        }
        // sin(angle) at a corner is 2·area over the product of its sides'
        // lengths, and sin(angle / 2) ≥ sin(angle) / 2. (A triangle without
        // area has no least angle to go by: `ConvexRegion` still makes a
        // region of it, unbounded.)
        let area2 = ((b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)).abs();
        let side = |p: Point, q: Point| ((q.0 - p.0).powi(2) + (q.1 - p.1).powi(2)).sqrt();
        let (ab, bc, ca) = (side(a, b), side(b, c), side(c, a));
        let longest_pair = (ab * ca).max(ab * bc).max(bc * ca);
        let least_half_sine = area2 / longest_pair / 2.0;
        // Half of `grow` for the reach, half for the region box's slack.
        // (NaN, from a side of length 0, gives up too.)
        if least_half_sine.is_nan() || least_half_sine * grow < 2.0 * TOUCH {
            return None;
        }
    }
    (lo.0 <= hi.0 && lo.1 <= hi.1)
        .then_some(((lo.0 - grow, lo.1 - grow), (hi.0 + grow, hi.1 + grow)))
}

/// Most lattice points in the box of a caster's footprint for which
/// [`Sampler::mask_lattice`] is asked (a big caster is seldom
/// hidden whole; on `bench` 4 096, 16 384 and 65 536 were alike).
const MOST_BOX_POINTS: f64 = 4096.0;

/// Texels per side of the footprint's first cells.
const TOP_CELL: u32 = 4;
/// How near (texel units) a lattice point or cell must be to a footprint
/// polygon or edge to count as touching it: rays exactly on an edge may
/// hit under the tie rule.
const TOUCH: f64 = 1e-6;

/// One face's view of a caster: its hittable triangles projected, and the
/// edges of their union (`None`: a directional light, or some edge reaches
/// behind the face's plane: every cell is treated as crossed).
struct Footprint {
    face: usize,
    /// Whole-lattice mode under occlusion tests: `Occlusion::margin`, and
    /// per polygon its box grown by it and its depth plane (`None`: it has
    /// none, the caster counts as nearest everywhere near it).
    margin: f64,
    planes: Vec<(Rect, Option<Affine>)>,
    polygons: Vec<FacePolygon>,
    /// `polygons` grown by [`TOUCH`], for the lattice points' tests.
    regions: Vec<Option<ConvexRegion>>,
    outline: Option<Vec<(Point, Point)>>,
    density: u32,
}

/// The footprint lattice of the caster on every face of the light.
fn footprint_lattice(sampler: &mut Sampler<'_, '_>, run: &[TraceTriangle], config: &BakeConfig) {
    let density = config.refine_density;
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let caster = &sampler.rays.casters.casters[sampler.caster as usize];
    let is_hittable =
        |t: &TraceTriangle| hittable(t, grid.direction(), caster.double_sided, config);
    // A model under a directional light traces the whole lattice (no
    // outline, every cell crossed); terrain blocks and perspective lights,
    // whose footprints can be as large as the world, probe cells inside the
    // outline.
    let outline = match grid.direction() {
        Some(_) if !caster.is_terrain() => None,
        direction => Some(outline_edges(run, direction, caster.double_sided, config)),
    };
    let margin = sampler.hidden.as_ref().map(|h| h.occlusion.margin());
    for face in 0..grid.faces() {
        // Every triangle, once: the box of all for the occlusion test, the
        // hittable ones for the lattice.
        let projected: Vec<Option<ProjectedPolygon>> = run
            .iter()
            .map(|t| {
                grid.project_triangle_with_depth(face, t.vertices.map(|v| reference + v.as_dvec3()))
            })
            .collect();
        if face == 0 && sampler.mask_lattice(run, &projected, density) {
            return;
        }
        // A polygon the mask hides whole is left out before its setup.
        let mask = sampler.mask();
        let reach = margin.unwrap_or(0.0).max(1.0 / f64::from(density));
        let masked = |p: &ProjectedPolygon| mask.is_some_and(|m| m.holds_polygon(p, reach));
        let projected: Vec<&ProjectedPolygon> = projected
            .iter()
            .zip(run)
            .filter_map(|(p, t)| p.as_ref().filter(|p| is_hittable(t) && !masked(p)))
            .collect();
        if !projected
            .iter()
            .any(|p| near_face(grid, p, margin, density))
        {
            // No top cell of this face is near it: nothing to trace here.
            continue;
        }
        let planes = match margin.filter(|_| outline.is_none()) {
            None => Vec::new(),
            Some(margin) => projected.iter().map(|p| depth_plane(p, margin)).collect(),
        };
        let polygons: Vec<FacePolygon> = projected.iter().map(|p| p.flat()).collect();
        let outline = outline.as_ref().and_then(|edges| {
            edges
                .iter()
                .map(|&(a, b)| {
                    Some((
                        grid.project_point(face, reference + a)?,
                        grid.project_point(face, reference + b)?,
                    ))
                })
                .collect::<Option<Vec<_>>>()
        });
        let footprint = Footprint {
            face,
            margin: margin.unwrap_or(0.0),
            planes,
            regions: polygons
                .iter()
                .map(|p| ConvexRegion::new(p, TOUCH))
                .collect(),
            polygons,
            outline,
            density,
        };
        if footprint.sample(sampler) {
            return;
        }
    }
}

/// Whether polygon `p` (projected on a face of `grid`) may lie near a top
/// cell of the face ([`Footprint::sample`] bins it only there): its box,
/// grown by the depth `margin` (if any), by two lattice points and by a top
/// cell (the face's last top cell may reach past its edge), meets the
/// face. A perspective light's caster often shows on one or two of six.
fn near_face(grid: &TexelGrid, p: &ProjectedPolygon, margin: Option<f64>, density: u32) -> bool {
    let slack = margin.unwrap_or(0.0) + 2.0 / f64::from(density.max(1)) + f64::from(TOP_CELL);
    let (lo, hi) = bounds(p.iter().map(|&(x, y, _)| (x, y)));
    let (width, height) = (f64::from(grid.width()), f64::from(grid.height()));
    hi.0 > -slack && hi.1 > -slack && lo.0 < width + slack && lo.1 < height + slack
}

/// A projected triangle's box grown by `margin` and the plane of its
/// depths (a directional light's: t plus a constant), if it has one.
fn depth_plane(projected: &[(f64, f64, f64)], margin: f64) -> (Rect, Option<Affine>) {
    let rect = Rect::around(projected.iter().map(|&(x, y, _)| (x, y))).grown(margin);
    let plane = match projected {
        [a, b, c] => Affine::through([*a, *b, *c]),
        _ => None,
    };
    (rect, plane)
}

/// Whether rays of the light can hit triangle `t` under the face-culling
/// rule: a directional light's rays share one direction, so a culled face
/// is culled for all of them; a perspective light's may see either side.
fn hittable(
    t: &TraceTriangle,
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> bool {
    let Some(direction) = direction else {
        return true;
    };
    let [a, b, c] = t.vertices.map(|v| v.as_dvec3());
    let back = (b - a).cross(c - a).dot(direction) > 0.0;
    double_sided
        || match config.face_culling {
            FaceCulling::Back => !back,
            FaceCulling::Front => back,
            FaceCulling::None => true,
        }
}

/// The edges (light-relative) of the union of the caster's hittable
/// triangles: edges that exactly one hittable triangle uses.
fn outline_edges(
    run: &[TraceTriangle],
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> Vec<(DVec3, DVec3)> {
    let bits = |v: glam::Vec3| v.to_array().map(f32::to_bits);
    // Every edge of every hittable triangle, keyed by its vertices' bits
    // (ordered: the six words packed in order into three), its uses
    // counted in an open-addressing table (on `bench`, all lights, one
    // thread: 15.2 ms sorting the keys, 4.2 ms so): an edge used
    // once is on the outline. Edges are kept in the order first met (the
    // triangles'), so fixed: the work is the same run to run.
    type Key = (u64, u64, u64);
    let pack = |[a, b, c]: [u32; 3], [d, e, f]: [u32; 3]| -> Key {
        let word = |hi: u32, lo: u32| (u64::from(hi) << 32) | u64::from(lo);
        (word(a, b), word(c, d), word(e, f))
    };
    let slot_bits = (6 * run.len()).max(16).next_power_of_two().trailing_zeros();
    let slot_of = |(x, y, z): Key| {
        let mix = |h: u64, word: u64| {
            let h = (h ^ word).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            h ^ (h >> 29)
        };
        (mix(mix(mix(0, x), y), z) >> (64 - slot_bits)) as usize
    };
    let mut slots: Vec<u32> = vec![u32::MAX; 1 << slot_bits];
    let mut edges: Vec<(Key, u32, (glam::Vec3, glam::Vec3))> = Vec::new();
    for t in run
        .iter()
        .filter(|t| hittable(t, direction, double_sided, config))
    {
        for i in 0..3 {
            let (a, b) = (t.vertices[i], t.vertices[(i + 1) % 3]);
            let (ka, kb) = (bits(a), bits(b));
            let key = if ka <= kb { pack(ka, kb) } else { pack(kb, ka) };
            let mut at = slot_of(key);
            loop {
                match slots[at] {
                    u32::MAX => {
                        slots[at] = edges.len() as u32;
                        edges.push((key, 1, (a, b)));
                        break;
                    }
                    k if edges[k as usize].0 == key => {
                        edges[k as usize].1 += 1;
                        break;
                    }
                    _ => at = (at + 1) & (slots.len() - 1),
                }
            }
        }
    }
    edges
        .into_iter()
        .filter(|&(_, uses, _)| uses == 1)
        .map(|(_, _, (a, b))| (a.as_dvec3(), b.as_dvec3()))
        .collect()
}

/// A top cell's lattice in whole-lattice mode ([`Footprint::fill_lattice`]):
/// per point, row by row, whether it lies on the footprint and the
/// caster's nearest depth there (`-∞` where a polygon without a plane may
/// be hit, or without planes at all; `+∞` where none may). Reused from cell
/// to cell.
#[derive(Default)]
struct LatticeCell {
    cell: (i64, i64, i64, i64),
    on: Vec<bool>,
    near: Vec<f64>,
}

impl LatticeCell {
    fn index(&self, i: i64, j: i64) -> usize {
        let (i0, j0, ni, _) = self.cell;
        ((j - j0) * ni + (i - i0)) as usize
    }
}

/// Outline cells traced at once per thread ([`Footprint::outline_cells`]):
/// enough to share out, few to trace in vain past the cell that proves
/// the caster.
const OUTLINE_WAVE: usize = 4;

/// A probed lattice point and the passes whose front set holds the caster
/// there ([`Footprint::probe`]).
type Probed = ((i64, i64), u8);

/// A small cell of lattice points the outline crosses, and the polygons
/// (indices) near it.
type OutlineCell = ((i64, i64, i64, i64), Vec<u32>);

/// A polygon or outline edge (index) near a top cell (row, column).
type Binned = ((i64, i64), u32);

/// The top cells that polygons are near, in order (row by row), each with
/// the polygons and the outline edges near it (indices, in order), from
/// lists of [`Binned`] sorted.
struct Bins<'b> {
    polygons: &'b [Binned],
    edges: &'b [Binned],
}

impl Iterator for Bins<'_> {
    type Item = ((i64, i64), Vec<u32>, Vec<u32>);

    fn next(&mut self) -> Option<Self::Item> {
        let &(cell, _) = self.polygons.first()?;
        let take = |list: &mut &[Binned]| {
            // Those of cells before this one (edges of cells without
            // polygons) are skipped.
            let skip = list.partition_point(|&(c, _)| c < cell);
            let near = list[skip..].partition_point(|&(c, _)| c == cell);
            let indices = list[skip..skip + near].iter().map(|&(_, i)| i).collect();
            *list = &list[skip + near..];
            indices
        };
        let polygons = take(&mut self.polygons);
        Some((cell, polygons, take(&mut self.edges)))
    }
}

/// The polygons and outline edges (indices) near one cell.
struct Near<'f> {
    polygons: &'f [u32],
    edges: &'f [u32],
}

impl Footprint {
    /// Lattice point `(i, j)` in texel units: the centre of that texel of
    /// the grid `density` times denser.
    #[inline]
    fn point(&self, i: i64, j: i64) -> Point {
        let d = self.density as f64;
        ((i as f64 + 0.5) / d, (j as f64 + 0.5) / d)
    }

    /// Whether lattice point `p` lies on polygon `index` (within [`TOUCH`]).
    #[inline]
    fn touches(&self, index: u32, p: Point) -> bool {
        self.regions[index as usize]
            .as_ref()
            .is_some_and(|region| region.contains(p))
    }

    /// Samples the footprint cell by cell; true once the caster is proven
    /// useful.
    fn sample(&self, sampler: &mut Sampler<'_, '_>) -> bool {
        let grid = sampler.rays.grid;
        let d = self.density as i64;
        let (width, height) = (grid.width() as i64 * d, grid.height() as i64 * d);
        let top = TOP_CELL as i64 * d;
        let (cells_x, cells_y) = ((width + top - 1) / top, (height + top - 1) / top);
        // Top cells a box (texel units) may touch, clipped to the face.
        let span = |lo: f64, hi: f64, cells: i64| {
            let first = ((lo * d as f64 - 1.0) / top as f64)
                .floor()
                .clamp(0.0, cells as f64) as i64;
            let last = ((hi * d as f64 + 1.0) / top as f64)
                .ceil()
                .clamp(0.0, cells as f64) as i64;
            first..last
        };
        // (top cell, index) of every polygon and outline edge near a top
        // cell, sorted by cell (row by row), then index.
        let mut polygon_bins: Vec<Binned> = Vec::new();
        for (index, polygon) in self.polygons.iter().enumerate() {
            // Grown by the depth margin: a cell's list must hold every
            // polygon whose depth may count at its points.
            let (lo, hi) = bounds(polygon.iter().copied());
            let (lo, hi) = (
                (lo.0 - self.margin, lo.1 - self.margin),
                (hi.0 + self.margin, hi.1 + self.margin),
            );
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    polygon_bins.push(((cy, cx), index as u32));
                }
            }
        }
        polygon_bins.sort_unstable();
        let mut edge_bins: Vec<Binned> = Vec::new();
        for (index, &(a, b)) in self.outline.iter().flatten().enumerate() {
            let (lo, hi) = bounds([a, b]);
            for cy in span(lo.1, hi.1, cells_y) {
                for cx in span(lo.0, hi.0, cells_x) {
                    edge_bins.push(((cy, cx), index as u32));
                }
            }
        }
        edge_bins.sort_unstable();
        let bins = Bins {
            polygons: &polygon_bins,
            edges: &edge_bins,
        };
        let mut lattice = LatticeCell::default();
        let mut outline_cells = Vec::new();
        for ((cy, cx), polygons, edges) in bins {
            let (i0, j0) = (cx * top, cy * top);
            let cell = (i0, j0, top.min(width - i0), top.min(height - j0));
            if cell.2 <= 0 || cell.3 <= 0 {
                continue;
            }
            let proven = match self.outline {
                // Every point here that may be on the footprint is surely
                // hidden.
                None if sampler.mask().is_some_and(|m| m.holds_cell(cell)) => false,
                None => {
                    self.fill_lattice(&polygons, cell, &mut lattice);
                    self.lattice_batches(sampler, &lattice, cell)
                }
                Some(_) => {
                    let near = &Near {
                        polygons: &polygons,
                        edges: &edges,
                    };
                    self.cell(sampler, near, cell, &[], &mut outline_cells)
                }
            };
            if proven {
                return true;
            }
        }
        self.outline_cells(sampler, &outline_cells)
    }

    /// [`Self::outline_cell`] of each of `cells` in order until one proves
    /// the caster, a wave of cells at a time traced in parallel: a large
    /// caster's outline (a spot light's wall: 495 cells, 70 % of that
    /// light's refinement on `bench`) would leave the other threads idle.
    /// In outline mode a cell's rays and answer do not depend on the
    /// cells before it, and only the cells up to the first that proves
    /// the caster count (their proofs and rays), so the answer and the
    /// rays counted are the walk's one cell at a time, whatever the
    /// threads.
    fn outline_cells(&self, sampler: &mut Sampler<'_, '_>, cells: &[OutlineCell]) -> bool {
        debug_assert!(
            cells.is_empty() || sampler.hidden.is_none(),
            "no occlusion test in outline mode"
        );
        let (rays, caster) = (sampler.rays, sampler.caster);
        let wave = OUTLINE_WAVE * rayon::current_num_threads();
        for cells in cells.chunks(wave) {
            let outcomes: Vec<(bool, Vec<u32>, usize)> = cells
                .par_iter()
                .map_init(PacketState::default, |packet, (cell, polygons)| {
                    packet.rays.clear();
                    packet
                        .rays
                        .extend(self.outline_rays(rays.grid, polygons, *cell));
                    let (mut proven, mut found) = (false, Vec::new());
                    rays.trace_packet(packet, |c| {
                        proven |= c == caster;
                        found.push(c);
                    });
                    (proven, found, packet.rays.len())
                })
                .collect();
            for (proven, found, traced) in outcomes {
                for c in found {
                    sampler.useful.insert(c);
                }
                sampler.traced += traced as u64;
                if proven {
                    return true;
                }
            }
        }
        false
    }

    /// Whole-lattice mode (no outline): which lattice points of a top
    /// `cell` lie on one of `polygons` (the cell's bin), and the caster's
    /// nearest depth at each, worked out once for the cell; its batches
    /// read them.
    fn fill_lattice(
        &self,
        polygons: &[u32],
        cell: (i64, i64, i64, i64),
        lattice: &mut LatticeCell,
    ) {
        let (i0, j0, ni, nj) = cell;
        // The cell's points a box may hold (rounded outward; every point
        // in the range is tested).
        let block = LatticeBlock {
            i0,
            j0,
            ni,
            nj,
            density: self.density,
        };
        lattice.cell = cell;
        lattice.on.clear();
        lattice.on.resize((ni * nj) as usize, false);
        // Without planes nothing is hidden: every point counts as nearest.
        let unknown = if self.planes.is_empty() {
            f64::NEG_INFINITY
        } else {
            f64::INFINITY
        };
        lattice.near.clear();
        lattice.near.resize((ni * nj) as usize, unknown);
        for &k in polygons {
            let region = &self.regions[k as usize];
            let Some((b, plane)) = self.planes.get(k as usize) else {
                // No depths: only whether points lie on it.
                let Some(region) = region else { continue };
                let b = region.bounds();
                for j in block.rows(b.y0, b.y1) {
                    for i in block.columns(b.x0, b.x1) {
                        let at = lattice.index(i, j);
                        lattice.on[at] |= region.contains(self.point(i, j));
                    }
                }
                continue;
            };
            // One walk of both boxes: the points on the polygon (within
            // [`TOUCH`]), and the points within the depth margin of it (in
            // its box grown by the margin and within the margin of every
            // edge's line), whose depth counts wherever some polygon puts
            // them on the footprint (`near` is read only there).
            let walk = region.as_ref().map_or(*b, |r| b.union(r.bounds()));
            for j in block.rows(walk.y0, walk.y1) {
                for i in block.columns(walk.x0, walk.x1) {
                    let (p, at) = (self.point(i, j), lattice.index(i, j));
                    let on = region.as_ref().is_some_and(|r| r.contains(p));
                    lattice.on[at] |= on;
                    let outside = p.0 < b.x0 || p.0 > b.x1 || p.1 < b.y0 || p.1 > b.y1;
                    // A point on the polygon is within the margin of it.
                    let near_it = on
                        || region
                            .as_ref()
                            .is_none_or(|r| r.contains_grown(p, self.margin));
                    if outside || !near_it {
                        continue;
                    }
                    let depth = plane.map_or(f64::NEG_INFINITY, |plane| plane.at(p));
                    let near = &mut lattice.near[at];
                    *near = near.min(if depth.is_nan() {
                        f64::NEG_INFINITY
                    } else {
                        depth
                    });
                }
            }
        }
    }

    /// The batches of a top cell in whole-lattice mode: quartered down to
    /// at most [`BATCH`] lattice points, each traced by
    /// [`Self::whole_cell`]; true once one proves the caster useful.
    fn lattice_batches(
        &self,
        sampler: &mut Sampler<'_, '_>,
        lattice: &LatticeCell,
        (i0, j0, ni, nj): (i64, i64, i64, i64),
    ) -> bool {
        if ni * nj <= BATCH as i64 {
            return self.whole_cell(sampler, lattice, (i0, j0, ni, nj));
        }
        quarters((i0, j0, ni, nj)).any(|quarter| self.lattice_batches(sampler, lattice, quarter))
    }

    /// Every lattice point of a small cell (within the top cell
    /// `lattice`) on the footprint, traced as one batch (whole-lattice
    /// mode: a model under a directional light, whose lattice rays are
    /// parallel and a fraction of a texel apart); true if any proves the
    /// caster useful.
    fn whole_cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        lattice: &LatticeCell,
        (i0, j0, ni, nj): (i64, i64, i64, i64),
    ) -> bool {
        let mut points: Vec<(Point, f64)> = Vec::new();
        let mask = sampler.mask();
        let masked = |i: i64, j: i64| mask.is_some_and(|m| m.holds(i, j));
        for j in j0..j0 + nj {
            for i in i0..i0 + ni {
                let at = lattice.index(i, j);
                if lattice.on[at] && !masked(i, j) {
                    points.push((self.point(i, j), lattice.near[at]));
                }
            }
        }
        let ray = |(p, _): (Point, f64)| sampler.rays.grid.ray_through(self.face, p.0, p.1);
        if sampler.hidden.is_some() && points.len() > FEW_POINTS {
            // The points the occluders met so far surely hide need no ray,
            // nor a probe: often they are all of them.
            points = sampler.unhidden(points);
            if points.is_empty() {
                return false;
            }
            // A probe: the middle point alone, for the casters in front of
            // the caster here.
            let probe = points.remove(points.len() / 2);
            if sampler.trace(&ray(probe)).0 {
                return true;
            }
            let (caster, casters) = (sampler.caster, sampler.rays.casters);
            let met_new = sampler
                .hidden
                .as_mut()
                .is_some_and(|hidden| hidden.note(caster, casters, sampler.hits.iter()));
            // Else the rest were tested against these occluders already.
            if met_new && points.len() > FEW_POINTS {
                points = sampler.unhidden(points);
            }
        }
        let batch: Vec<TexelRay> = points.into_iter().map(ray).collect();
        sampler.trace_batch(&batch)
    }

    /// The rays of an outline cell: every lattice point of a small cell the
    /// outline crosses that lies on one of `polygons` (those near it),
    /// traced as one batch: the points a quartering down to single points
    /// would trace (and the corners it would probe inside the footprint),
    /// as one packet of a fraction of a texel instead of single rays.
    fn outline_rays<'g>(
        &'g self,
        grid: &'g TexelGrid,
        polygons: &'g [u32],
        (i0, j0, ni, nj): (i64, i64, i64, i64),
    ) -> impl Iterator<Item = TexelRay> + 'g {
        (j0..j0 + nj)
            .flat_map(move |j| (i0..i0 + ni).map(move |i| self.point(i, j)))
            .filter(|&p| polygons.iter().any(|&k| self.touches(k, p)))
            .map(|p| grid.ray_through(self.face, p.0, p.1))
    }

    /// Lattice points `i0..i0+ni × j0..j0+nj` of an outlined footprint
    /// (terrain blocks, perspective lights), but for the small cells the
    /// outline crosses: those are added to `outline_cells` (with the
    /// polygons near each) for [`Self::outline_cell`] after the inside
    /// (a caster is proven there more often, and sooner: on `bench` the
    /// sun's terrain blocks all were, inside cells whose probes disagree);
    /// true once proven useful.
    fn cell(
        &self,
        sampler: &mut Sampler<'_, '_>,
        near: &Near<'_>,
        (i0, j0, ni, nj): (i64, i64, i64, i64),
        probed: &[Probed],
        outline_cells: &mut Vec<OutlineCell>,
    ) -> bool {
        let d = self.density as f64;
        let rect = Rect {
            x0: i0 as f64 / d,
            y0: j0 as f64 / d,
            x1: (i0 + ni) as f64 / d,
            y1: (j0 + nj) as f64 / d,
        };
        let point = |i: i64, j: i64| self.point(i, j);
        let grid = sampler.rays.grid;
        if ni == 1 && nj == 1 {
            // A corner of the cell it was split from (whose probe proved
            // nothing): the same ray would again.
            if probed.iter().any(|&(at, _)| at == (i0, j0)) {
                return false;
            }
            let p = point(i0, j0);
            let inside = near.polygons.iter().any(|&i| self.touches(i, p));
            return inside && sampler.trace(&grid.ray_through(self.face, p.0, p.1)).0;
        }
        // What meets this cell, handed down so smaller cells test less.
        let grown = rect.grown(TOUCH);
        let polygons: Vec<u32> = near
            .polygons
            .iter()
            .copied()
            .filter(|&i| beam::overlaps_rect(&self.polygons[i as usize], grown))
            .collect();
        if polygons.is_empty() {
            return false;
        }
        let all = self.outline.as_deref().unwrap_or_default();
        let edges: Vec<u32> = near
            .edges
            .iter()
            .copied()
            .filter(|&e| {
                let (a, b) = all[e as usize];
                beam::segment_meets_rect(a, b, grown)
            })
            .collect();
        let crossed = !edges.is_empty();
        let near = &Near {
            polygons: &polygons,
            edges: &edges,
        };
        if crossed && ni * nj <= BATCH as i64 {
            outline_cells.push(((i0, j0, ni, nj), polygons));
            return false;
        }
        let mut corners: [Probed; 4] = Default::default();
        if !crossed {
            let last = (i0 + ni - 1, j0 + nj - 1);
            let at = [(i0, j0), (last.0, j0), (i0, last.1), last];
            let (proven, fronts) = self.probe(sampler, at, probed);
            if proven {
                return true;
            }
            if fronts.iter().all(|&f| f == fronts[0]) {
                return false;
            }
            corners = [0, 1, 2, 3].map(|k| (at[k], fronts[k]));
        }
        // A crossed cell probed nothing.
        let probed = if crossed { &[][..] } else { &corners[..] };
        quarters((i0, j0, ni, nj))
            .any(|quarter| self.cell(sampler, near, quarter, probed, outline_cells))
    }

    /// The probes of a cell: per corner (`at`, lattice points), the passes
    /// whose front set holds the caster ([`Sampler::front_passes`]), and
    /// whether one proves it useful. A corner already `probed` (one of the
    /// corners of the cell this one was split from, which proved nothing)
    /// is not traced again, nor is a corner twice (a cell one point wide):
    /// the same ray gives the same answer. The others go together.
    fn probe(
        &self,
        sampler: &mut Sampler<'_, '_>,
        at: [(i64, i64); 4],
        probed: &[Probed],
    ) -> (bool, [u8; 4]) {
        let grid = sampler.rays.grid;
        let mut fronts = [0u8; 4];
        // The corners to trace (index into `at`), each point once.
        let mut fresh: Vec<usize> = Vec::with_capacity(4);
        for (k, &corner) in at.iter().enumerate() {
            if let Some(&(_, front)) = probed.iter().find(|&&(p, _)| p == corner) {
                fronts[k] = front;
            } else if !fresh.iter().any(|&f| at[f] == corner) {
                fresh.push(k);
            }
        }
        let rays: Vec<TexelRay> = fresh
            .iter()
            .map(|&k| {
                let p = self.point(at[k].0, at[k].1);
                grid.ray_through(self.face, p.0, p.1)
            })
            .collect();
        let proven = sampler.trace_batch(&rays);
        for (&k, hits) in fresh.iter().zip(sampler.packet.hits(rays.len())) {
            fronts[k] = sampler.front_passes(hits);
        }
        // A corner met twice takes its first's answer.
        for k in 0..4 {
            if let Some(&first) = fresh.iter().find(|&&f| at[f] == at[k]) {
                fronts[k] = fronts[first];
            }
        }
        (proven, fronts)
    }
}

/// The non-empty quarters of a cell `(i0, j0, ni, nj)` of lattice points,
/// in the order cells are visited (the first ones the larger).
fn quarters((i0, j0, ni, nj): (i64, i64, i64, i64)) -> impl Iterator<Item = (i64, i64, i64, i64)> {
    let (hi, hj) = ((ni + 1) / 2, (nj + 1) / 2);
    [
        (i0, j0, hi, hj),
        (i0 + hi, j0, ni - hi, hj),
        (i0, j0 + hj, hi, nj - hj),
        (i0 + hi, j0 + hj, ni - hi, nj - hj),
    ]
    .into_iter()
    .filter(|&(_, _, na, nb)| na > 0 && nb > 0)
}

/// The triangle an area-weighted `pick` in `[0, total)` falls on, from
/// the running sums of the areas: the first whose sum exceeds it (the last
/// when none does, as for a NaN pick).
fn pick_triangle(running: &[f64], pick: f64) -> usize {
    running
        .partition_point(|&s| pick.partial_cmp(&s) != Some(std::cmp::Ordering::Less))
        .min(running.len().saturating_sub(1))
}

/// Each value's sum with those before it, added in order.
fn running_sums(values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut sum = 0.0;
    values
        .map(|v| {
            sum += v;
            sum
        })
        .collect()
}

fn area(triangle: &TraceTriangle) -> f64 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    0.5 * (b - a).cross(c - a).length()
}

/// A uniform point of the triangle (light-relative), away from its edges.
fn sample_point(triangle: &TraceTriangle, rng: &mut Rng) -> DVec3 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    let squeeze = |r: f64| EDGE_MARGIN + (1.0 - 2.0 * EDGE_MARGIN) * r;
    let (r1, r2) = (squeeze(rng.unit()).sqrt(), squeeze(rng.unit()));
    a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `footprint_box` holds the box of each triangle's region grown by
    /// [`TOUCH`] (which holds every point the region accepts) whenever it
    /// answers, over seeded random triangles from fat ones to needles, and
    /// from 5 texels to a ten-thousandth, far from the origin; and it
    /// answers for all but the sharpest.
    #[test]
    fn the_footprint_box_holds_every_region_it_answers_for() {
        let mut rng = Rng::new(17);
        let (mut answered, mut refused) = (0, 0);
        for k in 0..2000 {
            let a = ((rng.unit() - 0.5) * 2e4, (rng.unit() - 0.5) * 2e4);
            // The corner at `a`: from 1 rad down to 1e-9 rad.
            let angle = 10f64.powf(-9.0 * rng.unit());
            // Sides from 0.1 mm to 5 texels.
            let (side, other) = (10f64.powf(-4.0 + 4.7 * rng.unit()), 0.2 + rng.unit());
            let turn = rng.unit() * std::f64::consts::TAU;
            let b = (a.0 + side * turn.cos(), a.1 + side * turn.sin());
            let far = side * other;
            let c = (
                a.0 + far * (turn + angle).cos(),
                a.1 + far * (turn + angle).sin(),
            );
            let triangle = [a, b, c];
            let Some((lo, hi)) = footprint_box(std::iter::once(Some(triangle)), 1.0 / 8.0) else {
                refused += 1;
                continue;
            };
            answered += 1;
            if let Some(region) = ConvexRegion::new(&triangle, TOUCH) {
                let r = region.bounds();
                assert!(
                    r.x0 >= lo.0 && r.y0 >= lo.1 && r.x1 <= hi.0 && r.y1 <= hi.1,
                    "triangle {k} {triangle:?}: region {r:?} outside {lo:?}..{hi:?}"
                );
            }
        }
        assert!(
            answered > 400 && refused > 400,
            "{answered} answered, {refused} refused"
        );
    }

    /// `outline_edges` finds the edges exactly one hittable triangle uses,
    /// each once, as counting every edge against every other does: over
    /// seeded random height grids (shared vertices, as a terrain block's)
    /// with some triangles turned to face away from a sun straight down
    /// (not hittable, so holes with edges of their own), and loose
    /// triangles.
    #[test]
    fn the_outline_is_the_edges_one_hittable_triangle_uses() {
        use glam::Vec3;
        let config = BakeConfig::default();
        let down = Some(DVec3::new(0.0, -1.0, 0.0));
        let mut rng = Rng::new(41);
        for round in 0..60 {
            let n = 1 + rng.below(9);
            let height: Vec<f32> = (0..(n + 1) * (n + 1))
                .map(|_| rng.range(0.0, 3.0) as f32)
                .collect();
            let at = |i: usize, j: usize| Vec3::new(i as f32, height[j * (n + 1) + i], j as f32);
            let mut run = Vec::new();
            for j in 0..n {
                for i in 0..n {
                    let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                    for mut vertices in [[a, c, b], [a, d, c]] {
                        if rng.chance(0.2) {
                            vertices.swap(1, 2);
                        }
                        run.push(TraceTriangle {
                            vertices,
                            caster: 0,
                        });
                    }
                }
            }
            for _ in 0..round % 4 {
                let mut v = || {
                    Vec3::new(
                        rng.range(-5.0, 5.0) as f32,
                        0.0,
                        rng.range(-5.0, 5.0) as f32,
                    )
                };
                let vertices = [v(), v(), v()];
                run.push(TraceTriangle {
                    vertices,
                    caster: 0,
                });
            }
            let key = |a: Vec3, b: Vec3| {
                let (a, b) = (
                    a.to_array().map(f32::to_bits),
                    b.to_array().map(f32::to_bits),
                );
                if a <= b {
                    (a, b)
                } else {
                    (b, a)
                }
            };
            let kept: Vec<&TraceTriangle> = run
                .iter()
                .filter(|t| hittable(t, down, false, &config))
                .collect();
            let edges: Vec<(Vec3, Vec3)> = kept
                .iter()
                .flat_map(|t| (0..3).map(|i| (t.vertices[i], t.vertices[(i + 1) % 3])))
                .collect();
            let mut expected: Vec<_> = edges
                .iter()
                .filter(|&&(a, b)| {
                    edges
                        .iter()
                        .filter(|&&(c, d)| key(a, b) == key(c, d))
                        .count()
                        == 1
                })
                .map(|&(a, b)| key(a, b))
                .collect();
            let mut found: Vec<_> = outline_edges(&run, down, false, &config)
                .into_iter()
                .map(|(a, b)| key(a.as_vec3(), b.as_vec3()))
                .collect();
            expected.sort_unstable();
            found.sort_unstable();
            assert_eq!(found, expected, "round {round}");
            assert!(!found.is_empty() || kept.is_empty(), "round {round}");
        }
    }

    /// The walk `pick_triangle` replaced: the first triangle whose running
    /// sum exceeds the pick, else the last.
    fn pick_by_walk(areas: &[f64], pick: f64) -> usize {
        let mut sum = 0.0;
        for (i, a) in areas.iter().enumerate() {
            sum += a;
            if pick < sum {
                return i;
            }
        }
        areas.len() - 1
    }

    #[test]
    fn a_pick_falls_on_the_triangle_the_walk_over_areas_finds() {
        let mut rng = Rng::new(17);
        for round in 0..2000 {
            let n = 1 + rng.below(40);
            // Some zero areas (degenerate triangles), which no pick may land on
            // unless it is the last.
            let areas: Vec<f64> = (0..n)
                .map(|_| {
                    if rng.below(4) == 0 {
                        0.0
                    } else {
                        rng.range(0.0, 3.0)
                    }
                })
                .collect();
            let running = running_sums(areas.iter().copied());
            let sum = running[n - 1];
            let pick = match round % 50 {
                0 => f64::NAN,
                1 => sum,
                _ => rng.unit() * sum,
            };
            assert_eq!(
                pick_triangle(&running, pick),
                pick_by_walk(&areas, pick),
                "{areas:?} {pick}"
            );
        }
    }
}
