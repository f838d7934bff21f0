//! `shadowcull xcheck`: the ray-cast bake against the rasterized method,
//! pair by pair (caster × light), with a cause for every disagreement found
//! by re-testing that caster with rays.
//!
//! docs/contract.md §4 allows only rasterization rules at triangle edges and depth
//! quantization as causes, so those are the only explanations:
//! - the ray cast finds the caster useful and the raster does not: every
//!   texel where a centre ray makes it useful is re-traced. It is a **tie**
//!   when another caster's hit lies within ε in front of it (or level with
//!   it to f32 precision): the ray cast keeps both in its front set, LEQUAL
//!   on one f32 depth keeps only the nearer. It is an **edge** when a ray
//!   moved [`EDGE_JITTER`] texel off the centre gives another answer: a
//!   triangle edge passes that close to the centre, where the ray test's tie
//!   rule and the rasterizer's snapped top-left rule part.
//! - the raster finds it useful and the ray cast does not: the queries do
//!   not say at which texels, so every texel is re-traced with rays moved
//!   [`EDGE_JITTER`] off its centre; it is an edge when such rays find the
//!   caster useful at no fewer texels than the raster passed samples.
//!
//! Anything else stays unexplained.

use super::RasterResult;
use crate::bake::casters::{CasterTable, Owner};
use crate::bake::setup::{BakeWorld, LightSetup};
use crate::bake::trace_light::{LightRays, RayRules};
use crate::bake::BakeConfig;
use crate::classify::{Passes, RayHit};
use crate::scene::Scene;
use rayon::prelude::*;

/// How far (texels) the edge re-test moves rays off a texel centre: more
/// than the rasterizer's vertex snapping (llvmpipe: 1/256 pixel) and the
/// f32 rounding of projected positions (about 1e-4 texel on 2048-texel
/// tiles). Four rays, ±x and ±y, catch any edge within 1/181 texel.
pub const EDGE_JITTER: f64 = 1.0 / EDGE_JITTER_PER_TEXEL as f64;
const EDGE_JITTER_PER_TEXEL: u32 = 128;

#[derive(Debug, Clone, serde::Serialize)]
pub struct Disagreement {
    pub chunk: String,
    pub kind: &'static str,
    /// The instance's index in its chunk (terrain: none).
    pub index: Option<usize>,
    pub group: Option<usize>,
    pub light: usize,
    pub light_name: String,
    pub ray_cast: bool,
    pub raster: bool,
    /// Texel centres where the ray cast finds it useful (any pass).
    pub ray_texels: u64,
    /// Samples that passed its query (the larger of the two variants).
    pub raster_texels: u64,
    /// `None`: unexplained.
    pub cause: Option<String>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct LightTexels {
    pub light: usize,
    pub name: String,
    /// Σ over casters of texels where the caster is useful (All pass).
    pub ray_cast: u64,
    /// Of `ray_cast`, the useful casters beyond the first at texels whose
    /// front set holds several casters (hits within ε of the nearest:
    /// docs/contract.md §4). LEQUAL passes only exactly equal depths, so at such a texel
    /// the raster counts between one and all of them: `ray_cast − tied ≤
    /// raster ≤ ray_cast` up to edge texels.
    pub ray_cast_tied: u64,
    pub raster: u64,
    pub ray_seconds: f64,
    pub raster_seconds: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct XcheckReport {
    pub pairs: u64,
    pub agreeing: u64,
    pub unexplained: u64,
    pub disagreements: Vec<Disagreement>,
    pub lights: Vec<LightTexels>,
    pub renderer: String,
    /// How the raster counted its samples (`Atomics`, `Queries`, …).
    pub counter: String,
    pub notes: Vec<String>,
}

/// The ray-cast side: per light, per caster, the texels (centre rays) at
/// which it is useful, in the All pass (`all`) and in any pass (`any`).
pub struct RayCounts {
    pub all: Vec<Vec<u64>>,
    pub any: Vec<Vec<u64>>,
    /// Per light: Σ over texels of (casters useful in the All pass − 1),
    /// where at least one is.
    pub tied: Vec<u64>,
    pub seconds: Vec<f64>,
}

/// A texel of a light: face, x, y.
type Texel = (usize, u32, u32);

/// One light's centre-ray counts, and the texels where the watched casters
/// are useful.
struct CentrePass {
    all: Vec<u64>,
    any: Vec<u64>,
    tied: u64,
    /// (caster, texel), sorted.
    watched: Vec<(u32, Texel)>,
}

/// One worker's share of a [`CentrePass`] (and its reused buffers).
struct Tally {
    all: Vec<u64>,
    any: Vec<u64>,
    tied: u64,
    watched: Vec<(u32, Texel)>,
    hits: Vec<RayHit>,
    seen: Vec<u32>,
}

/// Traces every texel centre like the bake does: per caster, the texels
/// where it is useful in the All pass and in any pass, the ties, and (for
/// casters with `watch` set) the texels themselves.
fn centre_pass(rays: &LightRays, watch: &[bool]) -> CentrePass {
    let grid = rays.grid;
    let n = rays.casters.len();
    let all_pass = LightRays {
        rules: RayRules {
            passes: Passes::AllOnly,
            ..rays.rules
        },
        ..*rays
    };
    let rows = grid.faces() as u64 * grid.height() as u64;
    let tally = (0..rows)
        .into_par_iter()
        .fold(
            || Tally {
                all: vec![0; n],
                any: vec![0; n],
                tied: 0,
                watched: Vec::new(),
                hits: Vec::new(),
                seen: Vec::new(),
            },
            |mut tally, row| {
                let face = (row / grid.height() as u64) as usize;
                let y = (row % grid.height() as u64) as u32;
                for x in 0..grid.width() {
                    let ray = grid.ray(face, x, y);
                    let Tally {
                        all,
                        any,
                        tied,
                        watched,
                        hits,
                        seen,
                    } = &mut tally;
                    seen.clear();
                    rays.trace(&ray, hits, |c| seen.push(c));
                    seen.sort_unstable();
                    seen.dedup();
                    for &c in seen.iter() {
                        any[c as usize] += 1;
                        if watch[c as usize] {
                            watched.push((c, (face, x, y)));
                        }
                    }
                    let mut front = 0u64;
                    all_pass.trace(&ray, hits, |c| {
                        all[c as usize] += 1;
                        front += 1;
                    });
                    *tied += front.saturating_sub(1);
                }
                tally
            },
        )
        .map(|t| (t.all, t.any, t.tied, t.watched))
        .reduce(
            || (vec![0; n], vec![0; n], 0, Vec::new()),
            |(mut a, mut b, t, mut w), (c, d, u, x)| {
                a.iter_mut().zip(c).for_each(|(p, q)| *p += q);
                b.iter_mut().zip(d).for_each(|(p, q)| *p += q);
                w.extend(x);
                (a, b, t + u, w)
            },
        );
    let (all, any, tied, mut watched) = tally;
    watched.sort_unstable();
    CentrePass {
        all,
        any,
        tied,
        watched,
    }
}

/// Whether `caster` is useful on ray `(cx, cy)` of `face` (texel units).
fn useful_at(
    rays: &LightRays,
    hits: &mut Vec<RayHit>,
    face: usize,
    at: (f64, f64),
    caster: u32,
) -> bool {
    let mut useful = false;
    rays.trace(&rays.grid.ray_through(face, at.0, at.1), hits, |c| {
        useful |= c == caster;
    });
    useful
}

/// The four rays of the edge re-test around texel `(x, y)`'s centre.
fn jittered(x: u32, y: u32) -> [(f64, f64); 4] {
    let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
    [
        (cx - EDGE_JITTER, cy),
        (cx + EDGE_JITTER, cy),
        (cx, cy - EDGE_JITTER),
        (cx, cy + EDGE_JITTER),
    ]
}

/// Why the raster may miss `caster` at a texel where the centre ray finds
/// it useful.
#[derive(Debug, Clone, Copy, PartialEq)]
enum TexelCause {
    /// Another caster's hit `dt` metres in front of it (≤ ε; ≤ 0 is level
    /// to f32 precision).
    Tie {
        other: u32,
        dt: f32,
    },
    Edge,
    Unexplained,
}

fn texel_cause(rays: &LightRays, hits: &mut Vec<RayHit>, caster: u32, texel: Texel) -> TexelCause {
    let (face, x, y) = texel;
    let ray = rays.grid.ray(face, x, y);
    let passes = passes_useful(rays, hits, &ray, caster);
    // `hits` now holds the ray's hits under the light's own passes.
    if let Some((other, dt)) = tie_rival(hits, caster, rays.rules.tie_epsilon, passes) {
        return TexelCause::Tie { other, dt };
    }
    let moved = jittered(x, y)
        .iter()
        .any(|&at| !useful_at(rays, hits, face, at, caster));
    if moved {
        TexelCause::Edge
    } else {
        TexelCause::Unexplained
    }
}

/// The passes in which a caster is useful on one ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct UsefulIn {
    all: bool,
    opaque: bool,
}

/// In which passes `caster` is useful on `ray`; leaves the ray's hits under
/// the light's own passes in `hits`.
fn passes_useful(
    rays: &LightRays,
    hits: &mut Vec<RayHit>,
    ray: &crate::light::TexelRay,
    caster: u32,
) -> UsefulIn {
    let all_only = LightRays {
        rules: RayRules {
            passes: Passes::AllOnly,
            ..rays.rules
        },
        ..*rays
    };
    let mut all = false;
    all_only.trace(ray, hits, |c| all |= c == caster);
    // A caster useful in both passes is reported twice.
    let mut reports = 0u32;
    rays.trace(ray, hits, |c| reports += u32::from(c == caster));
    UsefulIn {
        all,
        opaque: rays.rules.passes == Passes::AllAndOpaque && reports > u32::from(all),
    }
}

/// A hit of another caster within ε in front of `caster`'s (or level with
/// it to f32 precision) in *every* pass where `caster` is useful: the
/// Opaque pass (and the raster's Opaque variant) has no alpha-tested
/// groups, so an alpha-tested rival cannot explain a miss there. Returns
/// the rival and how far in front it is.
fn tie_rival(hits: &[RayHit], caster: u32, epsilon: f32, passes: UsefulIn) -> Option<(u32, f32)> {
    let own = hits.iter().find(|h| h.caster == caster)?;
    // f32 depth of equal surfaces may round either way: a hit level with
    // this one to a few ulps counts as in front.
    let level = own.t.abs() * 4.0 * f32::EPSILON;
    let rival = |opaque_pass: bool| {
        hits.iter().find(|h| {
            h.caster != caster
                && !h.receiver_only
                && !(opaque_pass && h.alpha_tested)
                && h.t >= own.t - epsilon
                && h.t <= own.t + level
        })
    };
    if !passes.all && !passes.opaque {
        return None;
    }
    let mut found = None;
    if passes.opaque {
        found = Some(rival(true)?);
    }
    if passes.all {
        found = Some(rival(false)?);
    }
    found.map(|h| (h.caster, own.t - h.t))
}

/// Texels where `candidates` are useful on some ray moved [`EDGE_JITTER`]
/// off a texel centre, per caster.
fn jitter_pass(rays: &LightRays, candidates: &[bool]) -> Vec<u64> {
    let grid = rays.grid;
    let n = rays.casters.len();
    let rows = grid.faces() as u64 * grid.height() as u64;
    (0..rows)
        .into_par_iter()
        .fold(
            || (vec![0u64; n], Vec::new(), Vec::new()),
            |(mut found, mut hits, mut seen), row| {
                let face = (row / grid.height() as u64) as usize;
                let y = (row % grid.height() as u64) as u32;
                for x in 0..grid.width() {
                    seen.clear();
                    for (cx, cy) in jittered(x, y) {
                        let ray = grid.ray_through(face, cx, cy);
                        rays.trace(&ray, &mut hits, |c| {
                            if candidates[c as usize] {
                                seen.push(c);
                            }
                        });
                    }
                    seen.sort_unstable();
                    seen.dedup();
                    for &c in &seen {
                        found[c as usize] += 1;
                    }
                }
                (found, hits, seen)
            },
        )
        .map(|(found, _, _)| found)
        .reduce(
            || vec![0; n],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(p, q)| *p += q);
                a
            },
        )
}

/// Traces every texel centre of every light like the bake does, counting
/// per caster the texels where it is useful.
pub fn ray_counts(world: &BakeWorld, config: &BakeConfig) -> RayCounts {
    let casters = &world.casters;
    let mut out = RayCounts {
        all: Vec::new(),
        any: Vec::new(),
        tied: Vec::new(),
        seconds: Vec::new(),
    };
    let nobody = vec![false; casters.len()];
    for light in 0..config.lights.len() {
        let started = std::time::Instant::now();
        let Ok(setup) = LightSetup::new(world, config, light) else {
            out.all.push(vec![0; casters.len()]);
            out.any.push(vec![0; casters.len()]);
            out.tied.push(0);
            out.seconds.push(0.0);
            continue;
        };
        let rays = setup.rays(world, config);
        let centre = centre_pass(&rays, &nobody);
        out.all.push(centre.all);
        out.any.push(centre.any);
        out.tied.push(centre.tied);
        out.seconds.push(started.elapsed().as_secs_f64());
    }
    out
}

/// Compares the two methods; `raster` must come from the same scene and
/// config.
pub fn compare(world: &BakeWorld, config: &BakeConfig, raster: &RasterResult) -> XcheckReport {
    let mut report = XcheckReport {
        pairs: 0,
        agreeing: 0,
        unexplained: 0,
        disagreements: Vec::new(),
        lights: Vec::new(),
        renderer: raster.renderer.clone(),
        counter: format!("{:?}", raster.counter),
        notes: raster.ground_note.iter().cloned().collect(),
    };
    for light in 0..config.lights.len() {
        compare_light(world, config, raster, light, &mut report);
    }
    report
}

/// Light `light`'s texel counts and its (caster, light) pairs, each
/// disagreement with its cause, added to `report`.
fn compare_light(
    world: &BakeWorld,
    config: &BakeConfig,
    raster: &RasterResult,
    light: usize,
    report: &mut XcheckReport,
) {
    let casters = &raster.casters;
    let started = std::time::Instant::now();
    let setup = LightSetup::new(world, config, light).ok();
    let light_name = config.lights[light].name.clone();
    let raster_useful: Vec<bool> = raster.masks.iter().map(|m| m & (1 << light) != 0).collect();
    let not_in_raster: Vec<bool> = raster_useful.iter().map(|u| !u).collect();
    let rays = setup.as_ref().map(|s| s.rays(world, config));
    let centre = match &rays {
        Some(rays) => centre_pass(rays, &not_in_raster),
        None => CentrePass {
            all: vec![0; casters.len()],
            any: vec![0; casters.len()],
            tied: 0,
            watched: Vec::new(),
        },
    };
    let ray_seconds = started.elapsed().as_secs_f64();
    report.lights.push(LightTexels {
        light,
        name: light_name.clone(),
        ray_cast: centre.all.iter().sum(),
        ray_cast_tied: centre.tied,
        raster: raster.texels.get(light).map_or(0, |t| t.iter().sum()),
        ray_seconds,
        raster_seconds: raster.seconds.get(light).copied().unwrap_or(0.0),
    });
    // Raster-only casters: one jittered pass for all of them.
    let raster_only: Vec<bool> = (0..casters.len())
        .map(|id| raster_useful[id] && centre.any[id] == 0 && !casters.casters[id].receiver_only)
        .collect();
    let jittered_found = match &rays {
        Some(rays) if raster_only.iter().any(|&b| b) => jitter_pass(rays, &raster_only),
        _ => vec![0; casters.len()],
    };
    let evidence = Evidence {
        scene: world.scene,
        casters,
        rays: rays.as_ref(),
        centre: &centre,
        jittered_found: &jittered_found,
    };
    let mut hits = Vec::new();
    for (id, caster) in casters.casters.iter().enumerate() {
        // Neither method traces a caster it cannot model.
        if caster.receiver_only || caster.is_unmodelled() {
            continue;
        }
        report.pairs += 1;
        let ray_n = centre.any[id];
        let ray = ray_n > 0;
        let ras = raster_useful[id];
        if ray == ras {
            report.agreeing += 1;
            continue;
        }
        let ras_all = raster.texels.get(light).map_or(0, |t| t[id]);
        let ras_opaque = raster.texels_opaque.get(light).map_or(0, |t| t[id]);
        let cause = evidence.cause(id, ray, (ras_all, ras_opaque), &mut hits);
        if cause.is_none() {
            report.unexplained += 1;
        }
        let (chunk, kind, index, group) = describe(world.scene, casters, id);
        report.disagreements.push(Disagreement {
            chunk,
            kind,
            index,
            group,
            light,
            light_name: light_name.clone(),
            ray_cast: ray,
            raster: ras,
            ray_texels: ray_n,
            raster_texels: ras_all.max(ras_opaque),
            cause,
        });
    }
}

/// What one light's re-tests found, to explain its disagreements by.
struct Evidence<'a> {
    scene: &'a Scene,
    casters: &'a CasterTable,
    /// `None`: the light reaches nothing.
    rays: Option<&'a LightRays<'a>>,
    centre: &'a CentrePass,
    /// Per caster, texels where rays off the centres find it useful (the
    /// raster-only casters alone).
    jittered_found: &'a [u64],
}

impl Evidence<'_> {
    /// Why caster `id` is useful to one method and not the other (`ray`:
    /// the ray cast's answer; `(all, opaque)`: the raster's samples in
    /// either variant); `None`: unexplained.
    fn cause(
        &self,
        id: usize,
        ray: bool,
        (ras_all, ras_opaque): (u64, u64),
        hits: &mut Vec<RayHit>,
    ) -> Option<String> {
        match (self.rays, ray) {
            (Some(rays), true) => {
                let watched = &self.centre.watched;
                let from = watched.partition_point(|&(c, _)| c < id as u32);
                let to = watched.partition_point(|&(c, _)| c <= id as u32);
                let causes: Vec<(Texel, TexelCause)> = watched[from..to]
                    .iter()
                    .map(|&(c, t)| (t, texel_cause(rays, hits, c, t)))
                    .collect();
                describe_ray_only(self.casters, self.scene, &causes)
            }
            // Each raster sample must have a near ray to back it.
            (Some(_), false) => (ras_all.max(ras_opaque) <= self.jittered_found[id]).then(|| {
                format!(
                    "edge: rays 1/{EDGE_JITTER_PER_TEXEL} texel off the centres find it useful at {} texel(s), \
                     the raster passes {} sample(s) (all groups {ras_all}, opaque groups {ras_opaque})",
                    self.jittered_found[id],
                    ras_all.max(ras_opaque)
                )
            }),
            (None, _) => None,
        }
    }
}

/// The cause of a ray-only disagreement from its texels' causes: explained
/// when every texel is.
fn describe_ray_only(
    casters: &CasterTable,
    scene: &Scene,
    causes: &[(Texel, TexelCause)],
) -> Option<String> {
    if causes.is_empty() || causes.iter().any(|(_, c)| *c == TexelCause::Unexplained) {
        return None;
    }
    let ties: Vec<&(Texel, TexelCause)> = causes
        .iter()
        .filter(|(_, c)| matches!(c, TexelCause::Tie { .. }))
        .collect();
    let edges = causes.len() - ties.len();
    let mut parts = Vec::new();
    if let Some(&&((face, x, y), TexelCause::Tie { other, dt })) = ties.first() {
        let (chunk, kind, index, group) = describe(scene, casters, other as usize);
        let whom = match (index, group) {
            (Some(i), Some(g)) => format!("{chunk} {kind} {i} group {g}"),
            _ => format!("{chunk} {kind}"),
        };
        parts.push(format!(
            "tie at {} texel(s): another caster's hit within ε in front (e.g. texel {face}/{x},{y}: {whom}, {dt:.2e} m), which LEQUAL on one depth does not keep",
            ties.len()
        ));
    }
    if edges > 0 {
        parts.push(format!(
            "edge at {edges} texel(s): rays 1/{EDGE_JITTER_PER_TEXEL} texel off the centre answer otherwise"
        ));
    }
    Some(parts.join("; "))
}

fn describe(
    scene: &Scene,
    casters: &CasterTable,
    id: usize,
) -> (String, &'static str, Option<usize>, Option<usize>) {
    match casters.casters[id].owner {
        Owner::Group {
            instance, group, ..
        } => {
            let inst = &scene.instances[instance as usize];
            let kind = match inst.kind {
                crate::formats::chunk::InstanceKind::SpeedTree => "speedtree",
                _ => "model",
            };
            (
                scene.chunks[inst.chunk].name.clone(),
                kind,
                Some(inst.index),
                Some(group as usize),
            )
        }
        Owner::Unmodelled { instance } => {
            let tree = &scene.instances[instance as usize];
            (
                scene.chunks[tree.chunk].name.clone(),
                "speedtree",
                Some(tree.index),
                None,
            )
        }
        Owner::Terrain { block } => {
            let chunk = scene
                .chunks
                .iter()
                .find(|c| c.terrain == Some(block as usize))
                .map_or_else(|| format!("terrain block {block}"), |c| c.name.clone());
            (chunk, "terrain", None, None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(t: f32, caster: u32, alpha_tested: bool) -> RayHit {
        RayHit {
            t,
            caster,
            receiver_only: false,
            alpha_tested,
        }
    }

    const ALL: UsefulIn = UsefulIn {
        all: true,
        opaque: false,
    };
    const BOTH: UsefulIn = UsefulIn {
        all: true,
        opaque: true,
    };
    const OPAQUE: UsefulIn = UsefulIn {
        all: false,
        opaque: true,
    };

    #[test]
    fn an_alpha_tested_rival_ties_only_in_the_all_pass() {
        // Caster 2 at 10 m, alpha-tested caster 1 5e-5 m in front.
        let hits = [hit(10.0 - 5e-5, 1, true), hit(10.0, 2, false)];
        assert_eq!(tie_rival(&hits, 2, 1e-4, ALL).map(|r| r.0), Some(1));
        assert_eq!(tie_rival(&hits, 2, 1e-4, OPAQUE), None);
        assert_eq!(tie_rival(&hits, 2, 1e-4, BOTH), None);
        // An opaque rival explains both passes.
        let hits = [hit(10.0 - 5e-5, 3, false), hit(10.0, 2, false)];
        assert_eq!(tie_rival(&hits, 2, 1e-4, BOTH).map(|r| r.0), Some(3));
        // Beyond ε, or useful in no pass: no tie.
        let hits = [hit(10.0 - 2e-4, 3, false), hit(10.0, 2, false)];
        assert_eq!(tie_rival(&hits, 2, 1e-4, BOTH), None);
        let none = UsefulIn {
            all: false,
            opaque: false,
        };
        assert_eq!(tie_rival(&hits, 2, 1.0, none), None);
    }
}
