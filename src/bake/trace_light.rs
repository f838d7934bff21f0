//! One light's rays: texel tiles in parallel, each ray's hits filtered by
//! face culling and the below-ground test, then classified (docs/contract.md §4). The
//! result is a set of useful casters, the same for any thread count (tiles
//! are OR-ed, and each ray's answer does not depend on traversal order).
//! A grid pass leaves out the rays that can meet only casters already
//! proven ([`PacketSkip`]): they could add nothing to the set.

use super::casters::CasterTable;
use super::ground::Ground;
use super::texel_beam::{self, Rect};
use crate::classify::{self, Passes, RayHit};
use crate::formats::bake_settings::FaceCulling;
use crate::light::{TexelGrid, TexelRay};
use crate::trace::{DropsRepeat, FaceCull, Hit, PacketRays, PacketScratch, TraceRay, Tracer};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};

/// Whether the ray's early cut-off is worth recomputing after its `hits`-th
/// kept hit. Every hit while there are few (the common ray has two or three,
/// and an early cut keeps the traversal short), then at powers of two: a
/// stack of n coincident copies ties n hits at one distance, and sorting and
/// scanning the list after each of them made such a ray O(n² log n); at
/// powers of two the sorts add up to O(n log n). A late cut-off only lets
/// hits through that cannot change the answer (see `classify::cutoff`).
fn cutoff_due(hits: usize) -> bool {
    hits <= 8 || hits.is_power_of_two()
}

/// Receives the number of rays traced, tile by tile, from worker threads.
pub trait RayCounter: Sync {
    fn add(&self, rays: u64);
}

/// Metres between a directional light's rays beyond which its tiles are
/// traced ray by ray (see [`LightRays::trace_tiles`]).
pub const MAX_PACKET_SPACING: f64 = 0.5;

/// Texels per side of the groups whose rays a ray-by-ray grid pass checks
/// together for casters not yet settled ([`PacketSkip::Settled`]), at one
/// ray a texel (fewer when supersampled).
pub const RAY_BY_RAY_GROUP: u32 = 8;

/// Texels per tile side: big enough to amortise scheduling, small enough
/// to balance 2–64 threads and to report progress often.
pub const TILE: u32 = 32;

/// Least step between neighbouring texels' directions (unit depth) for
/// which a spot or point light's packets are gated by their corner rays
/// (`LightRays::corners_hold_packets`): half of it, a texel centre's
/// distance inside the corners' cone, is then over ten times the slope
/// error of an f32 direction (below 1e-6 at the widest cube-face corner).
const GRID_SLOPE_SLACK: f64 = 1e-4;

/// Tiles of `grid`: faces × rows of tiles × columns of tiles.
pub fn tile_count(grid: &TexelGrid) -> u64 {
    let (tiles_x, tiles_y) = tiles_per_face(grid);
    grid.faces() as u64 * tiles_x * tiles_y
}

fn tiles_per_face(grid: &TexelGrid) -> (u64, u64) {
    (
        grid.width().div_ceil(TILE) as u64,
        grid.height().div_ceil(TILE) as u64,
    )
}

/// Tile `tile`'s face and texel rectangle `x0..x1 × y0..y1`.
pub fn tile_rect(grid: &TexelGrid, tile: u64) -> (usize, u32, u32, u32, u32) {
    let (tiles_x, tiles_y) = tiles_per_face(grid);
    let face = (tile / (tiles_x * tiles_y)) as usize;
    let within = tile % (tiles_x * tiles_y);
    let x0 = (within % tiles_x) as u32 * TILE;
    let y0 = (within / tiles_x) as u32 * TILE;
    let x1 = (x0 + TILE).min(grid.width());
    let y1 = (y0 + TILE).min(grid.height());
    (face, x0, y0, x1, y1)
}

/// Where on a directional light's grid a ray can hit anything: the
/// projection of the box holding everything in the light's top level (a
/// hexagon: the grid is the rectangle around it), grown by a texel and by
/// the rounding of rays and boxes. A tile outside it is not traced at all
/// (its rays are counted, their answer is empty): the empty corners of a
/// sun's grid around the world's slanted projection are most of the rays
/// of a fine sun on a big world.
///
/// Exact: a ray of texel (x, y) passes through the texel's square, and
/// every point of it projects there up to the rounding of its f32
/// light-relative origin; a hit lies in some entry's box, rounded outward
/// and padded, and a point of a box projects into the convex hull of its
/// corners' projections. Spot and point lights trace every tile (the light
/// is usually inside the box, whose projection is then the whole face).
#[derive(Debug, Clone, Default)]
pub struct TileReach {
    /// The hull of the box's corners in texel units, counter-clockwise;
    /// `None`: trace every tile.
    hull: Option<Vec<(f64, f64)>>,
    /// Texels the hull is grown by.
    margin: f64,
}

impl TileReach {
    pub fn new(grid: &TexelGrid, top: &crate::trace::TopLevel) -> TileReach {
        TileReach::of_bounds(grid, top.bounds())
    }

    /// The reach of a top level of extent `extent` (built or not).
    pub fn of_extent(grid: &TexelGrid, extent: &crate::trace::Extent) -> TileReach {
        TileReach::of_bounds(grid, extent.bounds)
    }

    /// The reach of light-relative `bounds` (a top level's).
    fn of_bounds(grid: &TexelGrid, bounds: Option<(glam::Vec3, glam::Vec3)>) -> TileReach {
        let reference = grid.reference_point();
        let bounds = bounds.map(|(lo, hi)| {
            let (lo, hi) = (lo.as_dvec3(), hi.as_dvec3());
            (
                reference + lo,
                reference + hi,
                lo.abs().max(hi.abs()).max_element(),
            )
        });
        TileReach::of_box(grid, bounds)
    }

    /// The reach of everything inside the world box `(min, max)`, whose
    /// largest light-relative coordinate is the third value (for the
    /// rounding margin); `None`: nothing in reach.
    pub fn of_box(grid: &TexelGrid, bounds: Option<(DVec3, DVec3, f64)>) -> TileReach {
        if grid.texel_size().is_none() {
            return TileReach::default();
        }
        let Some((min, max, magnitude)) = bounds else {
            // Nothing in reach: an empty hull, no tile can hit anything.
            return TileReach {
                hull: Some(Vec::new()),
                margin: 0.0,
            };
        };
        let corners: Option<Vec<(f64, f64)>> = (0..8)
            .map(|c| {
                let pick = |bit: usize, i: usize| if c & bit == 0 { min[i] } else { max[i] };
                grid.project_point(0, DVec3::new(pick(1, 0), pick(2, 1), pick(4, 2)))
            })
            .collect();
        let Some(corners) =
            corners.filter(|c| c.iter().all(|p| p.0.is_finite() && p.1.is_finite()))
        else {
            return TileReach::default();
        };
        TileReach {
            hull: Some(texel_beam::convex_hull(corners)),
            margin: 1.0 + grid.image_rounding(magnitude),
        }
    }

    /// Whether a ray of the texels `x0..x1 × y0..y1` can hit anything:
    /// the rectangle, grown by the margin, meets the hull.
    pub fn may_hit(&self, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> bool {
        let Some(hull) = &self.hull else {
            return true;
        };
        let rect = Rect {
            x0: f64::from(x0),
            y0: f64::from(y0),
            x1: f64::from(x1),
            y1: f64::from(y1),
        };
        texel_beam::overlaps_rect(hull, rect.grown(self.margin))
    }
}

/// The rules a ray applies to its hits.
#[derive(Debug, Clone, Copy)]
pub struct RayRules {
    pub face_culling: FaceCulling,
    pub height_bias: f64,
    pub tie_epsilon: f32,
    pub passes: Passes,
}

impl RayRules {
    pub fn new(config: &super::config::BakeConfig, passes: Passes) -> RayRules {
        RayRules {
            face_culling: config.face_culling,
            height_bias: config.height_bias,
            tie_epsilon: config.tie_epsilon as f32,
            passes,
        }
    }
}

/// A set of caster ids as bits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CasterSet(Vec<u64>);

impl CasterSet {
    pub fn new(casters: usize) -> Self {
        CasterSet(vec![0; casters.div_ceil(64)])
    }

    pub fn insert(&mut self, caster: u32) {
        self.0[caster as usize / 64] |= 1 << (caster % 64);
    }

    pub fn contains(&self, caster: u32) -> bool {
        self.0[caster as usize / 64] & (1 << (caster % 64)) != 0
    }

    /// Takes each of `casters` out of the set.
    pub fn remove_all(&mut self, casters: &[u32]) {
        for &c in casters {
            self.0[c as usize / 64] &= !(1 << (c % 64));
        }
    }

    pub fn union(mut self, other: &CasterSet) -> Self {
        for (a, b) in self.0.iter_mut().zip(&other.0) {
            *a |= b;
        }
        self
    }

    pub fn len(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn heap_bytes(&self) -> u64 {
        self.0.capacity() as u64 * 8
    }

    /// The bits, 64 caster ids per word (id `i` is bit `i % 64` of word
    /// `i / 64`): how a partial result stores a set.
    pub fn words(&self) -> &[u64] {
        &self.0
    }

    /// The set of `casters` ids whose bits are `words`, or `None` when the
    /// word count does not fit or a bit past the last caster is set.
    pub fn from_words(casters: usize, words: Vec<u64>) -> Option<Self> {
        let spare = casters % 64;
        let last_ok = spare == 0 || words.last().is_none_or(|w| w >> spare == 0);
        (words.len() == casters.div_ceil(64) && last_ok).then_some(CasterSet(words))
    }
}

/// Scratch of [`LightRays::trace_packet`], reused by one thread: the
/// packet's rays (the caller fills `rays`) and each ray's hits.
#[derive(Default)]
pub struct PacketState {
    pub rays: Vec<TexelRay>,
    single: Vec<RayHit>,
    traced: Vec<TraceRay>,
    hits: Vec<Vec<RayHit>>,
    limits: Vec<f32>,
    scratch: PacketScratch,
    keep: Vec<bool>,
}

impl PacketState {
    /// The kept hits (up to each ray's cut-off, sorted) of the first
    /// `rays` rays of the latest [`LightRays::trace_packet`].
    pub fn hits(&self, rays: usize) -> &[Vec<RayHit>] {
        &self.hits[..rays.min(self.hits.len())]
    }
}

/// Whether a grid pass leaves out packets that cannot change its answer.
#[derive(Clone, Copy, Debug)]
pub enum PacketSkip<'k> {
    /// Every packet traced: the benches time the traversal like for like.
    Never,
    /// A packet's rays that can meet only settled casters ([`Settled`]:
    /// proven useful by an earlier packet of the pass on any thread, in
    /// `known`, or never useful, receiver-only) are left out, and the
    /// packet whole when its beam reaches none other
    /// (`Tracer::rays_reaching`). Such rays could only prove casters
    /// already proven, so the answer OR `known` is the same whichever rays
    /// the threads' timing leaves out.
    Settled { known: Option<&'k CasterSet> },
}

/// Where a group of rays checked ray by ray finds the entries holding an
/// unsettled caster: what `Tracer::gate_packet` found from its corner
/// rays just before, or a walk of the top level with its rays' own beam.
#[derive(Clone, Copy)]
enum OpenEntriesFrom {
    Gate,
    RaysBeam,
}

/// The casters no ray of a grid pass can newly prove useful: proven so
/// far by any of its threads, known before it, or receiver-only; and
/// whether the pass asks each packet's corner rays first
/// ([`LightRays::corners_hold_packets`], decided once a pass).
struct Settled {
    casters: Vec<AtomicU64>,
    by_corners: bool,
}

impl Settled {
    fn new(casters: &CasterTable, known: Option<&CasterSet>, by_corners: bool) -> Settled {
        let mut words = casters.receiver_only.clone();
        words.resize(casters.len().div_ceil(64), 0);
        if let Some(known) = known {
            for (word, k) in words.iter_mut().zip(&known.0) {
                *word |= k;
            }
        }
        Settled {
            casters: words.into_iter().map(AtomicU64::new).collect(),
            by_corners,
        }
    }

    fn insert(&self, caster: u32) {
        self.casters[caster as usize / 64].fetch_or(1 << (caster % 64), Ordering::Relaxed);
    }

    fn contains(&self, caster: u32) -> bool {
        self.casters[caster as usize / 64].load(Ordering::Relaxed) & (1 << (caster % 64)) != 0
    }
}

/// Caster `c` proven useful by a ray of a grid pass: into the thread's
/// `useful`, and into the pass's `settled` set (once per caster and
/// thread: most proofs repeat one the thread already made).
fn prove(c: u32, settled: Option<&Settled>, useful: &mut CasterSet) {
    if let Some(settled) = settled.filter(|_| !useful.contains(c)) {
        settled.insert(c);
    }
    useful.insert(c);
}

/// What the per-hit filter (docs/contract.md §4, steps 1 and 2) makes of
/// one hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HitFate {
    /// It reaches the rules.
    Kept(RayHit),
    /// A face the light's face culling drops.
    FacingAway,
    /// A non-terrain hit below the terrain surface.
    BelowGround,
    /// Its caster id is not in the table (never for a table's own world).
    Unknown,
}

/// Everything one light's rays need: its grid, how to find hits, what the
/// hits belong to, the ground and the rules. Made by
/// [`super::setup::LightSetup::rays`]; the grid pass, refinement, the
/// pictures and the cross-check all trace through this one value, so they
/// apply the same filter and the same classification.
#[derive(Clone, Copy)]
pub struct LightRays<'a> {
    pub grid: &'a TexelGrid,
    pub tracer: Tracer<'a>,
    pub casters: &'a CasterTable,
    pub ground: Option<&'a Ground<'a>>,
    pub rules: RayRules,
    /// The tiles whose rays can hit something.
    pub tiles: &'a TileReach,
}

impl LightRays<'_> {
    /// Traces every texel of the grid with `samples`² rays each (1: the
    /// texel centre; k: a k×k pattern of sub-texel centres); `rays_done`
    /// hears of every finished tile so a caller can show progress.
    pub fn trace_grid(
        &self,
        samples: u32,
        skip: PacketSkip,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        self.trace_tiles(0..self.tile_count(), samples, skip, rays_done)
    }

    /// Tiles of [`TILE`]² texels: faces, then rows of tiles, then columns
    /// (the order of [`tile_rect`]). A distributed bake hands out
    /// ranges of these.
    pub fn tile_count(&self) -> u64 {
        tile_count(self.grid)
    }

    /// [`Self::trace_grid`] over the tiles `tiles` only (a shard's range, or
    /// a spread sample for the plan's ray rate): the OR of the answers over
    /// a partition of `0..tile_count()` is the grid's. Tiles are traced as
    /// packets of coherent rays (`Tracer::for_each_packet_hit`; a
    /// directional light's rays more than [`MAX_PACKET_SPACING`] apart, ray
    /// by ray): the answers are the single-ray ones either way. With
    /// [`PacketSkip::Settled`] the rays of a packet that cannot meet a
    /// caster not yet proven are left out: the answer OR `known` is the
    /// same.
    pub fn trace_tiles(
        &self,
        tiles: impl IntoParallelIterator<Item = u64>,
        samples: u32,
        skip: PacketSkip,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let grid = self.grid;
        let casters = self.casters.len();
        let samples = samples.max(1);
        let side = self.packet_side(samples);
        let settled = match skip {
            PacketSkip::Never => None,
            PacketSkip::Settled { known } => Some(Settled::new(
                self.casters,
                known,
                self.corners_hold_packets(),
            )),
        };
        let settled = settled.as_ref();
        tiles
            .into_par_iter()
            .fold(
                || (CasterSet::new(casters), PacketState::default()),
                |(mut useful, mut state), tile| {
                    let (face, x0, y0, x1, y1) = tile_rect(grid, tile);
                    let rect = (x0, y0, x1, y1);
                    match side {
                        _ if !self.tiles.may_hit(rect) => {}
                        None => self.trace_tile_ray_by_ray(
                            face,
                            rect,
                            samples,
                            settled,
                            &mut state,
                            &mut useful,
                        ),
                        Some(side) => {
                            for py in (y0..y1).step_by(side as usize) {
                                for px in (x0..x1).step_by(side as usize) {
                                    let texels = (px, py, (px + side).min(x1), (py + side).min(y1));
                                    self.trace_tile_packet(
                                        face,
                                        texels,
                                        samples,
                                        settled,
                                        &mut state,
                                        &mut useful,
                                    );
                                }
                            }
                        }
                    }
                    rays_done.add(((x1 - x0) * (y1 - y0)) as u64 * (samples as u64).pow(2));
                    (useful, state)
                },
            )
            .map(|(useful, _)| useful)
            .reduce(|| CasterSet::new(casters), |a, b| a.union(&b))
    }

    /// The rays of the texels `x0..x1 × y0..y1` of `face` one by one; with
    /// `settled`, only those that may meet a caster not yet settled (found
    /// a group of about [`RAY_BY_RAY_GROUP`]² rays at a time, as a
    /// packet's would be).
    fn trace_tile_ray_by_ray(
        &self,
        face: usize,
        (x0, y0, x1, y1): (u32, u32, u32, u32),
        samples: u32,
        settled: Option<&Settled>,
        state: &mut PacketState,
        useful: &mut CasterSet,
    ) {
        // About a packet's worth of rays a group, as `packet_side` makes.
        let side = (RAY_BY_RAY_GROUP / samples).max(1);
        for gy in (y0..y1).step_by(side as usize) {
            for gx in (x0..x1).step_by(side as usize) {
                let group = (gx, gy, (gx + side).min(x1), (gy + side).min(y1));
                let gated = match self.gate(face, group, samples, settled, state) {
                    Some(false) => continue,
                    Some(true) => OpenEntriesFrom::Gate,
                    None => OpenEntriesFrom::RaysBeam,
                };
                self.texel_rays_into(state, face, group, samples);
                self.prepare_packet(state);
                if let Some(settled) = settled {
                    if self.keep_unsettled(state, settled, gated) == 0 {
                        continue;
                    }
                }
                let PacketState {
                    rays,
                    traced,
                    single,
                    ..
                } = state;
                for (ray, relative) in rays.iter().zip(traced.iter()) {
                    self.trace_relative(ray, relative, single, settled, |c| {
                        prove(c, settled, useful)
                    });
                }
            }
        }
    }

    /// The rays of the texels `x0..x1 × y0..y1` of `face` as one packet,
    /// less those that can meet only `settled` casters (when given), which
    /// hears of every caster proven.
    fn trace_tile_packet(
        &self,
        face: usize,
        texels: (u32, u32, u32, u32),
        samples: u32,
        settled: Option<&Settled>,
        state: &mut PacketState,
        useful: &mut CasterSet,
    ) {
        let unsettled = |c: u32| settled.is_some_and(|s| !s.contains(c));
        let which = match (settled, self.gate(face, texels, samples, settled, state)) {
            (_, Some(false)) => return,
            (None, _) => PacketRays::All,
            (Some(_), Some(true)) => PacketRays::Gated(&unsettled),
            (Some(_), None) => PacketRays::MeetingUnsettled(&unsettled),
        };
        self.texel_rays_into(state, face, texels, samples);
        self.prepare_packet(state);
        self.trace_prepared(state, which, settled, |c| prove(c, settled, useful));
    }

    /// With `settled`, when its pass asks corner rays first,
    /// whether a ray (`samples`² a texel) of the texels `texels` of `face`
    /// may meet a caster not yet settled (`Tracer::gate_packet`, which
    /// leaves what it found in `state` for the packet); `None` when not
    /// asked.
    fn gate(
        &self,
        face: usize,
        texels: (u32, u32, u32, u32),
        samples: u32,
        settled: Option<&Settled>,
        state: &mut PacketState,
    ) -> Option<bool> {
        let settled = settled.filter(|s| s.by_corners)?;
        let unsettled = |c: u32| !settled.contains(c);
        let corners = self.corner_rays(face, texels, samples);
        Some(
            self.tracer
                .gate_packet(&corners, &mut state.scratch, &unsettled),
        )
    }

    /// Whether the rays through the corners of a packet's texel rectangle
    /// bound its rays for `Tracer::gate_packet`: always for a directional
    /// light (parallel rays, whose origins' rounding the beam allows for);
    /// for a spot or point light when half a texel is far wider than the
    /// f32 rounding of a direction ([`GRID_SLOPE_SLACK`]), so the rays
    /// through texel centres stay inside the corners' cone.
    fn corners_hold_packets(&self) -> bool {
        let grid = self.grid;
        if grid.direction().is_some() {
            return true;
        }
        let at = |cx, cy| grid.unit_depth_direction(0, cx, cy);
        let step_x = (at(1.0, 0.0) - at(0.0, 0.0)).length();
        let step_y = (at(0.0, 1.0) - at(0.0, 0.0)).length();
        step_x.min(step_y) >= GRID_SLOPE_SLACK
    }

    /// The light-relative rays through the four corners of a rectangle
    /// holding the ray positions (`samples`² a texel) of the texels `x0..x1
    /// × y0..y1` of `face`, for `Tracer::gate_packet`: a directional
    /// light's through the outermost positions themselves (its beam allows
    /// for the rounding of every origin), a spot or point light's through
    /// the texels' edges (half a texel out, which covers the rounding of
    /// every direction, see [`Self::corners_hold_packets`]).
    pub fn corner_rays(
        &self,
        face: usize,
        (x0, y0, x1, y1): (u32, u32, u32, u32),
        samples: u32,
    ) -> [TraceRay; 4] {
        let inset = match self.grid.direction() {
            Some(_) => 0.5 / f64::from(samples.max(1)),
            None => 0.0,
        };
        let (lo, hi) = (
            (f64::from(x0) + inset, f64::from(y0) + inset),
            (f64::from(x1) - inset, f64::from(y1) - inset),
        );
        [(lo.0, lo.1), (hi.0, lo.1), (lo.0, hi.1), (hi.0, hi.1)].map(|(x, y)| {
            let ray = self.grid.ray_through(face, x, y);
            self.light_relative(&ray)
        })
    }

    /// The rays of the texels `x0..x1 × y0..y1` of `face`, into
    /// `state.rays`.
    fn texel_rays_into(
        &self,
        state: &mut PacketState,
        face: usize,
        (x0, y0, x1, y1): (u32, u32, u32, u32),
        samples: u32,
    ) {
        state.rays.clear();
        for y in y0..y1 {
            for x in x0..x1 {
                state.rays.extend(self.grid.texel_rays(face, x, y, samples));
            }
        }
    }

    /// Keeps in `state` the prepared rays that may meet a caster not yet
    /// settled (only those can change the answer), against the entries
    /// `from` says; returns how many.
    fn keep_unsettled(
        &self,
        state: &mut PacketState,
        settled: &Settled,
        from: OpenEntriesFrom,
    ) -> usize {
        let PacketState {
            rays,
            traced,
            scratch,
            keep,
            ..
        } = state;
        let unsettled = |c: u32| !settled.contains(c);
        let kept = match from {
            OpenEntriesFrom::Gate => self
                .tracer
                .rays_reaching_gated(traced, scratch, &unsettled, keep),
            OpenEntriesFrom::RaysBeam => {
                self.tracer.rays_reaching(traced, scratch, &unsettled, keep)
            }
        };
        if kept < rays.len() {
            let mut k = keep.iter();
            rays.retain(|_| k.next() == Some(&true));
            let mut k = keep.iter();
            traced.retain(|_| k.next() == Some(&true));
        }
        kept
    }

    /// Texels per packet side: about 64 rays (8×8 texels, fewer when
    /// supersampled); `None`: ray by ray, for a directional light whose
    /// rays lie more than [`MAX_PACKET_SPACING`] apart, where a packet's
    /// footprint outgrows the triangles and the tile path is slower
    /// (docs/performance.md).
    fn packet_side(&self, samples: u32) -> Option<u32> {
        let grid = self.grid;
        if grid.width() >= 2 {
            let (a, b) = (grid.ray(0, 0, 0), grid.ray(0, 1, 0));
            let spacing = (b.origin - a.origin).length() / f64::from(samples);
            if a.direction == b.direction && spacing > MAX_PACKET_SPACING {
                return None;
            }
        }
        Some((8 / samples).max(1))
    }

    /// One ray of the light: its hits filtered by face culling and the
    /// below-ground test, classified, and each caster it proves useful handed
    /// to `on_useful` (a caster useful in both passes is handed twice).
    /// `hits` is scratch space reused across rays.
    pub fn trace(&self, ray: &TexelRay, hits: &mut Vec<RayHit>, on_useful: impl FnMut(u32)) {
        self.trace_relative(ray, &self.light_relative(ray), hits, None, on_useful);
    }

    /// [`Self::trace`] of `ray` whose light-relative form `traced` is made;
    /// with `settled`, the casters it need not prove, whose repeated hits
    /// on a stack of coincident copies the tracer may leave out
    /// ([`Self::repeat_is_moot`]).
    fn trace_relative(
        &self,
        ray: &TexelRay,
        traced: &TraceRay,
        hits: &mut Vec<RayHit>,
        settled: Option<&Settled>,
        mut on_useful: impl FnMut(u32),
    ) {
        hits.clear();
        let mut limit = traced.t_max;
        let repeats = |c: u32, anchors: [u32; 2]| self.repeat_is_moot_given(settled, c, anchors);
        let repeats = settled.map(|_| &repeats as &DropsRepeat);
        self.tracer.for_each_hit_dropping(traced, repeats, |hit| {
            self.offer(&hit, ray, hits, &mut limit)
        });
        self.conclude(hits, limit, &mut on_useful);
    }

    /// [`Self::trace`] for each ray of `state.rays` (a tile of coherent
    /// rays), traced as packets: every ray gets the answer it gets alone.
    pub fn trace_packet(&self, state: &mut PacketState, on_useful: impl FnMut(u32)) {
        self.prepare_packet(state);
        self.trace_prepared(state, PacketRays::All, None, on_useful);
    }

    /// [`Self::trace_packet`] of only the rays that may meet a caster
    /// `unsettled` accepts: the others may be left out, and then have no
    /// hits (they could prove only casters `unsettled` turns away).
    pub fn trace_packet_meeting(
        &self,
        state: &mut PacketState,
        unsettled: &dyn Fn(u32) -> bool,
        on_useful: impl FnMut(u32),
    ) {
        self.prepare_packet(state);
        let which = PacketRays::MeetingUnsettled(unsettled);
        self.trace_prepared(state, which, None, on_useful);
    }

    /// The light-relative rays of `state.rays`, into `state.traced`.
    fn prepare_packet(&self, state: &mut PacketState) {
        state.traced.clear();
        let rays = state.rays.iter().map(|r| self.light_relative(r));
        state.traced.extend(rays);
    }

    /// [`Self::trace_packet`] of rays [`Self::prepare_packet`] made, less
    /// those `which` leaves out (they prove nothing); with `settled`, the
    /// casters they need not prove, whose repeated hits on a stack of
    /// coincident copies the tracer may leave out
    /// ([`Self::repeat_is_moot`]).
    fn trace_prepared(
        &self,
        state: &mut PacketState,
        which: PacketRays,
        settled: Option<&Settled>,
        mut on_useful: impl FnMut(u32),
    ) {
        let PacketState {
            rays,
            traced,
            hits,
            limits,
            scratch,
            ..
        } = state;
        if hits.len() < rays.len() {
            hits.resize_with(rays.len(), Vec::new);
        }
        limits.clear();
        limits.extend(traced.iter().map(|r| r.t_max));
        for list in hits.iter_mut() {
            list.clear();
        }
        let repeats = |c: u32, anchors: [u32; 2]| self.repeat_is_moot_given(settled, c, anchors);
        let mut cull = self.face_cull();
        if settled.is_some() {
            cull.repeats = Some(&repeats);
        }
        self.tracer
            .for_each_packet_hit_culled(traced, scratch, &cull, which, |lane, hit| {
                self.offer(&hit, &rays[lane], &mut hits[lane], &mut limits[lane])
            });
        for (list, &limit) in hits.iter_mut().zip(limits.iter()) {
            self.conclude(list, limit, &mut on_useful);
        }
    }

    /// One hit of a ray being traced: kept (filtered) into `hits`, the
    /// ray's cut-off `limit` recomputed when due; returns the ray's new t_max.
    #[inline]
    fn offer(&self, hit: &Hit, ray: &TexelRay, hits: &mut Vec<RayHit>, limit: &mut f32) -> f32 {
        if hit.t > *limit {
            return *limit;
        }
        let Some(kept) = self.filter_hit(hit, ray) else {
            return *limit;
        };
        hits.push(kept);
        if cutoff_due(hits.len()) {
            classify::sort_hits(hits);
            let rules = self.rules;
            *limit = limit.min(classify::cutoff(hits, rules.tie_epsilon, rules.passes));
        }
        *limit
    }

    /// The hits [`Self::filter_hit`] drops for their facing alone, for the
    /// tracer to skip.
    fn face_cull(&self) -> FaceCull<'_> {
        FaceCull {
            drops_back: match self.rules.face_culling {
                FaceCulling::Back => Some(true),
                FaceCulling::Front => Some(false),
                FaceCulling::None => None,
            },
            either_face: &self.casters.double_sided,
            repeats: None,
        }
    }

    /// [`Self::repeat_is_moot`] for a caster of `settled` (none without).
    fn repeat_is_moot_given(&self, settled: Option<&Settled>, c: u32, anchors: [u32; 2]) -> bool {
        settled.is_some_and(|s| s.contains(c)) && self.repeat_is_moot(c, anchors)
    }

    /// Whether a hit of caster `c` where kept hits of the distinct casters
    /// `a` and `b` lie, at one distance with the same alpha-testing (the
    /// copies of a stack of coincident placements), changes no other
    /// caster's answer (docs/contract.md §4): the crossing count, which
    /// stops at two, has two crossings there at the latest; and the
    /// nearest caster's distance is no farther without it, since `c` is
    /// receiver-only or `a` or `b` is a caster. Only `c`'s own membership
    /// of the front set depends on it: moot once `c` is settled.
    fn repeat_is_moot(&self, c: u32, [a, b]: [u32; 2]) -> bool {
        let flags = |id: u32| {
            let caster = self.casters.casters.get(id as usize);
            caster.map(|x| (x.receiver_only, x.alpha_tested))
        };
        let (Some((c_receives, c_alpha)), Some((a_receives, a_alpha)), Some((b_receives, b_alpha))) =
            (flags(c), flags(a), flags(b))
        else {
            return false;
        };
        a != b
            && c_alpha == a_alpha
            && c_alpha == b_alpha
            && (c_receives || !a_receives || !b_receives)
    }

    /// A traced ray's kept hits up to its cut-off, classified.
    fn conclude(&self, hits: &mut Vec<RayHit>, limit: f32, on_useful: &mut impl FnMut(u32)) {
        hits.retain(|h| h.t <= limit);
        classify::sort_hits(hits);
        let rules = self.rules;
        classify::classify_ray(hits, rules.tie_epsilon, rules.passes, on_useful);
    }

    /// Every hit of `ray` that survives the filter, sorted (no early
    /// cut-off): the filter margin needs the farthest surface, not only an
    /// answer.
    pub fn all_hits(&self, ray: &TexelRay, hits: &mut Vec<RayHit>) {
        let traced = self.light_relative(ray);
        hits.clear();
        self.tracer.for_each_hit(&traced, |hit| {
            if let Some(kept) = self.filter_hit(&hit, ray) {
                hits.push(kept);
            }
            traced.t_max
        });
        classify::sort_hits(hits);
    }

    /// The front surface of texel `(face, x, y)` as the bake's All pass sees
    /// it: the nearest hit that survives the same filter as the bake's rays
    /// (face culling, double-sided, mirrored, below ground), whatever its
    /// caster — receiver-only and alpha-tested groups included. Equal
    /// distances go to the lowest caster id, the bake's canonical hit order.
    /// `None`: the ray meets nothing that counts. `t` is metres from the
    /// ray's origin. The rules' `passes` play no part.
    pub fn front_hit(&self, face: usize, x: u32, y: u32) -> Option<RayHit> {
        let ray = self.grid.ray(face, x, y);
        let traced = self.light_relative(&ray);
        let mut best: Option<RayHit> = None;
        self.tracer.for_each_hit(&traced, |hit| {
            let limit = best.map_or(traced.t_max, |b| b.t);
            if hit.t > limit {
                return limit;
            }
            if let Some(kept) = self.filter_hit(&hit, &ray) {
                if best.is_none_or(|b| (kept.t, kept.caster) < (b.t, b.caster)) {
                    best = Some(kept);
                }
            }
            best.map_or(traced.t_max, |b| b.t)
        });
        best
    }

    /// Every hit of `ray` (no early cut-off), each with what the filter
    /// makes of it ([`HitFate`]), in the order the tracer finds them: a
    /// caller explaining a verdict needs the hits the rules never see.
    pub fn every_hit(&self, ray: &TexelRay, mut visit: impl FnMut(&Hit, HitFate)) {
        let traced = self.light_relative(ray);
        self.tracer.for_each_hit(&traced, |hit| {
            visit(&hit, self.fate(&hit, ray));
            traced.t_max
        });
    }

    /// A ray in the tracer's light-relative f32 frame.
    pub fn light_relative(&self, ray: &TexelRay) -> TraceRay {
        let reference: DVec3 = self.grid.reference_point();
        TraceRay {
            origin: (ray.origin - reference).as_vec3(),
            direction: ray.direction.as_vec3(),
            t_min: ray.t_min as f32,
            t_max: if ray.t_max.is_finite() {
                ray.t_max as f32
            } else {
                f32::INFINITY
            },
        }
    }

    /// The per-hit rules every consumer of a light's rays applies before
    /// classification: face culling (double-sided groups exempt; mirrored
    /// instances are judged in model space, see `trace::instance`) and the
    /// below-ground test for non-terrain hits. `None`: the hit does not count.
    fn filter_hit(&self, hit: &Hit, ray: &TexelRay) -> Option<RayHit> {
        match self.fate(hit, ray) {
            HitFate::Kept(kept) => Some(kept),
            HitFate::FacingAway | HitFate::BelowGround | HitFate::Unknown => None,
        }
    }

    /// What [`Self::filter_hit`] makes of `hit`, and why when it drops it.
    #[inline]
    fn fate(&self, hit: &Hit, ray: &TexelRay) -> HitFate {
        let Some(caster) = self.casters.casters.get(hit.caster as usize) else {
            return HitFate::Unknown;
        };
        let culled = !caster.double_sided
            && match self.rules.face_culling {
                FaceCulling::Back => hit.back_facing,
                FaceCulling::Front => !hit.back_facing,
                FaceCulling::None => false,
            };
        if culled {
            return HitFate::FacingAway;
        }
        if let Some(ground) = self.ground.filter(|_| !caster.is_terrain()) {
            let p = ray.origin + ray.direction * hit.t as f64;
            if ground.is_below(p, self.rules.height_bias) {
                return HitFate::BelowGround;
            }
        }
        HitFate::Kept(RayHit {
            t: hit.t,
            caster: hit.caster,
            receiver_only: caster.receiver_only,
            alpha_tested: caster.alpha_tested,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn inside(hull: &[(f64, f64)], p: (f64, f64)) -> bool {
        (0..hull.len()).all(|i| {
            let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
            (b.0 - a.0) * (p.1 - a.1) - (b.1 - a.1) * (p.0 - a.0) >= 0.0
        })
    }

    /// Every tile holding a point of the hull may hit (checked on a dense
    /// lattice of points against the hull of random projected boxes), and
    /// tiles well away from it are skipped.
    #[test]
    fn tiles_meeting_the_hull_may_hit_and_far_ones_do_not() {
        let mut rng = Rng::new(5);
        let (mut kept, mut skipped) = (0, 0);
        for _ in 0..200 {
            let centre = (rng.range(20.0, 80.0), rng.range(20.0, 80.0));
            let points: Vec<(f64, f64)> = (0..8)
                .map(|_| {
                    (
                        centre.0 + rng.range(-30.0, 30.0),
                        centre.1 + rng.range(-30.0, 30.0),
                    )
                })
                .collect();
            let hull = texel_beam::convex_hull(points.clone());
            for p in &points {
                assert!(
                    inside(&hull, *p) || hull.contains(p),
                    "the hull holds its points"
                );
            }
            let reach = TileReach {
                hull: Some(hull.clone()),
                margin: 1.0,
            };
            for ty in 0..13u32 {
                for tx in 0..13u32 {
                    let rect = (tx * 8, ty * 8, tx * 8 + 8, ty * 8 + 8);
                    let meets = (0..=32).any(|i| {
                        (0..=32).any(|j| {
                            let p = (
                                f64::from(rect.0) + f64::from(i) / 4.0,
                                f64::from(rect.1) + f64::from(j) / 4.0,
                            );
                            inside(&hull, p)
                        })
                    });
                    let may = reach.may_hit(rect);
                    assert!(!meets || may, "tile {rect:?} meets {hull:?}");
                    kept += usize::from(may);
                    skipped += usize::from(!may);
                }
            }
        }
        assert!(kept > 1000 && skipped > 1000, "{kept} {skipped}");
        let nothing = TileReach {
            hull: Some(Vec::new()),
            margin: 1.0,
        };
        assert!(!nothing.may_hit((0, 0, 32, 32)));
        assert!(TileReach::default().may_hit((0, 0, 32, 32)));
    }
}
