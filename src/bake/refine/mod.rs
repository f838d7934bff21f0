//! Refinement (`--refine`): after the texel grid, every caster not yet
//! useful for a light gets extra rays where it actually is. The grid
//! samples the light's view at texel centres, so a caster smaller than a
//! texel, or one that shows only in a sliver between centres, can be
//! missed.
//!
//! Two kinds of rays, both fixed before tracing and OR-ed (the outcome does
//! not depend on order or threads):
//! - area-weighted points of the caster's own surface (`refine_samples`
//!   per caster, deterministic per (light, caster); [`surface`]);
//! - its light-space footprint on the lattice of a grid `refine_density`
//!   times denser per side (the rays of that denser grid; [`footprint`]).
//!   The footprint is cut into cells; cells its hittable triangles miss
//!   are dropped whole and the caster's rays stop at the first that proves
//!   it useful. For a model under a directional light every lattice point
//!   on the footprint is traced, so at density 8 refinement finds every
//!   model caster the ×8 grid finds among those it refines (the footprint
//!   is bounded by the model's size over the texel size). Terrain blocks
//!   (as large as a chunk) and every caster of a spot or point light (a
//!   wall a metre from a point light fills most of a face: a million
//!   lattice points) are not bounded so: there a cell that the outline of
//!   the caster's union of hittable triangles ([`outline`]) does not cross
//!   is probed at its corners and split only where the probes disagree on
//!   whether the caster is front-most (in either pass); outline cells go
//!   down to at most [`sampler::BATCH`] lattice points, each of which on
//!   the footprint is then traced. Probing is a sample, which can miss a
//!   caster useful only inside a probed cell, so models, whose footprints
//!   are small, trace the whole lattice; for terrain the whole lattice
//!   would cost several plain bakes (see docs/performance.md).
//!
//! Whole-lattice cells leave out the lattice rays that cannot prove the
//! caster: the casters the caster's rays met so far are its occluders, a
//! point where they surely keep the caster out of the front set is not
//! traced (`bake::occlusion`), and each cell's middle point among the rest
//! is traced alone first (a probe, for more occluders). Most casters left
//! to refine lie under others (things under trees) and stay culled, so
//! most of their lattice rays could prove nothing. Before the lattice, the
//! occluders are asked once for every lattice point in the box of the
//! footprint, taking the caster's least depth anywhere (a
//! [`lattice::Mask`], found triangle by triangle:
//! `Occlusion::hidden_block`): when they hide all of them the lattice is
//! skipped whole, and else its polygons, top cells and points the mask
//! hides are left out before any work on them. A whole-lattice top cell
//! works out which of its points lie on the footprint, and the caster's
//! depth at each, once ([`lattice::TopCellPoints`]); its cells of at most
//! [`sampler::BATCH`] points read them.
//!
//! Surface points that cannot prove their caster (once it is proven, and
//! before that those its occluders surely hide from it) may still prove
//! others, so they are traced, but later and only where they may meet a
//! caster not yet proven. Candidates are refined in chunks (fixed by the
//! settings); a chunk's deferred points go after every caster of the chunk
//! has traced its own rays, gated by the casters proven so far: a set
//! fixed before they go, so which rays go does not depend on threads, and
//! smaller than the grid's proofs alone, so fewer rays go.
//!
//! Rays go as packets wherever they lie near each other (surface points,
//! a cell's corner probes, a small outline cell, a whole-lattice cell
//! after its probe): a packet gives each ray the answer it gets alone. A
//! terrain block's surface points, scattered over a chunk, go ray by ray.
//!
//! Threads share the casters out a few at a time, and a large caster's
//! outline cells a wave at a time; what is proven and every ray counted
//! are the same for any number of threads.
//!
//! This file is the driver: the candidates, their chunks, and the threads'
//! scratches. Each caster's rays go through its [`sampler::Sampler`].

mod footprint;
mod lattice;
mod outline;
mod sampler;
mod surface;

use super::config::BakeConfig;
use super::occlusion::Occlusion;
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays};
use crate::light::TexelRay;
use crate::progress::{Counter, Phase, Progress};
use footprint::footprint_lattice;
use rayon::prelude::*;
use sampler::{Known, Proven, Sampler, SamplerBuffers, BATCH};
use std::sync::Mutex;
use surface::surface_points;

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
    let scratches = Scratches::new(world.casters.len(), false);
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

/// What one caster's refinement rays prove (ids, ascending) and how many
/// rays they count: the unit the bake cache keeps.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OwnRefinement {
    pub proven: Vec<u32>,
    pub rays: u64,
}

/// [`refine`] of `casters` (candidates: neither useful after the grid nor
/// receiver-only), each on its own, for the bake cache: its own rays as
/// [`refine`] traces them, then its deferred surface points gated by
/// `known(caster)` (sorted lists: its cells' answers) and its own proofs
/// instead of by every caster proven so far. What a caster's own rays
/// prove, and the rays counted, do not depend on other casters in either
/// (its deferred points are counted whether left out or not, and which
/// are deferred its own rays decide); its deferred points prove, beyond
/// the gate, what they prove with any other gate that the bake's answer
/// holds, so the union over casters, with the grid's answer, is
/// [`refine`]'s. Each finished caster is counted on `counter`.
pub fn refine_each(
    world: &BakeWorld,
    setup: &LightSetup,
    rays_of_light: &LightRays<'_>,
    config: &BakeConfig,
    casters: &[u32],
    known: &(dyn Fn(u32) -> Vec<Vec<u32>> + Sync),
    counter: &Counter,
) -> Vec<OwnRefinement> {
    let occlusion = Occlusion::new(world, setup, rays_of_light, config);
    let scratches = Scratches::new(world.casters.len(), true);
    let samples = config.refine_samples;
    casters
        .par_iter()
        .with_max_len(MOST_CASTERS_A_TASK)
        .map(|&caster| {
            let run = setup.caster_triangles(world, caster);
            let is_terrain = world.casters.casters[caster as usize].is_terrain();
            let hidden = occlusion.as_ref().filter(|_| !is_terrain);
            let mut lists = known(caster);
            let refined = scratches.with(|scratch| {
                let mut sampler = scratch.sampler(rays_of_light, Known::Lists(&[]), caster, hidden);
                let (proven, deferred) = surface_points(&mut sampler, &run, setup.index, samples);
                if config.refine_density > 0 && !proven {
                    footprint_lattice(&mut sampler, &run, config);
                }
                let mut rays = sampler.traced;
                if !deferred.is_empty() {
                    lists.push(scratch.useful.logged());
                    let mut sampler =
                        scratch.sampler(rays_of_light, Known::Lists(&lists), caster, None);
                    for batch in deferred.chunks(BATCH) {
                        sampler.trace_batch_for_others(batch);
                    }
                    rays += sampler.traced;
                }
                OwnRefinement {
                    proven: scratch.useful.take_logged(),
                    rays,
                }
            });
            counter.add(1);
            refined
        })
        .collect()
}

/// The casters in the light's reach neither useful yet nor receiver-only,
/// terrain blocks first: the costliest to refine (each as large as a
/// chunk), so the threads share them out early instead of waiting on them
/// at the end.
pub fn candidates(world: &BakeWorld, setup: &LightSetup, already_useful: &CasterSet) -> Vec<u32> {
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
                    let mut sampler = scratch.sampler(self.rays, Known::Set(known), caster, hidden);
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
                    let mut sampler =
                        scratch.sampler(self.rays, Known::Set(settled), *caster, None);
                    for batch in rays.chunks(BATCH) {
                        sampler.trace_batch_for_others(batch);
                    }
                    scratch.rays += sampler.traced;
                })
            });
    }
}

/// Casters one task refines at most: small tasks share the casters out
/// evenly between threads to the end of each chunk, where rayon's own
/// split leaves threads waiting (see docs/performance.md).
const MOST_CASTERS_A_TASK: usize = 16;

/// Each thread's scratch, kept for the whole light (its occluder images
/// stay warm from chunk to chunk and task to task), the thread's by its
/// index in the pool. What the scratches hold is a set and a count, the
/// same whichever thread refined which caster.
struct Scratches {
    slots: Vec<Mutex<Option<Scratch>>>,
    casters: usize,
    /// Each scratch logs what it proves (casters refined one by one).
    logged: bool,
}

impl Scratches {
    fn new(casters: usize, logged: bool) -> Scratches {
        // One more, for a caller outside the pool.
        let threads = rayon::current_num_threads() + 1;
        Scratches {
            slots: (0..threads).map(|_| Mutex::new(None)).collect(),
            casters,
            logged,
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
        let mut scratch = taken.unwrap_or_else(|| Scratch::new(self.casters, self.logged));
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
                proven = proven.union(&scratch.useful.set);
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
    useful: Proven,
    /// Surface points deferred by their caster ([`surface_points`]).
    deferred: Vec<(u32, Vec<TexelRay>)>,
    buffers: SamplerBuffers,
    rays: u64,
}

impl Scratch {
    fn new(casters: usize, logged: bool) -> Scratch {
        Scratch {
            useful: Proven::new(casters, logged),
            deferred: Vec::new(),
            buffers: SamplerBuffers::default(),
            rays: 0,
        }
    }

    /// Two threads' answers as one (the buffers of `self` kept).
    fn merge(mut self, mut other: Scratch) -> Scratch {
        self.deferred.append(&mut other.deferred);
        self.useful.merge(other.useful);
        Scratch {
            rays: self.rays + other.rays,
            ..self
        }
    }

    /// A sampler of `caster`'s rays recording into this scratch: `known`
    /// the casters already proven (its rays for others leave out those
    /// that can meet only these), `occlusion` when its rays where
    /// occluders surely hide it are left out (a model under a directional
    /// light).
    fn sampler<'r, 'a>(
        &'r mut self,
        rays: &'r LightRays<'a>,
        known: Known<'r>,
        caster: u32,
        occlusion: Option<&'r Occlusion<'r, 'r>>,
    ) -> Sampler<'r, 'a> {
        let useful = &mut self.useful;
        self.buffers.sampler(rays, known, useful, caster, occlusion)
    }
}
