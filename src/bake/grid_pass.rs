//! The grid pass of one light over a range of tiles, as the config asks:
//! texel centres (docs/contract.md §4), with the filter margin, or texel beams
//! (`--conservative`). One entry point for the bake, the shards and the
//! plan's sample, so a shard traces exactly what one bake traces.

use super::config::{BakeConfig, GridMode};
use super::setup::{BakeWorld, LightSetup};
use super::trace_light::{CasterSet, LightRays, PacketSkip, RayCounter};
use super::{conservative, filter_margin};
use rayon::prelude::*;

/// The casters the grid rays of `tiles` prove useful (receiver-only ones
/// included; the caller drops them), less some of those in `known` (the
/// caller ORs it in): centre rays leave out the packets that can only
/// prove casters already proven ([`PacketSkip::Settled`]). The union over
/// a partition of the light's tiles is the same whatever the partition.
pub fn trace_tiles(
    world: &BakeWorld,
    setup: &LightSetup,
    rays: &LightRays<'_>,
    config: &BakeConfig,
    tiles: impl IntoParallelIterator<Item = u64>,
    known: Option<&CasterSet>,
    rays_done: &dyn RayCounter,
) -> CasterSet {
    GridPass::new(world, setup, rays, config).trace(tiles, known, rays_done)
}

/// One light's grid pass as the config asks, prepared once for any number
/// of tile sets (the bake cache traces it cell by cell).
pub struct GridPass<'p, 'a> {
    rays: &'p LightRays<'p>,
    config: &'p BakeConfig,
    /// `--conservative`: the light's beams, its geometry binned by tile.
    beams: Option<conservative::Beams<'p, 'a>>,
}

impl<'p, 'a> GridPass<'p, 'a> {
    pub fn new(
        world: &'p BakeWorld<'a>,
        setup: &'p LightSetup,
        rays: &'p LightRays<'p>,
        config: &'p BakeConfig,
    ) -> Self {
        let beams = (config.grid_mode == GridMode::Conservative)
            .then(|| conservative::Beams::new(world, setup, rays, config));
        GridPass {
            rays,
            config,
            beams,
        }
    }

    /// [`trace_tiles`] over `tiles`.
    pub fn trace(
        &self,
        tiles: impl IntoParallelIterator<Item = u64>,
        known: Option<&CasterSet>,
        rays_done: &dyn RayCounter,
    ) -> CasterSet {
        let (rays, config) = (self.rays, self.config);
        let samples = config.supersample.max(1);
        let centres = |tiles: Vec<u64>| {
            if config.filter_radius > 0 {
                filter_margin::trace_tiles(rays, tiles, samples, config.filter_radius, rays_done)
            } else {
                rays.trace_tiles(tiles, samples, PacketSkip::Settled { known }, rays_done)
            }
        };
        let tiles: Vec<u64> = tiles.into_par_iter().collect();
        match &self.beams {
            None => centres(tiles),
            Some(beams) => {
                // The beams run over the same tiles after the centres.
                let known = centres(tiles.clone());
                let found = beams.trace_tiles(tiles, &known, &NoCount);
                known.union(&found)
            }
        }
    }
}

/// Progress is counted once, by the centre rays.
struct NoCount;

impl RayCounter for NoCount {
    fn add(&self, _rays: u64) {}
}
