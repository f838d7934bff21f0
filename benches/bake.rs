//! The bake on a generated world: the bottom levels (once per bake), each
//! light's top level, traced rays/s per light kind (the bake's grid pass,
//! and the two-level traversal alone on the same rays), and a whole bake
//! end to end. The world is `gen --preset bench` (seed 1), or with
//! `SHADOWCULL_BENCH_CHUNKS=N` a bench-density world of N×N chunks
//! (`gen --chunks N`).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use shadowcull::bake::setup::{BakeWorld, LightSetup};
use shadowcull::bake::trace_light::{PacketSkip, RayCounter};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::trace::TraceRay;
use std::time::Duration;

mod common;
use common::bench_world;

struct NoCount;
impl RayCounter for NoCount {
    fn add(&self, _: u64) {}
}

fn bake_bench(c: &mut Criterion) {
    let (_dir, settings, scene) = bench_world();
    let config = BakeConfig::from_settings(&settings);

    let mut group = c.benchmark_group("build");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(8));
    group.bench_function("bottom_levels", |b| b.iter(|| BakeWorld::new(&scene)));
    group.finish();

    let world = BakeWorld::new(&scene);
    for index in 0..config.lights.len() {
        let light = &config.lights[index];
        let kind = light.kind.type_name();
        let setup = LightSetup::new(&world, &config, index).expect("light setup");
        eprintln!(
            "{kind} `{}`: {} rays, {} instance parts and {} blocks in reach",
            light.name,
            setup.grid.texel_count(),
            setup.top.len() - setup.reach.blocks.len(),
            setup.reach.blocks.len()
        );
        let mut group = c.benchmark_group(format!("build/{kind}"));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(5));
        group.bench_function("top_level", |b| {
            b.iter(|| LightSetup::new(&world, &config, index).expect("light setup"))
        });
        group.finish();

        let rays_of_light = setup.rays(&world, &config);
        let grid = &setup.grid;
        let mut group = c.benchmark_group(format!("trace/{kind}"));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(10));
        group.throughput(Throughput::Elements(grid.texel_count()));
        group.bench_function("bake_rays", |b| {
            b.iter(|| rays_of_light.trace_grid(1, PacketSkip::Never, &NoCount))
        });
        // The same rays through the traversal alone (no classification),
        // single-threaded, collecting hits with an early cut-off at the
        // second (two hits suffice on most rays).
        let (width, height) = (grid.width(), grid.height());
        let rays: Vec<TraceRay> = (0..grid.faces())
            .flat_map(|f| (0..height).flat_map(move |y| (0..width).map(move |x| (f, x, y))))
            .map(|(f, x, y)| rays_of_light.light_relative(&grid.ray(f, x, y)))
            .collect();
        group.bench_function("two_hits", |b| {
            b.iter(|| {
                let mut total = 0usize;
                for ray in &rays {
                    let mut hits = 0;
                    let mut limit = ray.t_max;
                    rays_of_light.tracer.for_each_hit(ray, |hit| {
                        hits += 1;
                        if hits >= 2 {
                            limit = limit.min(hit.t);
                        }
                        limit
                    });
                    total += hits;
                }
                total
            })
        });
        group.finish();
    }

    let mut group = c.benchmark_group("bake");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(20));
    group.bench_function("all_lights", |b| {
        b.iter(|| bake::bake(&scene, &config, &Silent).expect("bake"))
    });
    group.finish();
}

criterion_group!(benches, bake_bench);
criterion_main!(benches);
