//! The rasterized reference against the ray-cast bake on the generated
//! `bench` world (seed 1), light by light on the same grids: each side from
//! the loaded scene to its masks (geometry, BVH or vertex upload, all
//! passes). Needs the `raster` feature and an OpenGL 3.3 driver (Mesa's
//! llvmpipe on a machine without a GPU):
//! `cargo bench --features raster --bench reference`.

use criterion::{criterion_group, criterion_main, Criterion};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::raster;
use std::time::Duration;

mod common;
use common::bench_world;

fn reference_bench(c: &mut Criterion) {
    let (_dir, settings, scene) = bench_world();
    let all = BakeConfig::from_settings(&settings);
    for light in &all.lights {
        let config = BakeConfig {
            lights: vec![light.clone()],
            ..all.clone()
        };
        let mut group = c.benchmark_group(format!("reference/{}", light.kind.type_name()));
        group.sample_size(10);
        group.measurement_time(Duration::from_secs(20));
        group.bench_function("ray_cast", |b| {
            b.iter(|| bake::bake(&scene, &config, &Silent).expect("bake"))
        });
        group.bench_function("raster", |b| {
            b.iter(|| {
                raster::raster(&scene, &config, raster::DEFAULT_MAX_TILE)
                    .unwrap_or_else(|e| panic!("the rasterized method failed: {e}"))
            })
        });
        group.finish();
    }
}

criterion_group!(benches, reference_bench);
criterion_main!(benches);
