//! `shadowcull explain`: why one caster is kept or culled for one light.
//! A reviewer sees a verdict per caster and cannot tell why; this traces
//! the light's grid rays (the bake's own texel rays, hit filter and rules,
//! through [`LightSetup::rays`]) with every hit kept, and counts for the
//! caster where it is the front hit, where that proves it useful
//! (docs/contract.md §4), who hides it, and what its rays meet after it.
//! The explanation's verdict is checked against a plain bake of the light:
//! they must agree, so a disagreement is a bug, not a matter of opinion.
//! [`picture`] draws the same counts texel by texel over `render`'s map.

use crate::bake::casters::{Caster, CasterTable, Owner};
use crate::bake::setup::{BakeWorld, LightSetup, NoSetup};
use crate::bake::trace_light::{tile_rect, CasterSet, HitFate, LightRays};
use crate::bake::{self, BakeConfig, GridMode, Silent};
use crate::classify::{self, Passes, RayHit};
use crate::formats::chunk::InstanceKind;
use crate::light::GridError;
use crate::render::{self, Picture, RenderError, TexelMark};
use crate::scene::Scene;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;

/// Hiders listed by name, most texels first; the rest are counted.
pub const TOP_HIDERS: usize = 5;

/// Which caster(s) to explain, as `--caster` names them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    /// The chunk file's name without extension.
    pub chunk: String,
    pub item: TargetItem,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TargetItem {
    Terrain,
    /// A `<model>`/`<shell>` (or with `speedtree`, a `<speedtree>`) at
    /// `index` among the chunk's elements of its kind; `group`: position
    /// among the instance's groups in report order, `None`: every group.
    Instance {
        speedtree: bool,
        index: usize,
        group: Option<usize>,
    },
}

impl std::str::FromStr for Target {
    type Err = String;

    /// `CHUNK:terrain`, `CHUNK:INDEX[:GROUP]` or
    /// `CHUNK:speedtree:INDEX[:GROUP]`.
    fn from_str(text: &str) -> Result<Target, String> {
        let fields: Vec<&str> = text.split(':').collect();
        let number = |s: &str, what: &str| {
            s.parse::<usize>()
                .map_err(|_| format!("{what} `{s}` is not a whole number (in `{text}`)"))
        };
        let (chunk, rest) = match fields.split_first() {
            Some((chunk, rest)) if !chunk.is_empty() && !rest.is_empty() => (*chunk, rest),
            _ => {
                return Err(format!(
                    "expected CHUNK:INDEX[:GROUP] or CHUNK:terrain, got `{text}`"
                ))
            }
        };
        let (speedtree, rest) = match rest {
            ["terrain"] => {
                return Ok(Target {
                    chunk: chunk.to_string(),
                    item: TargetItem::Terrain,
                })
            }
            ["speedtree", rest @ ..] => (true, rest),
            _ => (false, rest),
        };
        let (index, group) = match rest {
            [index] => (number(index, "INDEX")?, None),
            [index, group] => (number(index, "INDEX")?, Some(number(group, "GROUP")?)),
            _ => {
                return Err(format!(
                    "expected CHUNK:INDEX[:GROUP] or CHUNK:terrain, got `{text}`"
                ))
            }
        };
        Ok(Target {
            chunk: chunk.to_string(),
            item: TargetItem::Instance {
                speedtree,
                index,
                group,
            },
        })
    }
}

/// Why a light or caster cannot be explained. The caller names the
/// settings file.
#[derive(Debug, thiserror::Error)]
pub enum ExplainError {
    #[error("no light `{name}`: the lights are {}", .known.join(", "))]
    UnknownLight { name: String, known: Vec<String> },
    #[error("no chunk `{name}` in the space ({count} chunks, `{first}` to `{last}`)")]
    UnknownChunk {
        name: String,
        count: usize,
        first: String,
        last: String,
    },
    #[error("chunk `{chunk}` has {count} {what} elements: INDEX must be 0 to {}, not {index}", .count.saturating_sub(1))]
    IndexOutOfRange {
        chunk: String,
        what: &'static str,
        index: usize,
        count: usize,
    },
    #[error("`{name}` is not in the bake: the instance was left out when the world loaded (`shadowcull inspect` names why)")]
    LeftOut { name: String },
    #[error("`{name}` has {count} groups: GROUP must be 0 to {}, not {group}", .count.saturating_sub(1))]
    GroupOutOfRange {
        name: String,
        group: usize,
        count: usize,
    },
    #[error("chunk `{chunk}` has no terrain block")]
    NoTerrain { chunk: String },
    #[error(transparent)]
    Grid(#[from] GridError),
}

/// The index of the light called `name`, or an error listing them.
pub fn find_light(config: &BakeConfig, name: &str) -> Result<usize, ExplainError> {
    let lights = &config.lights;
    lights
        .iter()
        .position(|l| l.name == name)
        .ok_or_else(|| ExplainError::UnknownLight {
            name: name.to_string(),
            known: lights.iter().map(|l| l.name.clone()).collect(),
        })
}

/// The caster ids `target` names.
pub fn resolve(
    scene: &Scene,
    casters: &CasterTable,
    target: &Target,
) -> Result<Vec<u32>, ExplainError> {
    let Some(chunk_index) = scene.chunks.iter().position(|c| c.name == target.chunk) else {
        let name = |i: Option<&crate::scene::Chunk>| i.map_or(String::new(), |c| c.name.clone());
        return Err(ExplainError::UnknownChunk {
            name: target.chunk.clone(),
            count: scene.chunks.len(),
            first: name(scene.chunks.first()),
            last: name(scene.chunks.last()),
        });
    };
    let chunk = &scene.chunks[chunk_index];
    let (speedtree, index, group) = match target.item {
        TargetItem::Terrain => {
            let block = chunk.terrain.ok_or_else(|| ExplainError::NoTerrain {
                chunk: chunk.name.clone(),
            })?;
            return Ok(vec![casters.of_block[block]]);
        }
        TargetItem::Instance {
            speedtree,
            index,
            group,
        } => (speedtree, index, group),
    };
    let (count, what) = if speedtree {
        (chunk.speedtree_elements, "<speedtree>")
    } else {
        (chunk.instance_elements, "<model>/<shell>")
    };
    if index >= count {
        return Err(ExplainError::IndexOutOfRange {
            chunk: chunk.name.clone(),
            what,
            index,
            count,
        });
    }
    let name = target_name(&chunk.name, speedtree, index);
    let found = chunk.instances.clone().find(|&i| {
        let instance = &scene.instances[i];
        instance.index == index && (instance.kind == InstanceKind::SpeedTree) == speedtree
    });
    let ids = found.map_or(0..0, |i| casters.of_instance(scene, i));
    if ids.is_empty() {
        return Err(ExplainError::LeftOut { name });
    }
    match group {
        None => Ok(ids.collect()),
        Some(group) if group < ids.len() => Ok(vec![ids.start + group as u32]),
        Some(group) => Err(ExplainError::GroupOutOfRange {
            name,
            group,
            count: ids.len(),
        }),
    }
}

fn target_name(chunk: &str, speedtree: bool, index: usize) -> String {
    match speedtree {
        true => format!("{chunk}:speedtree:{index}"),
        false => format!("{chunk}:{index}"),
    }
}

/// A caster as `--caster` names it: `CHUNK:INDEX:GROUP`,
/// `CHUNK:speedtree:INDEX:GROUP` or `CHUNK:terrain`.
pub fn caster_name(scene: &Scene, casters: &CasterTable, id: u32) -> String {
    match casters.casters[id as usize].owner {
        Owner::Group { instance, .. } => {
            let placed = &scene.instances[instance as usize];
            let first = casters.first_of_instance[instance as usize].unwrap_or(id);
            let speedtree = placed.kind == InstanceKind::SpeedTree;
            let chunk = &scene.chunks[placed.chunk].name;
            format!(
                "{}:{}",
                target_name(chunk, speedtree, placed.index),
                id - first
            )
        }
        Owner::Terrain { block } => {
            let chunk = scene
                .chunks
                .iter()
                .find(|c| c.terrain == Some(block as usize));
            format!("{}:terrain", chunk.map_or("?", |c| c.name.as_str()))
        }
        Owner::Unmodelled { instance } => {
            let tree = &scene.instances[instance as usize];
            target_name(&scene.chunks[tree.chunk].name, true, tree.index)
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Useful,
    Culled,
}

impl Verdict {
    fn of(useful: bool) -> Verdict {
        if useful {
            Verdict::Useful
        } else {
            Verdict::Culled
        }
    }

    pub fn word(self) -> &'static str {
        match self {
            Verdict::Useful => "useful",
            Verdict::Culled => "culled",
        }
    }
}

/// The grid pass's reason for its verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Reason {
    /// The front hit with something behind it at some texel.
    SomethingBehind,
    /// A speedtree without a proxy: kept for every light.
    Unmodelled,
    /// `castsShadow` false: a receiver, never a caster.
    ReceiverOnly,
    /// The light's grid reaches nothing at all.
    LightReachesNothing,
    /// Its box lies outside the light's reach.
    OutOfReach,
    /// No texel ray meets it (between rays, smaller than a texel, or
    /// beyond a spot or point light's near..far range).
    NeverHit,
    /// Rays meet it, but every such hit faces away or lies below ground.
    HitsDropped,
    /// Never the front hit: nearer casters hide it at every texel.
    Hidden,
    /// The front hit at some texels, with nothing behind that counts.
    NothingBehind,
}

impl Reason {
    pub fn words(self) -> &'static str {
        match self {
            Reason::SomethingBehind => "it is the front hit with something behind it",
            Reason::Unmodelled => {
                "a speedtree without a proxy: kept for every light (docs/contract.md §4)"
            }
            Reason::ReceiverOnly => "castsShadow is false: a receiver only, never a caster",
            Reason::LightReachesNothing => "the light reaches no geometry",
            Reason::OutOfReach => "it lies outside the light's reach",
            Reason::NeverHit => {
                "no texel ray meets it (between rays, smaller than a texel, or outside the light's near..far range)"
            },
            Reason::HitsDropped => {
                "every ray that meets it meets a face turned away or a point below ground"
            }
            Reason::Hidden => "hidden: nearer casters are the front hit wherever its rays meet it",
            Reason::NothingBehind => "nothing that counts lies behind it where it is the front hit",
        }
    }
}

/// Texels where the caster is the front hit but not useful, by what its
/// ray meets after it (one class a texel, the first that applies).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Behind {
    /// Alpha-tested groups of casters: they drop out of the Opaque pass.
    pub alpha_tested: u64,
    /// Alpha-tested groups of receiver-only instances: out of the Opaque
    /// pass too.
    pub receiver_only_alpha_tested: u64,
    /// Hits below the terrain surface (ignored).
    pub below_ground: u64,
    /// Faces turned away from the light (face culling).
    pub facing_away: u64,
    /// No hit at all (within the light's range).
    pub nothing: u64,
}

impl Behind {
    fn add(&mut self, other: &Behind) {
        self.alpha_tested += other.alpha_tested;
        self.receiver_only_alpha_tested += other.receiver_only_alpha_tested;
        self.below_ground += other.below_ground;
        self.facing_away += other.facing_away;
        self.nothing += other.nothing;
    }
}

/// A nearer caster and the texels where it hides the target.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Hider {
    pub caster: String,
    pub texels: u64,
}

/// One caster's texel counts over the light's grid (rays, when
/// supersampled).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Texels {
    /// Rays with a hit on it that reaches the rules.
    pub hit: u64,
    /// Where it is in some pass's front set.
    pub front: u64,
    /// Of `front`, where the rules prove it useful.
    pub useful: u64,
    /// Where it is hit but never in front.
    pub hidden: u64,
    /// Nearer casters, most texels first (at most [`TOP_HIDERS`]).
    pub hidden_by: Vec<Hider>,
    /// Texels of `hidden` whose hiders are not listed.
    pub hidden_by_others: u64,
    /// Of `front − useful`, what lies behind it.
    pub behind: Behind,
    /// Rays meeting it only where the filter drops the hit: below ground.
    pub dropped_below_ground: u64,
    /// ... or only on faces turned away.
    pub dropped_facing_away: u64,
}

/// One caster's verdicts and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CasterExplanation {
    /// As `--caster` names it.
    pub caster: String,
    /// Its id in the bake's caster table.
    pub id: u32,
    pub resource: Option<String>,
    pub alpha_tested: bool,
    pub receiver_only: bool,
    /// The grid pass's verdict, from the counts below.
    pub grid_verdict: Verdict,
    pub reason: Reason,
    /// A bake's verdict with the modes asked (`--filter-radius`,
    /// `--conservative`, `--refine`).
    pub bake_verdict: Verdict,
    /// When the bake keeps what the grid pass culls: the rule that kept it.
    pub kept_by: Option<&'static str>,
    /// The explanation and the bake disagree: a bug.
    pub disagrees: bool,
    pub texels: Texels,
}

/// `explain` for one light.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Explanation {
    pub light: String,
    pub kind: &'static str,
    /// Grid size: faces × width × height texels.
    pub texels: u64,
    /// `all` or `all_and_opaque`.
    pub passes: &'static str,
    /// Rays per texel side of the grid pass (`--supersample`): the
    /// counts are of rays.
    pub supersample: u32,
    /// The modes the bake verdict was computed with.
    pub refine: bool,
    pub conservative: bool,
    /// `--filter-radius` (0: none).
    pub filter_radius: u32,
    pub casters: Vec<CasterExplanation>,
}

impl Explanation {
    /// Any caster whose explanation and bake verdict disagree.
    pub fn disagrees(&self) -> bool {
        self.casters.iter().any(|c| c.disagrees)
    }
}

/// Explains casters `ids` for light `light` of `config`. The grid pass is
/// traced with `config`'s rules at texel centres (`supersample`² rays a
/// texel); the bake verdict uses `config` whole, so the filter margin, the
/// conservative mode and refinement are reported as the rule that kept a
/// caster the grid pass culls.
pub fn explain(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    ids: &[u32],
) -> Result<Explanation, ExplainError> {
    let settings = &config.lights[light];
    let grid_config = grid_config(config);
    let setup = match LightSetup::new(world, &grid_config, light) {
        Ok(setup) => Some(setup),
        Err(nothing) if nothing.is_nothing_to_trace() => None,
        Err(NoSetup::Grid(err)) => return Err(err.into()),
        Err(NoSetup::NoGeometry) => None,
    };
    let tallies = match &setup {
        Some(setup) => trace(
            &setup.rays(world, &grid_config),
            grid_config.supersample,
            ids,
        ),
        None => vec![Tally::default(); ids.len()],
    };
    let baked = BakeVerdicts::new(world, setup.as_ref(), config, &grid_config);
    let casters = ids
        .iter()
        .zip(tallies)
        .map(|(&id, tally)| {
            let caster = &world.casters.casters[id as usize];
            let reason = reason(world, setup.as_ref(), id, caster, &tally);
            let grid_useful = matches!(reason, Reason::SomethingBehind | Reason::Unmodelled);
            let (plain_useful, bake_useful, kept_by) = baked.of(world, id);
            let disagrees = grid_useful != plain_useful || (plain_useful && !bake_useful);
            CasterExplanation {
                caster: caster_name(world.scene, &world.casters, id),
                id,
                resource: resource_of(world.scene, caster),
                alpha_tested: caster.alpha_tested,
                receiver_only: caster.receiver_only,
                grid_verdict: Verdict::of(grid_useful),
                reason,
                bake_verdict: Verdict::of(bake_useful),
                kept_by,
                disagrees,
                texels: tally.texels(world.scene, &world.casters),
            }
        })
        .collect();
    let texels = setup.as_ref().map_or(0, |s| {
        s.grid.faces() as u64 * u64::from(s.grid.width()) * u64::from(s.grid.height())
    });
    Ok(Explanation {
        light: settings.name.clone(),
        kind: settings.kind.type_name(),
        texels,
        passes: match setup.as_ref().map(|s| s.passes) {
            Some(Passes::AllAndOpaque) => "all_and_opaque",
            _ => "all",
        },
        supersample: grid_config.supersample.max(1),
        refine: config.refine_samples > 0 || config.refine_density > 0,
        conservative: config.grid_mode == GridMode::Conservative,
        filter_radius: config.filter_radius,
        casters,
    })
}

/// The grid pass `explain` counts: `config`'s rules and supersampling at
/// texel centres, without the modes that keep more.
fn grid_config(config: &BakeConfig) -> BakeConfig {
    BakeConfig {
        refine_samples: 0,
        refine_density: 0,
        grid_mode: GridMode::Centres,
        filter_radius: 0,
        ..config.clone()
    }
}

/// The light's map (`render`'s light view, in grey) with the texels of
/// casters `ids` marked as [`explain`] counts them: the same rays, filter
/// and rules, texel by texel. A texel of several rays (supersampling) or
/// several targets shows its best mark (useful, then nothing behind, then
/// hidden); with one ray a texel drawn 1:1, each mark's pixels equal the
/// explanation's `useful`, `front − useful` and `hidden`.
pub fn picture(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    ids: &[u32],
    max_size: Option<(u32, u32)>,
) -> Result<Picture, RenderError> {
    let grid_config = grid_config(config);
    // Without a setup the light reaches nothing, and the render says so.
    let setup = LightSetup::new(world, &grid_config, light).ok();
    let rays = setup.as_ref().map(|s| s.rays(world, &grid_config));
    let slot = slots(world.casters.len(), ids);
    let samples = grid_config.supersample;
    let marker = |face: usize, x: u32, y: u32| {
        let rays = rays.as_ref()?;
        let mut tallies = vec![Tally::default(); ids.len()];
        let mut scratch = RayHits::default();
        trace_texel(
            rays,
            samples,
            &slot,
            (face, x, y),
            &mut scratch,
            &mut tallies,
        );
        let sum = |count: fn(&Tally) -> u64| tallies.iter().map(count).sum::<u64>();
        if sum(|t| t.useful) > 0 {
            Some(TexelMark::Useful)
        } else if sum(|t| t.front) > 0 {
            Some(TexelMark::NothingBehind)
        } else if sum(|t| t.hidden) > 0 {
            Some(TexelMark::Hidden)
        } else {
            None
        }
    };
    render::light_view_marked(
        world,
        &grid_config,
        light,
        max_size,
        render::Source::Bake,
        &marker,
    )
}

/// The bake's verdicts for one light: a plain grid pass, then one bake per
/// mode `config` asks for, each adding its mode to the one before in the
/// order the bake applies them (the filter margin and the conservative
/// beams in the grid pass, then refinement), the last being `config`
/// whole.
struct BakeVerdicts {
    plain: Option<CasterSet>,
    /// Per mode asked: the rule it adds and the bake with it.
    rungs: Vec<(&'static str, Option<CasterSet>)>,
}

impl BakeVerdicts {
    fn new(
        world: &BakeWorld,
        setup: Option<&LightSetup>,
        config: &BakeConfig,
        grid_config: &BakeConfig,
    ) -> BakeVerdicts {
        let bake_with = |config: &BakeConfig| {
            // The modes change how the light is traced, never its setup.
            let baked = |setup| bake::bake_light(world, setup, config, &Silent, &mut Vec::new()).0;
            setup.map(baked)
        };
        let mut rungs = Vec::new();
        let mut step = grid_config.clone();
        if config.filter_radius > 0 {
            step.filter_radius = config.filter_radius;
            rungs.push(("the filter margin", bake_with(&step)));
        }
        if config.grid_mode == GridMode::Conservative {
            step.grid_mode = GridMode::Conservative;
            rungs.push(("the conservative grid pass", bake_with(&step)));
        }
        if config.refine_samples > 0 || config.refine_density > 0 {
            rungs.push(("refinement", bake_with(config)));
        }
        BakeVerdicts {
            plain: bake_with(grid_config),
            rungs,
        }
    }

    /// Caster `id`: useful in the plain bake, useful in the bake `config`
    /// asks for, and the first mode that kept it when only the modes do.
    fn of(&self, world: &BakeWorld, id: u32) -> (bool, bool, Option<&'static str>) {
        let useful_in = |set: &Option<CasterSet>| {
            let caster = &world.casters.casters[id as usize];
            caster.is_unmodelled() || set.as_ref().is_some_and(|s| s.contains(id))
        };
        let plain = useful_in(&self.plain);
        let Some((_, last)) = self.rungs.last() else {
            return (plain, plain, None);
        };
        let useful = useful_in(last);
        let kept_by = (useful && !plain)
            .then(|| self.rungs.iter().find(|(_, set)| useful_in(set)))
            .flatten()
            .map(|(rule, _)| *rule);
        (plain, useful, kept_by)
    }
}

fn resource_of(scene: &Scene, caster: &Caster) -> Option<String> {
    let (instance, part) = match caster.owner {
        Owner::Group { instance, part, .. } => (instance, part as usize),
        Owner::Unmodelled { instance } => (instance, 0),
        Owner::Terrain { .. } => return None,
    };
    let resources = &scene.instances[instance as usize].resources;
    resources.get(part).map(|r| r.trim().to_string())
}

/// The verdict's reason from the counts.
fn reason(
    world: &BakeWorld,
    setup: Option<&LightSetup>,
    id: u32,
    caster: &Caster,
    tally: &Tally,
) -> Reason {
    if caster.is_unmodelled() {
        return Reason::Unmodelled;
    }
    if caster.receiver_only {
        return Reason::ReceiverOnly;
    }
    let Some(setup) = setup.filter(|s| !s.top.is_empty()) else {
        return Reason::LightReachesNothing;
    };
    if tally.useful > 0 {
        Reason::SomethingBehind
    } else if tally.front > 0 {
        Reason::NothingBehind
    } else if tally.hidden > 0 {
        Reason::Hidden
    } else if tally.dropped_below_ground + tally.dropped_facing_away > 0 {
        Reason::HitsDropped
    } else if in_reach(world, setup, id, caster) {
        Reason::NeverHit
    } else {
        Reason::OutOfReach
    }
}

/// Whether caster `id`'s part or block is in the light's top level.
fn in_reach(world: &BakeWorld, setup: &LightSetup, id: u32, caster: &Caster) -> bool {
    match caster.owner {
        Owner::Terrain { block } => setup.reach.blocks.contains(&block),
        _ => setup.reach.parts.iter().any(|&p| {
            let part = &world.parts[p as usize];
            let groups = world.scene.models[part.model].groups.len() as u32;
            (part.first_caster..part.first_caster + groups).contains(&id)
        }),
    }
}

/// One caster's counts while tracing.
#[derive(Debug, Clone, Default)]
struct Tally {
    hit: u64,
    front: u64,
    useful: u64,
    hidden: u64,
    hidden_by: HashMap<u32, u64>,
    behind: Behind,
    dropped_below_ground: u64,
    dropped_facing_away: u64,
}

impl Tally {
    fn add(&mut self, other: &Tally) {
        self.hit += other.hit;
        self.front += other.front;
        self.useful += other.useful;
        self.hidden += other.hidden;
        for (&c, &n) in &other.hidden_by {
            *self.hidden_by.entry(c).or_default() += n;
        }
        self.behind.add(&other.behind);
        self.dropped_below_ground += other.dropped_below_ground;
        self.dropped_facing_away += other.dropped_facing_away;
    }

    fn texels(&self, scene: &Scene, casters: &CasterTable) -> Texels {
        let mut hiders: Vec<(u32, u64)> = self.hidden_by.iter().map(|(&c, &n)| (c, n)).collect();
        hiders.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        let listed = hiders.len().min(TOP_HIDERS);
        Texels {
            hit: self.hit,
            front: self.front,
            useful: self.useful,
            hidden: self.hidden,
            hidden_by: hiders[..listed]
                .iter()
                .map(|&(c, texels)| Hider {
                    caster: caster_name(scene, casters, c),
                    texels,
                })
                .collect(),
            hidden_by_others: hiders[listed..].iter().map(|h| h.1).sum(),
            behind: self.behind,
            dropped_below_ground: self.dropped_below_ground,
            dropped_facing_away: self.dropped_facing_away,
        }
    }
}

/// One ray's hits: those the rules see, sorted, and those the filter
/// dropped.
#[derive(Default)]
struct RayHits {
    kept: Vec<RayHit>,
    dropped: Vec<(f32, u32, HitFate)>,
}

/// Per caster id: its index in `ids`, or `u32::MAX`.
fn slots(casters: usize, ids: &[u32]) -> Vec<u32> {
    let mut slot = vec![u32::MAX; casters];
    for (i, &id) in ids.iter().enumerate() {
        slot[id as usize] = i as u32;
    }
    slot
}

/// Every ray of the grid, its hits tallied for the casters `ids`.
fn trace(rays: &LightRays, samples: u32, ids: &[u32]) -> Vec<Tally> {
    let slot = slots(rays.casters.len(), ids);
    let grid = rays.grid;
    (0..rays.tile_count())
        .into_par_iter()
        .fold(
            || (vec![Tally::default(); ids.len()], RayHits::default()),
            |(mut tallies, mut scratch), tile| {
                let (face, x0, y0, x1, y1) = tile_rect(grid, tile);
                if !rays.tiles.may_hit((x0, y0, x1, y1)) {
                    return (tallies, scratch);
                }
                for y in y0..y1 {
                    for x in x0..x1 {
                        let texel = (face, x, y);
                        trace_texel(rays, samples, &slot, texel, &mut scratch, &mut tallies);
                    }
                }
                (tallies, scratch)
            },
        )
        .map(|(tallies, _)| tallies)
        .reduce(
            || vec![Tally::default(); ids.len()],
            |mut a, b| {
                for (a, b) in a.iter_mut().zip(&b) {
                    a.add(b);
                }
                a
            },
        )
}

/// The rays of texel `(face, x, y)`, their hits tallied for the casters
/// `slot` names: the one path of both the counts and the picture.
fn trace_texel(
    rays: &LightRays,
    samples: u32,
    slot: &[u32],
    (face, x, y): (usize, u32, u32),
    scratch: &mut RayHits,
    tallies: &mut [Tally],
) {
    for ray in rays.grid.texel_rays(face, x, y, samples.max(1)) {
        scratch.kept.clear();
        scratch.dropped.clear();
        rays.every_hit(&ray, |hit, fate| match fate {
            HitFate::Kept(kept) => scratch.kept.push(kept),
            HitFate::Unknown => {}
            dropped => scratch.dropped.push((hit.t, hit.caster, dropped)),
        });
        classify::sort_hits(&mut scratch.kept);
        tally_ray(rays, scratch, slot, tallies);
    }
}

/// One pass's front: the nearest caster hit's distance and caster.
#[derive(Clone, Copy)]
struct Front {
    t1: f32,
    nearest: u32,
    alpha_only: bool,
}

/// The front of each pass of `which` over `kept` (sorted): All, then
/// Opaque; `None` where the pass has no caster hit.
fn fronts(kept: &[RayHit], which: Passes) -> [Option<Front>; 2] {
    let front = |alpha_only: bool| {
        kept.iter()
            .find(|h| !h.receiver_only && (!alpha_only || !h.alpha_tested))
            .map(|h| Front {
                t1: h.t,
                nearest: h.caster,
                alpha_only,
            })
    };
    match which {
        Passes::AllOnly => [front(false), None],
        Passes::AllAndOpaque => [front(false), front(true)],
    }
}

/// Adds one ray's hits to the tallies of the targets it meets.
fn tally_ray(rays: &LightRays, hits: &RayHits, slot: &[u32], tallies: &mut [Tally]) {
    let target = |c: u32| Some(slot[c as usize]).filter(|&s| s != u32::MAX);
    let met: Vec<u32> = {
        let mut met: Vec<u32> = hits.kept.iter().map(|h| h.caster).collect();
        met.extend(hits.dropped.iter().map(|d| d.1));
        met.retain(|&c| target(c).is_some());
        met.sort_unstable();
        met.dedup();
        met
    };
    if met.is_empty() {
        return;
    }
    let epsilon = rays.rules.tie_epsilon;
    let which = rays.rules.passes;
    let mut useful = Vec::new();
    classify::classify_ray(&hits.kept, epsilon, which, |c| useful.push(c));
    let fronts = fronts(&hits.kept, which);
    for c in met {
        let tally = &mut tallies[target(c).unwrap_or_default() as usize];
        let Some(first) = hits.kept.iter().find(|h| h.caster == c) else {
            let below = hits
                .dropped
                .iter()
                .any(|d| d.1 == c && d.2 == HitFate::BelowGround);
            if below {
                tally.dropped_below_ground += 1;
            } else {
                tally.dropped_facing_away += 1;
            }
            continue;
        };
        tally.hit += 1;
        if first.receiver_only {
            continue;
        }
        let in_pass = |f: &Front| !f.alpha_only || !first.alpha_tested;
        let is_front = fronts
            .iter()
            .flatten()
            .any(|f| in_pass(f) && first.t <= f.t1 + epsilon);
        if !is_front {
            tally.hidden += 1;
            // The last pass it takes part in: the Opaque pass's nearest
            // caster is what truly hides an opaque caster.
            let hider = fronts.iter().flatten().rev().find(|f| in_pass(f));
            if let Some(f) = hider {
                *tally.hidden_by.entry(f.nearest).or_default() += 1;
            }
            continue;
        }
        tally.front += 1;
        if useful.contains(&c) {
            tally.useful += 1;
            continue;
        }
        let behind = |h: &&RayHit| h.caster != c && h.t >= first.t - epsilon;
        let alpha = |receiver: bool| {
            hits.kept
                .iter()
                .filter(behind)
                .any(|h| h.alpha_tested && h.receiver_only == receiver)
        };
        let dropped = |fate: HitFate| hits.dropped.iter().any(|d| d.0 > first.t && d.2 == fate);
        let class = &mut tally.behind;
        if alpha(false) {
            class.alpha_tested += 1;
        } else if alpha(true) {
            class.receiver_only_alpha_tested += 1;
        } else if dropped(HitFate::BelowGround) {
            class.below_ground += 1;
        } else if dropped(HitFate::FacingAway) {
            class.facing_away += 1;
        } else {
            class.nothing += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn instance(chunk: &str, index: usize, group: Option<usize>) -> Target {
        Target {
            chunk: chunk.into(),
            item: TargetItem::Instance {
                speedtree: false,
                index,
                group,
            },
        }
    }

    #[test]
    fn caster_names_parse_in_every_form() {
        let parse = |s: &str| s.parse::<Target>();
        assert_eq!(parse("00000000o:3"), Ok(instance("00000000o", 3, None)));
        assert_eq!(parse("a:3:1"), Ok(instance("a", 3, Some(1))));
        assert_eq!(
            parse("a:terrain").unwrap().item,
            TargetItem::Terrain,
            "terrain"
        );
        assert_eq!(
            parse("a:speedtree:2:0").unwrap().item,
            TargetItem::Instance {
                speedtree: true,
                index: 2,
                group: Some(0)
            }
        );
        for bad in [
            "",
            "a",
            ":3",
            "a:",
            "a:x",
            "a:3:y",
            "a:1:2:3",
            "a:-1",
            "a:terrain:1",
        ] {
            assert!(parse(bad).is_err(), "`{bad}` refused");
        }
    }
}
