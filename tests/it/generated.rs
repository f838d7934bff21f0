//! Worlds written by `gen` read back through the readers: the scene holds
//! exactly what the generator placed, and the committed fixtures are what
//! the generator writes today.

use shadowcull::files::read_bake_settings;
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::gen::{generate, Expected, Preset, SETTINGS_FILE};
use shadowcull::scene::{load_scene, LoadConfig, Scene, Stats};
use std::path::{Path, PathBuf};

/// Seed of the committed fixtures.
pub const FIXTURE_SEED: u64 = 1;

pub fn fixture_dir(preset: Preset) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/worlds")
        .join(preset.name())
}

pub fn load_world(settings_file: &Path) -> Scene {
    let settings = read_bake_settings(settings_file).unwrap();
    load_scene(&LoadConfig {
        res_paths: ResPaths::new(settings.res_paths),
        space: settings.space,
        speedtrees: settings.speedtrees,
    })
    .unwrap()
}

fn stats_of(expected: &Expected) -> Stats {
    Stats {
        chunks: expected.chunks as usize,
        instances: expected.instances as usize,
        models: expected.models as usize,
        groups: expected.groups as usize,
        triangles: expected.triangles as usize,
        terrain_blocks: expected.terrain_blocks as usize,
        alpha_tested_groups: expected.alpha_tested_groups as usize,
        double_sided_groups: expected.double_sided_groups as usize,
        receiver_only_instances: expected.receiver_only_instances as usize,
        speedtrees: expected.speedtrees as usize,
        speedtrees_without_proxy: expected.speedtrees_without_proxy as usize,
        speedtree_proxies: expected.speedtree_proxies as usize,
    }
}

#[test]
fn generated_worlds_read_back_with_the_generators_counts() {
    for preset in [Preset::Small, Preset::Village, Preset::Forest] {
        for seed in [1, 7] {
            let world = generate(preset, seed);
            let dir = tempfile::tempdir().unwrap();
            write_tree(dir.path(), &world.files).unwrap();
            let scene = load_world(&dir.path().join(SETTINGS_FILE));
            assert!(
                scene.problems.is_empty(),
                "{preset:?}/{seed}: {:#?}",
                scene.problems
            );
            assert_eq!(
                scene.stats(),
                stats_of(&world.expected),
                "{preset:?} seed {seed}"
            );
            assert!(
                scene.instances.iter().any(|i| i.mirrored),
                "{preset:?}: a mirrored placement"
            );
            assert!(
                scene.instances.iter().any(|i| i.parts.len() == 2),
                "{preset:?}: a two-resource instance"
            );
        }
    }
}

#[test]
fn committed_fixtures_are_what_gen_writes() {
    let bless = std::env::var_os("SHADOWCULL_BLESS").is_some();
    for preset in [Preset::Small, Preset::Village] {
        let world = generate(preset, FIXTURE_SEED);
        let dir = fixture_dir(preset);
        if bless {
            let _ = std::fs::remove_dir_all(&dir);
            write_tree(&dir, &world.files).unwrap();
        }
        for (relative, bytes) in &world.files {
            let path = dir.join(relative);
            let committed = std::fs::read(&path).unwrap_or_else(|e| {
                panic!(
                    "{}: {e}; re-bless with SHADOWCULL_BLESS=1 cargo test fixtures",
                    path.display()
                )
            });
            assert!(
                committed == *bytes,
                "{} differs from `shadowcull gen --preset {} --seed {FIXTURE_SEED}`; re-bless with SHADOWCULL_BLESS=1",
                path.display(),
                preset.name()
            );
        }
        // A bake of a fixture keeps its cache beside the settings file
        // (ignored by git): not a stray file.
        let committed_files: Vec<_> = shadowcull::files::find_files(&dir, "")
            .unwrap()
            .into_iter()
            .filter(|f| !f.components().any(|c| c.as_os_str() == ".shadowcull-cache"))
            .collect();
        assert_eq!(
            committed_files.len(),
            world.files.len(),
            "{}: stray files",
            dir.display()
        );
    }
}
