//! SpeedTree placements and the chunk items the bake does not model
//! (docs/contract.md §2–§5, §8) on `gen --preset forest` worlds: the chunk
//! of terrain and 22 trees, proxies against the brute-force oracle, masks
//! inside `<speedtree>` in text and packed chunks, every item kind listed,
//! and what a missing file costs.

use crate::cli::shadowcull;
use crate::micro::{config, cube, directional, instance_masks, run, Mesh, World, OPAQUE};
use glam::{DMat4, DVec3, Vec3};
use serde_json::Value;
use shadowcull::bake::{self, shard, BakeConfig, Silent};
use shadowcull::files::{read_bake_settings, write_tree, ResPaths};
use shadowcull::formats::bake_settings::{CrownShape, LightKind, ParametricTree};
use shadowcull::formats::chunk::InstanceKind;
use shadowcull::formats::{parse_data_section, shadow_write};
use shadowcull::gen::{generate, Preset, SETTINGS_FILE};
use shadowcull::scene::speedtree::parametric_model;
use shadowcull::scene::{load_scene, LoadConfig, Scene};
use std::path::{Path, PathBuf};
use std::process::Output;
use tempfile::TempDir;

const SPACE: &str = "spaces/forest";
/// The forest's chunk of terrain and 22 trees (grid 1, 1).
const TREE_CHUNK: &str = "00010001o";

fn forest() -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &generate(Preset::Forest, 1).files).unwrap();
    dir
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn run_cli(args: &[&str]) -> Output {
    shadowcull(args)
}

fn path_str(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// `bake.xml` without its `<speedtrees>`, as `NAME` beside it; `extra`
/// goes where they were.
fn settings_without_proxies(dir: &Path, name: &str, extra: &str) -> PathBuf {
    let settings = std::fs::read_to_string(dir.join(SETTINGS_FILE)).unwrap();
    let start = settings.find("\t<speedtrees>").unwrap();
    let end = settings.find("</speedtrees>\n").unwrap() + "</speedtrees>\n".len();
    let path = dir.join(name);
    std::fs::write(
        &path,
        format!("{}{extra}{}", &settings[..start], &settings[end..]),
    )
    .unwrap();
    path
}

/// Leaves only the tree chunk (and its terrain) in the space.
fn only_the_tree_chunk(dir: &Path) {
    for entry in std::fs::read_dir(dir.join(SPACE)).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        let chunk_file = name.ends_with(".chunk") || name.ends_with(".cdata");
        if chunk_file && !name.starts_with(TREE_CHUNK) {
            std::fs::remove_file(path).unwrap();
        }
    }
}

fn json_of(output: &Output) -> Value {
    serde_json::from_slice(&output.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}\n{}", text(&output.stdout), text(&output.stderr)))
}

fn load(settings_file: &Path) -> Scene {
    let settings = read_bake_settings(settings_file).unwrap();
    load_scene(&LoadConfig::from_settings(&settings)).unwrap()
}

#[test]
fn a_chunk_of_terrain_and_22_trees_is_not_no_problems_without_proxies() {
    let dir = forest();
    only_the_tree_chunk(dir.path());
    let chunk = std::fs::read(dir.path().join(SPACE).join(format!("{TREE_CHUNK}.chunk"))).unwrap();
    let root = parse_data_section(&chunk).unwrap();
    assert!(
        chunk.starts_with(&shadowcull::formats::packed_xml::MAGIC),
        "packed, as real maps are"
    );
    assert_eq!(root.children_named("speedtree").count(), 22);
    assert_eq!(root.children_named("model").count(), 0);
    assert_eq!(root.children_named("terrain").count(), 1);

    let bare = settings_without_proxies(dir.path(), "bare.xml", "");
    let inspect = run_cli(&["inspect", path_str(&bare)]);
    let said = text(&inspect.stdout);
    assert_eq!(inspect.status.code(), Some(1), "{said}");
    assert!(!said.contains("no problems"), "{said}");
    assert!(said.contains("speedtrees without a proxy"), "{said}");
    let json = json_of(&run_cli(&["inspect", path_str(&bare), "--json"]));
    assert_eq!(json["speedtrees"], 22);
    assert_eq!(json["speedtrees_without_proxy"], 22);
    let listed: u64 = json["unproxied_speedtrees"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["placements"].as_u64().unwrap())
        .sum();
    assert_eq!(listed, 22, "counts per .spt add up");
    assert!(!json["problems"].as_array().unwrap().is_empty());

    let strict = run_cli(&["bake", path_str(&bare), "--dry-run", "--quiet"]);
    assert_eq!(strict.status.code(), Some(1));
    let error = text(&strict.stderr);
    assert!(
        error.contains("22 speedtree placements without a proxy")
            && error.contains("<unmodelledCasters> keep </unmodelledCasters>")
            && error.contains("speedtree/"),
        "{error}"
    );
    let plan = run_cli(&["plan", path_str(&bare)]);
    assert_eq!(plan.status.code(), Some(1), "{}", text(&plan.stdout));
    assert!(text(&plan.stdout).contains("without a proxy"));

    // Kept for every light: every baked bit, the mask alone.
    let kept = settings_without_proxies(
        dir.path(),
        "kept.xml",
        "\t<unmodelledCasters>\tkeep\t</unmodelledCasters>\n",
    );
    assert_eq!(
        run_cli(&["inspect", path_str(&kept)]).status.code(),
        Some(0)
    );
    let out = dir.path().join("out");
    let baked = run_cli(&[
        "bake",
        path_str(&kept),
        "--out",
        path_str(&out),
        "--report",
        "-",
        "--quiet",
    ]);
    assert!(baked.status.success(), "{}", text(&baked.stderr));
    let report = json_of(&baked);
    let trees: Vec<&Value> = report["casters"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["kind"] == "speedtree")
        .collect();
    assert_eq!(trees.len(), 22);
    for tree in &trees {
        assert_eq!(tree["unmodelled"], true);
        assert_eq!(tree["mask"], 0b111, "{tree}");
        assert!(tree.get("groups").is_none() && tree.get("proxy").is_none());
    }
    assert!(report["skipped"]
        .as_array()
        .unwrap()
        .iter()
        .any(|s| s["severity"] == "warning" && s["what"].as_str().unwrap().contains(".spt")));
    let written = std::fs::read(out.join(SPACE).join(format!("{TREE_CHUNK}.chunk"))).unwrap();
    let back = shadow_write::read_chunk_shadows(&parse_data_section(&written).unwrap()).unwrap();
    assert_eq!(back.speedtrees.len(), 22);
    assert!(back.speedtrees.iter().all(|s| s
        .as_ref()
        .is_some_and(|s| s.mask == 0b111 && s.render_sets.is_empty())));

    // With proxies the trees are casters, and nothing is left out.
    let inspect = run_cli(&["inspect", path_str(&dir.path().join(SETTINGS_FILE))]);
    let said = text(&inspect.stdout);
    assert!(inspect.status.success(), "{said}");
    assert!(
        said.contains(
            "no problems: every resource loaded and every chunk item that casts is modelled"
        ),
        "{said}"
    );
    let baked = run_cli(&[
        "bake",
        path_str(&dir.path().join(SETTINGS_FILE)),
        "--dry-run",
        "--report",
        "-",
        "--quiet",
    ]);
    assert!(baked.status.success(), "{}", text(&baked.stderr));
    let report = json_of(&baked);
    let trees: Vec<&Value> = report["casters"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["kind"] == "speedtree")
        .collect();
    assert_eq!(trees.len(), 22);
    for tree in &trees {
        let groups = tree["groups"].as_array().unwrap();
        let expected = if tree["proxy"] == "parametric" { 2 } else { 1 };
        assert_eq!(groups.len(), expected, "{tree}");
        assert!(tree.get("unmodelled").is_none());
    }
    let indices: Vec<u64> = trees.iter().map(|t| t["index"].as_u64().unwrap()).collect();
    assert_eq!(indices, (0..22).collect::<Vec<_>>());
    assert!(
        trees.iter().any(|t| t["mask"] != 0b111),
        "proxies can be culled"
    );
}

/// The forest's lights, coarser so the oracle stays quick.
fn coarse(settings: &Path) -> BakeConfig {
    let settings = read_bake_settings(settings).unwrap();
    let lights = settings
        .lights
        .iter()
        .map(|l| {
            let mut l = l.clone();
            match &mut l.kind {
                LightKind::Directional { texel_size, .. } => *texel_size *= 3.0,
                LightKind::Spot { resolution, .. } | LightKind::Point { resolution, .. } => {
                    *resolution = 64
                }
            }
            l
        })
        .collect();
    BakeConfig {
        lights,
        ..BakeConfig::from_settings(&settings)
    }
}

#[test]
fn proxies_agree_with_the_brute_force_oracle() {
    let dir = forest();
    let settings = dir.path().join(SETTINGS_FILE);
    let scene = load(&settings);
    assert!(scene.problems.is_empty(), "{:?}", scene.problems);
    let config = coarse(&settings);
    let fast = bake::bake(&scene, &config, &Silent).unwrap();
    let oracle = bake::bake(
        &scene,
        &BakeConfig {
            brute_force: true,
            ..config
        },
        &Silent,
    )
    .unwrap();
    assert_eq!(fast.masks, oracle.masks, "BVH and brute force disagree");
    let tree_masks: Vec<u32> = scene
        .instances
        .iter()
        .enumerate()
        .filter(|(_, i)| i.kind == InstanceKind::SpeedTree)
        .flat_map(|(index, _)| fast.casters.of_instance(&scene, index))
        .map(|id| fast.masks[id as usize])
        .collect();
    assert!(tree_masks.len() > 45, "every tree has its proxy's groups");
    assert!(tree_masks.iter().any(|&m| m != 0));
    assert!(tree_masks.iter().any(|&m| m != 0b111));
}

#[test]
fn an_alpha_tested_crown_culls_nothing_below_it_and_the_oracle_agrees() {
    // A tree scaled unevenly and turned, its crown over a box on flat
    // ground, the sun almost overhead.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let tree = ParametricTree {
        trunk_radius: 0.3,
        trunk_height: 3.0,
        crown_radius: 2.0,
        crown_height: 3.0,
        crown_base: 2.0,
        crown_shape: CrownShape::Ellipsoid,
    };
    let mut proxy = parametric_model(&tree);
    proxy.resource = "proxy".into();
    world.scene.models.push(proxy);
    let proxy = world.scene.models.len() - 1;
    let box_model = world.model(Mesh {
        groups: vec![(
            cube(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 0.8, 0.5)),
            OPAQUE,
        )],
    });
    let placed = DMat4::from_translation(DVec3::new(8.0, 0.0, 8.0))
        * DMat4::from_rotation_y(0.4)
        * DMat4::from_scale(DVec3::new(1.3, 1.69, 0.8));
    let tree_instance = world.place((0, 0), &[proxy], placed, true);
    let box_instance = world.place(
        (0, 0),
        &[box_model],
        DMat4::from_translation(DVec3::new(9.0, 0.0, 8.0)),
        true,
    );
    let result = run(
        &world,
        &config(vec![directional(DVec3::new(0.05, -1.0, 0.03), 0.1)]),
    );
    let tree_masks = instance_masks(&result, &world, tree_instance);
    assert_eq!(tree_masks, [1, 1], "trunk and crown both cast");
    let box_masks = instance_masks(&result, &world, box_instance);
    assert_eq!(
        box_masks,
        [1],
        "the crown's holes may let light through to the box"
    );
}

#[test]
fn masks_inside_speedtrees_round_trip_in_text_and_packed_chunks() {
    let dir = forest();
    let settings = dir.path().join(SETTINGS_FILE);
    let baked = run_cli(&["bake", path_str(&settings), "--report", "-", "--quiet"]);
    assert!(baked.status.success(), "{}", text(&baked.stderr));
    let report = json_of(&baked);
    let mut seen = (false, false);
    for entry in report["casters"].as_array().unwrap() {
        if entry["kind"] != "speedtree" {
            continue;
        }
        let chunk = entry["chunk"].as_str().unwrap();
        let bytes = std::fs::read(dir.path().join(SPACE).join(format!("{chunk}.chunk"))).unwrap();
        let packed = bytes.starts_with(&shadowcull::formats::packed_xml::MAGIC);
        if packed {
            seen.0 = true;
        } else {
            seen.1 = true;
        }
        let back = shadow_write::read_chunk_shadows(&parse_data_section(&bytes).unwrap()).unwrap();
        let index = entry["index"].as_u64().unwrap() as usize;
        let shadow = back.speedtrees[index]
            .as_ref()
            .expect("a <shadow> in the item");
        assert_eq!(u64::from(shadow.mask), entry["mask"].as_u64().unwrap());
        let groups: Vec<u64> = shadow.groups().map(u64::from).collect();
        let reported: Vec<u64> = entry["groups"]
            .as_array()
            .unwrap()
            .iter()
            .map(|g| g.as_u64().unwrap())
            .collect();
        assert_eq!(
            groups, reported,
            "{chunk} speedtree {index} (packed: {packed})"
        );
    }
    assert_eq!(seen, (true, true), "trees in packed and text chunks");
    // The contract's example entry has the fields a parametric tree's has.
    let contract = include_str!("../../docs/contract.md");
    let example = &contract[contract.find("```json\n").unwrap() + "```json\n".len()..];
    let example: Value = serde_json::from_str(&example[..example.find("```").unwrap()]).unwrap();
    let keys = |entry: &Value| -> Vec<String> {
        let mut keys: Vec<String> = entry.as_object().unwrap().keys().cloned().collect();
        keys.sort();
        keys
    };
    let documented = example["casters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["kind"] == "speedtree")
        .unwrap();
    let parametric = report["casters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["proxy"] == "parametric")
        .unwrap();
    assert_eq!(keys(documented), keys(parametric));
    // The same masks again: nothing to change.
    let check = run_cli(&["bake", path_str(&settings), "--check", "--quiet"]);
    assert_eq!(check.status.code(), Some(0), "{}", text(&check.stderr));
    let again = run_cli(&["bake", path_str(&settings), "--report", "-", "--quiet"]);
    assert_eq!(json_of(&again)["casters"], report["casters"]);
}

#[test]
fn a_tree_scaled_unevenly_stretches_its_proxy() {
    let dir = forest();
    let scene = load(&dir.path().join(SETTINGS_FILE));
    let chunk = scene
        .chunks
        .iter()
        .position(|c| c.name == TREE_CHUNK)
        .unwrap();
    let tree = scene
        .instances
        .iter()
        .find(|i| i.chunk == chunk && i.kind == InstanceKind::SpeedTree && i.index == 0)
        .unwrap();
    let lengths = [
        tree.world.x_axis.truncate().length(),
        tree.world.y_axis.truncate().length(),
        tree.world.z_axis.truncate().length(),
    ];
    for (got, want) in lengths.iter().zip([1.3, 1.69, 0.8]) {
        assert!((got - want).abs() < 1e-5, "{lengths:?}");
    }
    // Upright, so the proxy's height scales by 1.69 exactly.
    let model = &scene.models[tree.parts[0].unwrap()];
    let (min, max) = model.bounds().unwrap();
    let low = tree
        .world
        .transform_point3(DVec3::new(0.0, f64::from(min.y), 0.0));
    let high = tree
        .world
        .transform_point3(DVec3::new(0.0, f64::from(max.y), 0.0));
    let height = f64::from(max.y - min.y);
    assert!(((high.y - low.y) - 1.69 * height).abs() < 1e-4);
    let mirrored = scene
        .instances
        .iter()
        .find(|i| i.chunk == chunk && i.kind == InstanceKind::SpeedTree && i.index == 7)
        .unwrap();
    assert!(
        mirrored.mirrored,
        "a negative scale mirrors a tree as a model"
    );
}

#[test]
fn every_item_kind_is_listed_by_inspect_plan_and_the_bake() {
    let dir = forest();
    let settings = dir.path().join(SETTINGS_FILE);
    let inspect = run_cli(&["inspect", path_str(&settings), "--json"]);
    assert!(inspect.status.success(), "{}", text(&inspect.stderr));
    let json = json_of(&inspect);
    let expected = serde_json::to_value(generate(Preset::Forest, 1).expected).unwrap();
    for (field, value) in expected.as_object().unwrap() {
        assert_eq!(&json[field], value, "{field}");
    }
    let treatment = |kind: &str| -> String {
        json["items"]
            .as_array()
            .unwrap()
            .iter()
            .find(|i| i["kind"] == kind)
            .unwrap_or_else(|| panic!("no <{kind}> in {}", json["items"]))["treatment"]
            .as_str()
            .unwrap()
            .to_string()
    };
    for (kind, want) in [
        ("model", "modelled"),
        ("speedtree", "modelled"),
        ("terrain", "modelled"),
        ("vlo", "receives_only"),
        ("particles", "receives_only"),
        ("flora", "receives_only"),
        ("audio", "not_geometry"),
        ("UserDataObject", "not_geometry"),
        ("entity", "not_geometry"),
        ("omniLight", "not_geometry"),
        ("worldNavmesh", "not_geometry"),
        ("waypointGenerationTime", "chunk_data"),
        ("ControlPoint", "unknown"),
    ] {
        assert_eq!(treatment(kind), want, "{kind}");
    }
    let said = text(&run_cli(&["inspect", path_str(&settings)]).stdout);
    assert!(
        !said.contains("no problems:"),
        "an unknown kind may cast: {said}"
    );
    assert!(
        said.contains("unknown to shadowcull (<ControlPoint>)"),
        "{said}"
    );

    let plan = run_cli(&["plan", path_str(&settings)]);
    assert!(plan.status.success(), "{}", text(&plan.stderr));
    let baked = run_cli(&["bake", path_str(&settings), "--dry-run", "--quiet"]);
    assert!(baked.status.success(), "{}", text(&baked.stderr));
    for output in [text(&plan.stdout), text(&baked.stdout)] {
        for kind in [
            "vlo",
            "particles",
            "flora",
            "audio",
            "UserDataObject",
            "entity",
            "omniLight",
            "worldNavmesh",
            "ControlPoint",
        ] {
            let line = output
                .lines()
                .find(|l| l.contains(&format!(" <{kind}> in ")))
                .unwrap_or_else(|| panic!("<{kind}> is not listed:\n{output}"));
            assert!(line.contains("left out: "), "{line}");
        }
        assert!(
            !output.contains("<model> in"),
            "modelled kinds are not left out"
        );
    }
}

#[test]
fn shards_that_used_other_proxies_do_not_share_a_fingerprint() {
    let dir = forest();
    let settings = dir.path().join(SETTINGS_FILE);
    let with = load(&settings);
    let read = read_bake_settings(&settings).unwrap();
    let without = load_scene(&LoadConfig {
        speedtrees: Default::default(),
        ..LoadConfig::from_settings(&read)
    })
    .unwrap();
    let config = BakeConfig::from_settings(&read);
    let res_paths = ResPaths::new(read.res_paths.clone());
    let a = shard::fingerprint(&with, &config, &res_paths);
    let b = shard::fingerprint(&without, &config, &res_paths);
    assert_ne!(a.settings, b.settings);
    assert!(a.settings.contains("speedtrees = "), "{}", a.settings);
    let small = generate(Preset::Small, 1);
    let small_dir = tempfile::tempdir().unwrap();
    write_tree(small_dir.path(), &small.files).unwrap();
    let small_settings = small_dir.path().join(SETTINGS_FILE);
    let plain = shard::fingerprint(
        &load(&small_settings),
        &config,
        &ResPaths::new(vec![small_dir.path().to_path_buf()]),
    );
    assert!(
        !plain.settings.contains("speedtrees"),
        "unchanged without trees"
    );
}

#[test]
fn a_missing_model_or_cdata_says_how_much_of_the_world_loses_it() {
    let dir = tempfile::tempdir().unwrap();
    let world = generate(Preset::Village, 1);
    write_tree(dir.path(), &world.files).unwrap();
    let chunks: Vec<String> = world
        .files
        .iter()
        .filter(|(p, _)| p.ends_with(".chunk"))
        .map(|(_, b)| text(b))
        .collect();
    let crate_model = "sets/gen/props/crate.model";
    let placements: usize = chunks.iter().map(|c| c.matches(crate_model).count()).sum();
    let holding = chunks.iter().filter(|c| c.contains(crate_model)).count();
    assert!(placements > holding && holding > 1);
    std::fs::remove_file(dir.path().join(crate_model)).unwrap();
    std::fs::remove_file(dir.path().join("spaces/village/00000000o.cdata")).unwrap();
    let scene = load(&dir.path().join(SETTINGS_FILE));
    let model = scene
        .problems
        .iter()
        .find(|p| p.what == crate_model)
        .expect("the missing model is a problem");
    assert!(
        model.why.contains("not found in any res path")
            && model.why.contains("check <resPaths>")
            && model.why.contains(&format!(
                "{placements} placements in {holding} chunks lose it"
            )),
        "{model:?}"
    );
    let cdata = scene
        .problems
        .iter()
        .find(|p| p.what.ends_with("00000000o.chunk <terrain>"))
        .expect("the missing .cdata is a problem");
    assert!(
        cdata.why.contains("`00000000o.cdata` not found")
            && cdata.why.contains("check <resPaths>")
            && cdata.why.contains("1 chunk loses its terrain block"),
        "{cdata:?}"
    );
    assert!(!cdata.why.contains("os error"), "{cdata:?}");
}

#[test]
fn keep_going_with_nothing_loaded_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let world = generate(Preset::Small, 1);
    write_tree(dir.path(), &world.files).unwrap();
    for (path, _) in &world.files {
        if path.ends_with(".model") || path.ends_with(".cdata") {
            std::fs::remove_file(dir.path().join(path)).unwrap();
        }
    }
    let settings = dir.path().join(SETTINGS_FILE);
    let out = run_cli(&[
        "bake",
        path_str(&settings),
        "--keep-going",
        "--dry-run",
        "--quiet",
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("nothing loaded"),
        "{}",
        text(&out.stderr)
    );
    // One block left: something to bake.
    let block = world
        .files
        .iter()
        .find(|(p, _)| p.ends_with(".cdata"))
        .unwrap();
    std::fs::write(dir.path().join(&block.0), &block.1).unwrap();
    let out = run_cli(&[
        "bake",
        path_str(&settings),
        "--keep-going",
        "--dry-run",
        "--quiet",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
}

#[test]
fn the_render_legend_counts_the_trees_it_cannot_draw() {
    let dir = forest();
    let kept = settings_without_proxies(
        dir.path(),
        "kept.xml",
        "\t<unmodelledCasters>\tkeep\t</unmodelledCasters>\n",
    );
    let out = dir.path().join("sun.png");
    let rendered = run_cli(&[
        "render",
        path_str(&kept),
        "--light",
        "sun",
        "--size",
        "64x64",
        "-o",
        path_str(&out),
    ]);
    assert!(rendered.status.success(), "{}", text(&rendered.stderr));
    let legend = std::fs::read_to_string(dir.path().join("sun.txt")).unwrap();
    let trees = generate(Preset::Forest, 1).expected.speedtrees;
    assert!(
        legend.contains(&format!(
            "{trees} of the useful casters are speedtrees without a proxy"
        )),
        "{legend}"
    );
}
