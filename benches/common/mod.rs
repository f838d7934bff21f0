//! The generated `bench` world (seed 1), written to a temporary folder and
//! loaded, shared by the benches that bake it.

use shadowcull::formats::bake_settings::BakeSettings;
use shadowcull::formats::resources::{write_tree, ResPaths};
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig, Scene};

/// The folder (keep it alive while the scene is used), settings and scene.
pub fn bench_world() -> (tempfile::TempDir, BakeSettings, Scene) {
    let dir = tempfile::tempdir().expect("temporary folder");
    write_tree(dir.path(), &generate(Preset::Bench, 1).files).expect("write bench world");
    let settings =
        shadowcull::formats::read_bake_settings(&dir.path().join(SETTINGS_FILE)).expect("settings");
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths.clone()),
        space: settings.space.clone(),
    })
    .expect("load");
    (dir, settings, scene)
}
