//! Stacked coincident geometry: the `small` world with its first house
//! placed 1, 10, 100 and 1 000 times at one transform (a level editor's
//! duplicate key). Every ray through the stack ties all copies at one
//! distance; the bake must stay near-linear in the copies, not
//! quadratic. Coarse lights (about 20 000 rays) keep the largest case
//! quick.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::gen::{generate, stack_first_model, Preset, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig};
use std::time::Duration;

const CHUNK: &str = "spaces/small/00000000o.chunk";

/// The small world's settings with lights about 50 times coarser.
fn coarse(settings: &[u8]) -> Vec<u8> {
    String::from_utf8_lossy(settings)
        .replace("0.195312", "1.000000")
        .replace("\t512\t", "\t64\t")
        .replace("\t256\t", "\t32\t")
        .into_bytes()
}

fn coincident_bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("coincident");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(10));
    for copies in [1usize, 10, 100, 1000] {
        let mut world = generate(Preset::Small, 1);
        for (path, bytes) in &mut world.files {
            if path == CHUNK {
                *bytes = stack_first_model(bytes, copies).expect("the chunk holds a model");
            } else if path == SETTINGS_FILE {
                *bytes = coarse(bytes);
            }
        }
        let dir = tempfile::tempdir().expect("temporary folder");
        write_tree(dir.path(), &world.files).expect("write world");
        let settings = shadowcull::files::read_bake_settings(&dir.path().join(SETTINGS_FILE))
            .expect("settings");
        let scene = load_scene(&LoadConfig {
            res_paths: ResPaths::new(settings.res_paths.clone()),
            space: settings.space.clone(),
            speedtrees: settings.speedtrees.clone(),
        })
        .expect("load");
        let config = BakeConfig::from_settings(&settings);
        group.bench_with_input(BenchmarkId::from_parameter(copies), &copies, |b, _| {
            b.iter(|| bake::bake(&scene, &config, &Silent).expect("bake"))
        });
    }
    group.finish();
}

criterion_group!(benches, coincident_bench);
criterion_main!(benches);
