//! The synthetic world generator (`shadowcull gen`): time to make each
//! preset's files in memory, with the world's size (files, bytes and the
//! `Expected` counts) printed once before timing.

use criterion::{criterion_group, criterion_main, Criterion};
use shadowcull::gen::{generate, Preset};

fn generate_presets(c: &mut Criterion) {
    let mut group = c.benchmark_group("gen");
    group.sample_size(10);
    for preset in Preset::ALL {
        let world = generate(preset, 1);
        let bytes: usize = world.files.iter().map(|(_, b)| b.len()).sum();
        eprintln!(
            "{preset:?}: {} files, {bytes} bytes, {:?}",
            world.files.len(),
            world.expected
        );
        group.bench_function(format!("{preset:?}").to_lowercase(), |b| {
            b.iter(|| generate(preset, 1))
        });
    }
    group.finish();
}

criterion_group!(benches, generate_presets);
criterion_main!(benches);
