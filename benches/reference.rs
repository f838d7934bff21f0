//! The rasterized reference against the ray-cast bake on the generated
//! `bench` world (seed 1), light by light on the same grids: each side from
//! the loaded scene to its masks (geometry, BVH or vertex upload, all
//! passes). Needs the `raster` feature and an OpenGL 3.3 driver (Mesa's
//! llvmpipe on a machine without a GPU):
//! `cargo bench --features raster --bench reference`.

use criterion::{criterion_group, criterion_main, Criterion};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::formats::resources::{write_tree, ResPaths};
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use shadowcull::raster;
use shadowcull::scene::{load_scene, LoadConfig};
use std::time::Duration;

fn reference_bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temporary folder");
    write_tree(dir.path(), &generate(Preset::Bench, 1).files).expect("write bench world");
    let settings =
        shadowcull::formats::read_bake_settings(&dir.path().join(SETTINGS_FILE)).expect("settings");
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
    })
    .expect("load");
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
