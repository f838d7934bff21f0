//! Tile traversal against single rays on identical rays: per
//! light kind, the bake's tiles traced ray by ray (`single`) and as packets
//! (`tiles`), both through `LightRays::trace_tiles` on the rayon pool (every
//! packet traced: `PacketSkip::Never`), with
//! the same answer asserted before timing. The world is `gen --preset
//! bench` (seed 1) or, with `SHADOWCULL_BENCH_CHUNKS=N`, N×N chunks at the
//! bench's density; the sun's texel size is `SHADOWCULL_BENCH_TEXEL`
//! (default 0.25 m, a fine sun of a real world). A spread sample of about
//! `SHADOWCULL_BENCH_RAYS` rays (default 2 M) per light keeps a run short.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use shadowcull::bake::setup::{BakeWorld, LightSetup};
use shadowcull::bake::trace_light::{tile_rect, PacketSkip, RayCounter, TILE};
use shadowcull::bake::BakeConfig;
use shadowcull::formats::bake_settings::LightKind;
use shadowcull::trace::TraceMode;
use std::time::Duration;

mod common;
use common::bench_world;

struct NoCount;
impl RayCounter for NoCount {
    fn add(&self, _: u64) {}
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn tiles_bench(c: &mut Criterion) {
    let (_dir, settings, scene) = bench_world();
    let mut config = BakeConfig::from_settings(&settings);
    let texel: f64 = env_or("SHADOWCULL_BENCH_TEXEL", 0.25);
    for light in &mut config.lights {
        if let LightKind::Directional { texel_size, .. } = &mut light.kind {
            *texel_size = texel;
        }
    }
    let wanted: u64 = env_or("SHADOWCULL_BENCH_RAYS", 2_000_000);
    let world = BakeWorld::new(&scene);
    for index in 0..config.lights.len() {
        let kind = config.lights[index].kind.type_name();
        let setup = LightSetup::new(&world, &config, index).expect("light setup");
        let tiles = setup.rays(&world, &config);
        let mut single = tiles;
        single.tracer.mode = TraceMode::RayByRay;
        // One tile in k, picked by a multiplicative hash: a sample spread
        // over the whole grid (a plain stride would pick the same columns
        // of every row).
        let count = tiles.tile_count();
        let per_tile = u64::from(TILE * TILE);
        let step = (count * per_tile / wanted.max(1)).max(1);
        let sample: Vec<u64> = (0..count)
            .filter(|t| t.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40 < (1 << 24) / step)
            .collect();
        let rays: u64 = sample
            .iter()
            .map(|&t| {
                let (_, x0, y0, x1, y1) = tile_rect(&setup.grid, t);
                u64::from((x1 - x0) * (y1 - y0))
            })
            .sum();
        eprintln!("{kind}: {} of {count} tiles, {rays} rays", sample.len());
        assert_eq!(
            tiles.trace_tiles(sample.clone(), 1, PacketSkip::Never, &NoCount),
            single.trace_tiles(sample.clone(), 1, PacketSkip::Never, &NoCount),
            "{kind}: the tile path's answer differs"
        );
        let mut group = c.benchmark_group(format!("rays/{kind}"));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(10));
        group.throughput(Throughput::Elements(rays));
        group.bench_function("single", |b| {
            b.iter(|| single.trace_tiles(sample.clone(), 1, PacketSkip::Never, &NoCount))
        });
        group.bench_function("tiles", |b| {
            b.iter(|| tiles.trace_tiles(sample.clone(), 1, PacketSkip::Never, &NoCount))
        });
        group.finish();
    }
}

criterion_group!(benches, tiles_bench);
criterion_main!(benches);
