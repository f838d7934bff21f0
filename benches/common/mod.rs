//! The generated `bench` world (seed 1), or with `SHADOWCULL_BENCH_CHUNKS=N`
//! a bench-density world of N×N chunks, written to a temporary folder and
//! loaded, shared by the benches that bake it.

use shadowcull::files::{write_tree, ResPaths};
use shadowcull::formats::bake_settings::BakeSettings;
use shadowcull::gen::{generate_each, Preset, WorldSize, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig, Scene};

/// The folder (keep it alive while the scene is used), settings and scene.
pub fn bench_world() -> (tempfile::TempDir, BakeSettings, Scene) {
    let dir = tempfile::tempdir().expect("temporary folder");
    let size = match std::env::var("SHADOWCULL_BENCH_CHUNKS") {
        Ok(n) => WorldSize::BenchChunks(n.parse().expect("SHADOWCULL_BENCH_CHUNKS: a number")),
        Err(_) => WorldSize::Preset(Preset::Bench),
    };
    generate_each(size, 1, |path, bytes| {
        write_tree(dir.path(), &[(path.to_string(), bytes)])
    })
    .expect("write bench world");
    let settings =
        shadowcull::files::read_bake_settings(&dir.path().join(SETTINGS_FILE)).expect("settings");
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
        speedtrees: settings.speedtrees.clone(),
    })
    .expect("load");
    (dir, settings, scene)
}
