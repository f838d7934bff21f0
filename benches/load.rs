//! Load time of the generated `bench` world into one scene. The world is
//! generated once into a temporary folder; each iteration reads and
//! assembles the whole scene.

use criterion::{criterion_group, criterion_main, Criterion};
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::gen::{generate, Preset};
use shadowcull::scene::{load_scene, LoadConfig};

fn load_bench_world(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temporary folder");
    let world = generate(Preset::Bench, 1);
    write_tree(dir.path(), &world.files).expect("write the bench world");
    let settings = shadowcull::files::read_bake_settings(&dir.path().join("bake.xml"))
        .expect("bench settings");
    let config = LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
        speedtrees: settings.speedtrees.clone(),
    };
    let stats = load_scene(&config).expect("load").stats();
    eprintln!(
        "bench world: {} chunks, {} instances, {} models, {} groups, {} triangles, {} terrain blocks",
        stats.chunks, stats.instances, stats.models, stats.groups, stats.triangles, stats.terrain_blocks
    );
    let mut group = c.benchmark_group("load");
    group.sample_size(10);
    group.bench_function("bench_world", |b| {
        b.iter(|| load_scene(&config).expect("load"))
    });
    group.finish();
}

criterion_group!(benches, load_bench_world);
criterion_main!(benches);
