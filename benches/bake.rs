//! The bake on the generated `bench` world (seed 1): BVH build per light
//! (triangles/s), traced rays/s per light kind with the two-hit traversal
//! against obvhs's own closest-hit traversal on the same rays, and a whole
//! bake end to end.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use shadowcull::bake::casters::CasterTable;
use shadowcull::bake::ground::Ground;
use shadowcull::bake::trace_light::{LightRays, RayCounter, RayRules, Tracer};
use shadowcull::bake::{self, geometry, BakeConfig, Silent};
use shadowcull::classify::Passes;
use shadowcull::light::TexelGrid;
use shadowcull::trace::{Bvh, TraceRay};
use std::time::Duration;

mod common;
use common::bench_world;

struct NoCount;
impl RayCounter for NoCount {
    fn add(&self, _: u64) {}
}

fn bake_bench(c: &mut Criterion) {
    let (_dir, settings, scene) = bench_world();
    let casters = CasterTable::new(&scene);
    let bounds = geometry::world_bounds(&scene).expect("bench world has geometry");
    let ground = Ground::new(&scene);

    for light in &settings.lights {
        let kind = light.kind.type_name();
        let grid = TexelGrid::new(light, bounds).expect("grid");
        let light_geometry = geometry::light_geometry(&scene, &casters, &grid);
        let triangles = &light_geometry.triangles;
        eprintln!(
            "{kind} `{}`: {} rays, {} triangles in reach",
            light.name,
            grid.texel_count(),
            triangles.len()
        );

        let mut group = c.benchmark_group(format!("build/{kind}"));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(8));
        group.throughput(Throughput::Elements(triangles.len() as u64));
        group.bench_function("bvh", |b| b.iter(|| Bvh::build(triangles)));
        group.finish();

        let bvh = Bvh::build(triangles);
        let passes = if light_geometry.reaches_alpha_tested {
            Passes::AllAndOpaque
        } else {
            Passes::AllOnly
        };
        let rays_of_light = LightRays {
            grid: &grid,
            tracer: Tracer::Bvh(&bvh),
            casters: &casters,
            ground: ground.as_ref(),
            rules: RayRules::new(&BakeConfig::from_settings(&settings), passes),
        };
        let mut group = c.benchmark_group(format!("trace/{kind}"));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(10));
        group.throughput(Throughput::Elements(grid.texel_count()));
        group.bench_function("bake_rays", |b| {
            b.iter(|| rays_of_light.trace_grid(1, &NoCount))
        });
        // The same rays through the traversals alone (no classification),
        // single-threaded loops over every texel: ours collecting hits with
        // the early cut-off (two hits suffice on most rays), ours closest-hit,
        // obvhs's closest-hit with its own triangle test.
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
                    bvh.for_each_hit(ray, |hit| {
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
        group.bench_function("closest_hit", |b| {
            b.iter(|| rays.iter().filter(|r| bvh.closest_hit(r).is_some()).count())
        });
        group.bench_function("closest_hit_obvhs", |b| {
            b.iter(|| {
                rays.iter()
                    .filter(|r| bvh.closest_hit_obvhs(r).is_some())
                    .count()
            })
        });
        group.finish();
    }

    let config = BakeConfig::from_settings(&settings);
    let mut group = c.benchmark_group("bake");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(20));
    group.bench_function("bench_world_all_lights", |b| {
        b.iter(|| bake::bake(&scene, &config, &Silent).expect("bake"))
    });
    group.finish();
}

criterion_group!(benches, bake_bench);
criterion_main!(benches);
