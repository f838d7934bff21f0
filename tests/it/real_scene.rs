//! Scenes built from real BigWorld files: every real model loads with the
//! triangle counts its own index headers give, and the arctic space (whose
//! binaries are absent) still loads, with every missing resource listed.

use crate::support::realdata;
use shadowcull::files::{write_tree, ResPaths};
use shadowcull::formats::{binsection, primitives};
use shadowcull::scene::{load_scene, LoadConfig};
use std::collections::BTreeMap;
use std::path::Path;

pub(crate) fn real_model_names(res: &Path) -> Vec<String> {
    let mut names: Vec<String> = shadowcull::files::find_files(res, ".model")
        .unwrap()
        .into_iter()
        .map(|p| {
            p.strip_prefix(res)
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/")
        })
        .collect();
    names.sort();
    names
}

/// A one-chunk space placing every given model once, 10 m apart.
pub(crate) fn world_placing(models: &[String]) -> Vec<(String, Vec<u8>)> {
    let mut chunk = String::from("<root>\n");
    for (i, model) in models.iter().enumerate() {
        chunk += &format!(
            "\t<model>\n\t\t<resource>\t{model}\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t1.000000 0.000000 0.000000\t</row0>\n\t\t\t<row1>\t0.000000 1.000000 0.000000\t</row1>\n\t\t\t<row2>\t0.000000 0.000000 1.000000\t</row2>\n\t\t\t<row3>\t{}.000000 0.000000 50.000000\t</row3>\n\t\t</transform>\n\t</model>\n",
            3 * i
        );
    }
    chunk += "</root>\n";
    let settings = "<space.settings>\n\t<bounds>\n\t\t<minX>\t0\t</minX>\n\t\t<maxX>\t0\t</maxX>\n\t\t<minY>\t0\t</minY>\n\t\t<maxY>\t0\t</maxY>\n\t</bounds>\n</space.settings>\n";
    vec![
        (
            "spaces/real/00000000o.chunk".to_string(),
            chunk.into_bytes(),
        ),
        (
            "spaces/real/space.settings".to_string(),
            settings.as_bytes().to_vec(),
        ),
    ]
}

/// nPrimitives of every group of every index section of a `.primitives`
/// file, straight from the index headers.
fn header_triangles(primitives_file: &Path) -> BTreeMap<String, Vec<u32>> {
    let bytes = std::fs::read(primitives_file).unwrap();
    let container = binsection::parse(&bytes).unwrap();
    let mut groups = BTreeMap::new();
    for entry in &container.entries {
        if entry.name.ends_with("indices") {
            let indices = primitives::read_indices(&bytes[entry.data.clone()]).unwrap();
            groups.insert(
                entry.name.clone(),
                indices.groups.iter().map(|g| g.n_primitives).collect(),
            );
        }
    }
    groups
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn every_real_model_loads_with_its_index_header_counts() {
    let Some(root) = realdata("every_real_model_loads_with_its_index_header_counts") else {
        return;
    };
    let res = root.join("bigworld-14.4.1/res");
    let models = real_model_names(&res);
    assert_eq!(models.len(), 26, "{models:?}");
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &world_placing(&models)).unwrap();
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(vec![dir.path().to_path_buf(), res.clone()]),
        space: "spaces/real".into(),
        speedtrees: Default::default(),
    })
    .unwrap();
    assert!(scene.problems.is_empty(), "{:#?}", scene.problems);
    assert_eq!(scene.models.len(), models.len());

    let mut total_groups = 0;
    for model in &scene.models {
        // Oracle: the visual's own <primitiveGroup> elements, counted as text,
        // and each group's nPrimitives from its index section header.
        let visual_text = std::fs::read_to_string(model.file.with_extension("visual")).unwrap();
        let group_elements = visual_text.matches("<primitiveGroup>").count();
        assert_eq!(model.groups.len(), group_elements, "{}", model.resource);
        total_groups += group_elements;
        let headers = header_triangles(&model.file.with_extension("primitives"));
        let header_total: u32 = headers.values().flatten().sum();
        let loaded_total: usize = model.groups.iter().map(|g| g.triangles.len()).sum();
        assert!(loaded_total > 0, "{}", model.resource);
        for group in &model.groups {
            let per_section: Vec<u32> = headers
                .values()
                .filter_map(|groups| groups.get(group.primitive_group).copied())
                .collect();
            assert!(
                per_section.contains(&(group.triangles.len() as u32)),
                "{} group {}: {} triangles, headers say {per_section:?}",
                model.resource,
                group.primitive_group,
                group.triangles.len()
            );
        }
        assert!(loaded_total as u32 <= header_total, "{}", model.resource);
        for triangle in &model.triangles[..] {
            for &v in triangle {
                assert!(
                    model.positions[v as usize].is_finite(),
                    "{}",
                    model.resource
                );
            }
        }
    }
    let stats = scene.stats();
    assert_eq!(
        (stats.instances, stats.models, stats.groups),
        (26, 26, total_groups)
    );
    assert_eq!(
        stats.triangles,
        scene
            .models
            .iter()
            .map(|m| m.triangles.len())
            .sum::<usize>()
    );
    // The minspec trees' leaves are alpha-tested and double-sided.
    let tree = scene
        .models
        .iter()
        .find(|m| m.resource == "sets/minspec/props/tree/model/tree.model")
        .unwrap();
    assert!(tree.groups.iter().any(|g| g.alpha_tested && g.double_sided));
    assert!(stats.alpha_tested_groups > 0 && stats.double_sided_groups > 0);
}

/// Every real model of `root`'s bigworld-14.4.1 in a row (see
/// [`world_placing`]) over a thin ground slab (the real unit cube scaled),
/// written to a temporary folder (keep it while the scene is used) and
/// loaded; also the model names in placing order.
pub(crate) fn world_on_a_slab(
    root: &Path,
) -> (tempfile::TempDir, Vec<String>, shadowcull::scene::Scene) {
    let res = root.join("bigworld-14.4.1/res");
    let models = real_model_names(&res);
    let mut files = world_placing(&models);
    let chunk = String::from_utf8(files[0].1.clone()).unwrap();
    let ground = "\t<model>\n\t\t<resource>\thelpers/models/unit_cube.model\t</resource>\n\t\t<transform>\n\t\t\t<row0>\t90.000000 0.000000 0.000000\t</row0>\n\t\t\t<row1>\t0.000000 0.100000 0.000000\t</row1>\n\t\t\t<row2>\t0.000000 0.000000 20.000000\t</row2>\n\t\t\t<row3>\t-5.000000 -0.100000 40.000000\t</row3>\n\t\t</transform>\n\t</model>\n</root>\n";
    files[0].1 = chunk.replace("</root>\n", ground).into_bytes();
    let dir = tempfile::tempdir().unwrap();
    write_tree(dir.path(), &files).unwrap();
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(vec![dir.path().to_path_buf(), res]),
        space: "spaces/real".into(),
        speedtrees: Default::default(),
    })
    .unwrap();
    (dir, models, scene)
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn a_world_of_real_models_bakes_identically_with_the_oracle() {
    // Every real model in a row over a thin ground slab (the real unit cube
    // scaled), lit from above at an angle: BVH and brute force must agree
    // on real geometry (skinned, nodefull, alpha-tested, double-sided).
    let Some(root) = realdata("a_world_of_real_models_bakes_identically_with_the_oracle") else {
        return;
    };
    let (_dir, models, scene) = world_on_a_slab(&root);
    assert!(scene.problems.is_empty(), "{:#?}", scene.problems);
    let mut config = shadowcull::bake::BakeConfig {
        face_culling: shadowcull::formats::bake_settings::FaceCulling::Back,
        height_bias: 0.05,
        tie_epsilon: 1e-4,
        lights: vec![shadowcull::formats::bake_settings::LightSettings {
            name: "sun".into(),
            kind: shadowcull::formats::bake_settings::LightKind::Directional {
                direction: glam::DVec3::new(0.3, -1.0, 0.2).normalize(),
                texel_size: 0.1,
            },
        }],
        brute_force: false,
        ..Default::default()
    };
    let fast = shadowcull::bake::bake(&scene, &config, &shadowcull::bake::Silent).unwrap();
    // The oracle tests every triangle per ray: compare on a coarser grid.
    if let shadowcull::formats::bake_settings::LightKind::Directional { texel_size, .. } =
        &mut config.lights[0].kind
    {
        *texel_size = 0.7;
    }
    let coarse = shadowcull::bake::bake(&scene, &config, &shadowcull::bake::Silent).unwrap();
    config.brute_force = true;
    let oracle = shadowcull::bake::bake(&scene, &config, &shadowcull::bake::Silent).unwrap();
    assert_eq!(coarse.masks, oracle.masks);
    // Everything standing on the slab shadows it somewhere.
    let useful_instances = (0..models.len())
        .filter(|&i| {
            let first = fast.casters.first_of_instance[i].unwrap() as usize;
            let groups: usize = scene.instances[i]
                .parts
                .iter()
                .flatten()
                .map(|m| scene.models[*m].groups.len())
                .sum();
            fast.masks[first..first + groups].iter().any(|m| *m != 0)
        })
        .count();
    assert!(
        useful_instances >= 20,
        "only {useful_instances} of {} useful",
        models.len()
    );
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn arctic_loads_and_lists_every_missing_resource() {
    let Some(root) = realdata("arctic_loads_and_lists_every_missing_resource") else {
        return;
    };
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(vec![root.join("fantasydemo-arctic/res")]),
        space: "spaces/arctic".into(),
        speedtrees: Default::default(),
    })
    .unwrap();
    let stats = scene.stats();
    // README: 104 chunks; 250 <model> placements plus 4 <shell>s.
    assert_eq!(stats.chunks, 104);
    assert_eq!(stats.instances, 254);
    // No .primitives and no .cdata were collected: nothing loads, and each
    // of the 18 placed model resources and 100 terrain blocks is a problem.
    assert_eq!((stats.models, stats.terrain_blocks), (0, 0));
    let model_problems: Vec<_> = scene
        .problems
        .iter()
        .filter(|p| p.what.ends_with(".model"))
        .collect();
    assert_eq!(model_problems.len(), 18, "{model_problems:#?}");
    for problem in &model_problems {
        assert!(problem.why.contains(".primitives"), "{problem:?}");
    }
    let terrain_problems = scene
        .problems
        .iter()
        .filter(|p| p.what.ends_with("<terrain>"))
        .count();
    assert_eq!(terrain_problems, 100);
    assert!(scene
        .instances
        .iter()
        .any(|i| scene.chunks[i.chunk].grid.is_none()));
}
