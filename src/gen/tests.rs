//! Whole-world checks of the generator: determinism, resolvable references,
//! the `Expected` oracle against the written XML, geometry invariants.

use super::world::{det3, plan};
use super::*;
use std::collections::{BTreeMap, BTreeSet};

fn text(w: &GeneratedWorld, path: &str) -> String {
    String::from_utf8(
        w.file(path)
            .unwrap_or_else(|| panic!("missing {path}"))
            .to_vec(),
    )
    .expect("generated text is UTF-8")
}

/// Trimmed values of every `<tag>…</tag>` leaf in `s`.
fn leaves<'a>(s: &'a str, tag: &str) -> Vec<&'a str> {
    let open = format!("<{tag}>");
    let close = format!("</{tag}>");
    let mut out = Vec::new();
    let mut rest = s;
    while let Some(i) = rest.find(&open) {
        let after = &rest[i + open.len()..];
        let Some(j) = after.find(&close) else { break };
        out.push(after[..j].trim());
        rest = &after[j + close.len()..];
    }
    out
}

fn chunk_paths(w: &GeneratedWorld) -> Vec<String> {
    w.files
        .iter()
        .map(|(p, _)| p.clone())
        .filter(|p| p.ends_with(".chunk"))
        .collect()
}

fn parse_rows(m: &str) -> [[f64; 3]; 4] {
    let mut rows = [[0.0; 3]; 4];
    for (i, row) in rows.iter_mut().enumerate() {
        let v: Vec<f64> = leaves(m, &format!("row{i}"))[0]
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        row.copy_from_slice(&v);
    }
    rows
}

#[test]
fn preset_names_round_trip() {
    for p in Preset::ALL {
        assert_eq!(Preset::from_name(p.name()), Some(p));
    }
    assert_eq!(Preset::from_name("Village"), Some(Preset::Village));
    assert_eq!(Preset::from_name("huge"), None);
}

#[test]
fn same_seed_same_bytes_other_seed_other_bytes() {
    for p in [Preset::Small, Preset::Village, Preset::Forest] {
        let a = generate(p, 7);
        let b = generate(p, 7);
        assert_eq!(a, b);
        let c = generate(p, 8);
        assert_eq!(
            a.files.iter().map(|f| &f.0).collect::<Vec<_>>(),
            c.files.iter().map(|f| &f.0).collect::<Vec<_>>(),
            "the layout does not depend on the seed"
        );
        let differing = a
            .files
            .iter()
            .zip(&c.files)
            .filter(|(x, y)| x.0.ends_with(".chunk") && x.1 != y.1)
            .count();
        assert!(differing > 0, "{p:?}: seed changed no chunk");
    }
}

#[test]
fn paths_are_sorted_unique_and_relative() {
    let w = generate(Preset::Village, 1);
    for pair in w.files.windows(2) {
        assert!(pair[0].0 < pair[1].0, "{} !< {}", pair[0].0, pair[1].0);
    }
    for (p, _) in &w.files {
        assert!(!p.starts_with('/') && !p.contains('\\') && !p.contains(".."));
    }
    assert!(w.file(SETTINGS_FILE).is_some());
}

fn check_references(w: &GeneratedWorld, space: &str) {
    let settings = text(w, SETTINGS_FILE);
    assert_eq!(leaves(&settings, "space"), vec![space]);
    assert_eq!(leaves(&settings, "path"), vec!["."]);
    let mut resources = BTreeSet::new();
    for c in chunk_paths(w) {
        let s = text(w, &c);
        for r in leaves(&s, "resource") {
            if r.contains(".cdata/") {
                let (file, _) = r.split_once('/').unwrap();
                assert!(w.file(&format!("{space}/{file}")).is_some(), "{c}: {r}");
            } else {
                resources.insert(r.to_string());
            }
        }
    }
    assert!(!resources.is_empty());
    for r in &resources {
        let model = text(w, r);
        let visual_base = leaves(&model, "nodelessVisual")
            .into_iter()
            .chain(leaves(&model, "nodefullVisual"))
            .next()
            .unwrap_or_else(|| panic!("{r} names no visual"))
            .to_string();
        let visual = text(w, &format!("{visual_base}.visual"));
        assert!(visual.contains("<renderSet>"));
        assert!(w.file(&format!("{visual_base}.primitives")).is_some());
    }
}

#[test]
fn every_reference_resolves_to_a_generated_file() {
    for p in [Preset::Small, Preset::Village] {
        let w = generate(p, 3);
        check_references(&w, &format!("spaces/{}", p.name()));
    }
}

/// Recounts `Expected` from the written chunk and visual XML alone (all but
/// `triangles`, which needs the `.primitives` reader).
fn recount(w: &GeneratedWorld) -> Expected {
    let mut e = Expected::default();
    let mut distinct = BTreeSet::new();
    let mut proxies = BTreeSet::new();
    let mut per_model: BTreeMap<String, (u64, u64, u64)> = BTreeMap::new();
    let settings = crate::formats::bake_settings::from_bytes(
        w.file(SETTINGS_FILE).unwrap(),
        std::path::Path::new(SETTINGS_FILE),
    )
    .unwrap();
    for c in chunk_paths(w) {
        // Text or packed, read as the bake reads it.
        let root = crate::formats::parse_data_section(w.file(&c).unwrap()).unwrap();
        e.chunks += 1;
        e.terrain_blocks += root.children_named("terrain").count() as u64;
        for m in root.children_named("model") {
            e.instances += 1;
            let flag = m
                .child("castsShadow")
                .or_else(|| m.child("editorOnly").and_then(|e| e.child("castsShadow")));
            if flag.is_some_and(|f| f.value == "false") {
                e.receiver_only_instances += 1;
            }
            for r in m.children_named("resource").map(|r| r.value.as_str()) {
                distinct.insert(r.to_string());
                let counts = per_model.entry(r.to_string()).or_insert_with(|| {
                    let model = text(w, r);
                    let base = leaves(&model, "nodelessVisual")
                        .into_iter()
                        .chain(leaves(&model, "nodefullVisual"))
                        .next()
                        .unwrap()
                        .to_string();
                    let v = text(w, &format!("{base}.visual"));
                    (
                        v.matches("<primitiveGroup>").count() as u64,
                        v.matches("alphaTestEnable").count() as u64,
                        v.matches("doubleSided").count() as u64,
                    )
                });
                e.groups += counts.0;
                e.alpha_tested_groups += counts.1;
                e.double_sided_groups += counts.2;
            }
        }
        for tree in root.children_named("speedtree") {
            e.speedtrees += 1;
            match settings
                .speedtrees
                .proxy_for(tree.child_text("spt").unwrap())
            {
                Some(proxy) => {
                    proxies.insert(format!("{proxy:?}"));
                }
                None => e.speedtrees_without_proxy += 1,
            }
        }
    }
    e.models = distinct.len() as u64;
    e.speedtree_proxies = proxies.len() as u64;
    e
}

#[test]
fn expected_counts_match_the_written_xml() {
    for p in Preset::ALL {
        let w = generate(p, 11);
        let mut r = recount(&w);
        r.triangles = w.expected.triangles;
        assert_eq!(r, w.expected, "{p:?}");
    }
}

#[test]
fn triangle_count_matches_per_resource_meshes() {
    let w = generate(Preset::Village, 5);
    let tris: BTreeMap<String, u64> = models::catalog(1)
        .into_iter()
        .map(|d| (d.kind.resource(), d.mesh.triangles() as u64))
        .collect();
    let mut total = 0;
    for c in chunk_paths(&w) {
        let s = text(&w, &c);
        for r in leaves(&s, "resource") {
            if !r.contains(".cdata/") {
                total += tris[r];
            }
        }
    }
    assert_eq!(total, w.expected.triangles);
}

#[test]
fn village_has_every_feature() {
    let w = generate(Preset::Village, 1);
    let e = w.expected;
    assert_eq!(e.chunks, 9);
    assert_eq!(e.terrain_blocks, 9);
    assert!((100..=200).contains(&e.instances), "{e:?}");
    assert!(e.alpha_tested_groups > 0 && e.double_sided_groups > e.alpha_tested_groups);
    assert!(e.receiver_only_instances >= 2);
    assert_eq!(e.models, 8);
    let all: String = chunk_paths(&w).iter().map(|c| text(&w, c)).collect();
    assert!(all.contains("<editorOnly>\n\t\t\t<castsShadow>\tfalse\t</castsShadow>"));
    assert!(all.contains("\t\t<castsShadow>\tfalse\t</castsShadow>"));
    assert!(all.contains("<entity>") && all.contains("<worldNavmesh>"));
    assert!(all.split("<model>").any(|m| leaves(
        &m[..m.find("</model>").unwrap_or(m.len())],
        "resource"
    )
    .len()
        == 2));
    // Outdoor chunks imply their transform from the name.
    assert!(!all.contains("\n\t<transform>"));
    let chunk_names: BTreeSet<_> = chunk_paths(&w).into_iter().collect();
    for gx in -1i32..=1 {
        for gz in -1i32..=1 {
            let p = format!("spaces/village/{:04x}{:04x}o.chunk", gx as u16, gz as u16);
            assert!(chunk_names.contains(&p), "{p}");
        }
    }
    assert!(chunk_names.contains("spaces/village/ffffffffo.chunk"));
}

#[test]
fn mirrored_placements_have_negative_determinants() {
    let pl = plan(Preset::Village, 4);
    let w = generate(Preset::Village, 4);
    let mut planned = 0;
    for ch in &pl.chunks {
        for p in &ch.placements {
            assert_eq!(p.mirrored, det3(&p.transform) < 0.0);
            planned += p.mirrored as usize;
        }
    }
    assert!(planned >= 3, "too few mirrored placements: {planned}");
    // And as written, after %.6f rounding.
    let mut written = 0;
    let mut nonuniform = 0;
    for c in chunk_paths(&w) {
        let s = text(&w, &c);
        for m in s.split("<model>").skip(1) {
            let rows = parse_rows(&m[..m.find("</model>").unwrap()]);
            let d = det3(&rows);
            assert!(d.abs() > 0.05, "near-singular transform {rows:?}");
            written += (d < 0.0) as usize;
            let len = |r: [f64; 3]| (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            if (len(rows[0]) - len(rows[1])).abs() > 0.05 {
                nonuniform += 1;
            }
        }
    }
    assert_eq!(written, planned);
    assert!(nonuniform > 10);
}

#[test]
fn space_settings_and_bake_settings_describe_the_world() {
    let w = generate(Preset::Village, 2);
    let s = text(&w, "spaces/village/space.settings");
    assert!(s.starts_with(
        "<space.settings>\n\t<bounds>\n\t\t<minX>\t-1\t</minX>\n\t\t<maxX>\t1\t</maxX>\n"
    ));
    assert_eq!(leaves(&s, "chunkSize"), vec!["100.000000"]);
    assert_eq!(leaves(&s, "version"), vec!["200"]);
    assert_eq!(leaves(&s, "heightMapSize"), vec!["32"]);
    let b = text(&w, SETTINGS_FILE);
    assert_eq!(leaves(&b, "type"), vec!["directional", "spot", "point"]);
    let texel: f64 = leaves(&b, "texelSize")[0].parse().unwrap();
    let texels = 300.0 / texel;
    assert!((500.0..=520.0).contains(&texels), "{texels}");
}

#[test]
fn terrain_blocks_are_continuous_and_one_has_a_hole() {
    let pl = plan(Preset::Village, 9);
    let hms = pl.params.height_map_size;
    let grids: BTreeMap<(i32, i32), _> = pl
        .chunks
        .iter()
        .map(|c| ((c.gx, c.gz), world::height_map(&pl, c)))
        .collect();
    let g = &grids[&(0, 0)];
    assert_eq!(g.width, hms + 5);
    assert_eq!(g.heights.len(), g.width * g.height);
    let right = &grids[&(1, 0)];
    let w = g.width;
    for z in 0..w {
        // Sample at local x = chunkSize in (0,0) is local x = 0 in (1,0);
        // the borders overlap further: 2 samples either side.
        for k in 0..5 {
            assert_eq!(g.heights[z * w + hms + k], right.heights[z * w + k]);
        }
    }
    let spread = g.heights.iter().cloned().fold(f32::NEG_INFINITY, f32::max)
        - g.heights.iter().cloned().fold(f32::INFINITY, f32::min);
    assert!(spread > 0.5, "hills are too flat: {spread}");
    let holes: Vec<_> = pl
        .chunks
        .iter()
        .filter_map(|c| world::hole_map(&pl, c))
        .collect();
    assert_eq!(holes.len(), 1);
    assert!(holes[0].holes.iter().any(|&h| h) && !holes[0].holes.iter().all(|&h| h));
}

#[test]
fn fixture_presets_stay_small() {
    let total = |w: &GeneratedWorld| w.files.iter().map(|f| f.1.len()).sum::<usize>();
    let v = generate(Preset::Village, 1);
    assert!(total(&v) < 1_000_000, "village is {} bytes", total(&v));
    let s = generate(Preset::Small, 1);
    assert!(total(&s) < 200_000, "small is {} bytes", total(&s));
    assert!((8..=20).contains(&s.expected.instances));
    assert_eq!(s.expected.models, 8, "small shows every model");
    assert_eq!(s.expected.receiver_only_instances, 2);
    assert_eq!(s.expected.chunks, 4);
}

#[test]
fn bench_is_big() {
    let w = generate(Preset::Bench, 1);
    let e = w.expected;
    assert_eq!(e.chunks, 100);
    assert!(e.instances >= 20_000, "{e:?}");
    assert!(e.triangles >= 2_000_000, "{e:?}");
    check_references(&w, "spaces/bench");
}

#[test]
fn written_binaries_read_back_with_the_crate_readers() {
    use crate::formats::{binsection, primitives, terrain};
    use crate::gen::mesh::{is_closed_and_consistent, signed_volume};
    for p in [Preset::Small, Preset::Village] {
        let w = generate(p, 6);
        let mut tris_of_model: BTreeMap<String, u64> = BTreeMap::new();
        for (path, bytes) in w.files.iter().filter(|f| f.0.ends_with(".primitives")) {
            let bs = binsection::parse(bytes).unwrap();
            let v = primitives::read_vertices(bs.get("vertices").unwrap().0).unwrap();
            let ix = primitives::read_indices(bs.get("indices").unwrap().0).unwrap();
            assert_eq!(v.format, "xyznuv");
            assert_eq!(ix.format, "list", "small meshes use u16 indices");
            let visual = text(&w, &path.replace(".primitives", ".visual"));
            let materials: Vec<&str> = visual.split("<primitiveGroup>").skip(1).collect();
            assert_eq!(ix.groups.len(), materials.len(), "{path}");
            for (g, mat) in materials.iter().enumerate() {
                let idx = primitives::group_triangles(&ix, g, v.positions.len()).unwrap();
                let tris: Vec<[[f32; 3]; 3]> = idx
                    .chunks_exact(3)
                    .map(|t| [t[0], t[1], t[2]].map(|i| v.positions[i as usize]))
                    .collect();
                if !mat.contains("doubleSided") {
                    // Single-sided groups must be closed solids facing out.
                    is_closed_and_consistent(&tris).unwrap_or_else(|e| panic!("{path} {g}: {e}"));
                    assert!(signed_volume(&tris) > 0.0, "{path} group {g} faces inward");
                }
            }
            let n: u64 = ix.groups.iter().map(|g| g.n_primitives as u64).sum();
            tris_of_model.insert(path.replace(".primitives", ".model"), n);
        }
        let mut triangles = 0;
        for c in chunk_paths(&w) {
            for r in leaves(&text(&w, &c), "resource") {
                if !r.contains(".cdata/") {
                    triangles += tris_of_model[r];
                }
            }
        }
        assert_eq!(triangles, w.expected.triangles, "{p:?}");

        let pl = plan(p, 6);
        let mut holes = 0;
        for ch in &pl.chunks {
            let cdata = w
                .file(&format!("{}/{}.cdata", pl.params.space(), ch.name()))
                .unwrap();
            let t = terrain::read_terrain(cdata, "terrain2").unwrap();
            let want = world::height_map(&pl, ch);
            assert_eq!(t.heights.width, pl.params.height_map_size + 5);
            assert_eq!(t.heights.height, want.height);
            for (a, b) in t.heights.heights.iter().zip(&want.heights) {
                assert!((a - b).abs() < 1e-5, "{a} vs {b}");
            }
            if let Some(h) = t.holes {
                assert_eq!(h.width, pl.params.height_map_size);
                holes += h.holes.iter().filter(|&&x| x).count();
            }
        }
        let n = (pl.params.height_map_size / 8).max(2);
        assert_eq!(holes, n * n, "{p:?}");
    }
}

#[test]
fn scene_loader_reads_back_every_generated_model_exactly() {
    // The generator's in-memory meshes against what the whole loader
    // (model → visual → primitives, node transform applied) makes of the
    // written files: same groups, flags, triangles and positions.
    use crate::files::{write_tree, ResPaths};
    use crate::scene::{load_scene, LoadConfig};
    for preset in [Preset::Small, Preset::Village] {
        let world = generate(preset, 2);
        let dir = tempfile::tempdir().unwrap();
        write_tree(dir.path(), &world.files).unwrap();
        let scene = load_scene(&LoadConfig {
            res_paths: ResPaths::new(vec![dir.path().to_path_buf()]),
            space: plan(preset, 2).params.space(),
            speedtrees: Default::default(),
        })
        .unwrap();
        let catalog = models::catalog(plan(preset, 2).params.detail);
        assert!(!scene.models.is_empty());
        for model in &scene.models {
            let def = catalog
                .iter()
                .find(|d| d.kind.resource() == model.resource)
                .unwrap_or_else(|| panic!("{} is not a catalogue model", model.resource));
            let mesh = &def.mesh;
            assert_eq!(model.groups.len(), mesh.groups.len(), "{}", model.resource);
            for (i, (group, material)) in model.groups.iter().zip(&def.materials).enumerate() {
                assert_eq!(
                    group.alpha_tested, material.alpha_test,
                    "{} group {i}",
                    model.resource
                );
                assert_eq!(
                    group.double_sided, material.double_sided,
                    "{} group {i}",
                    model.resource
                );
                let written = &mesh.groups[i];
                assert_eq!(group.triangles.len(), written.n_primitives as usize);
                let first = written.start_index as usize;
                for (t, triangle) in model.triangles[group.triangles.clone()].iter().enumerate() {
                    for (corner, &vertex) in triangle.iter().enumerate() {
                        let expected_index = mesh.indices[first + 3 * t + corner] as usize;
                        let p = mesh.positions[expected_index];
                        let expected = match &def.node {
                            // Rows as written (%.6f), applied as p·M.
                            Some(m) => {
                                let m = m.map(|row| row.map(|v| (v * 1e6).round() / 1e6));
                                let [x, y, z] = p.map(f64::from);
                                [0, 1, 2].map(|c| {
                                    (x * m[0][c] + y * m[1][c] + z * m[2][c] + m[3][c]) as f32
                                })
                            }
                            None => p,
                        };
                        let got = model.positions[vertex as usize].to_array();
                        for c in 0..3 {
                            assert!(
                                (got[c] - expected[c]).abs() <= 1e-5 * (1.0 + expected[c].abs()),
                                "{} group {i} triangle {t}: {got:?} vs {expected:?}",
                                model.resource
                            );
                        }
                        if def.node.is_none() {
                            assert_eq!(got, expected, "{}: exact without a node", model.resource);
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn streamed_generation_equals_the_in_memory_one_and_any_size_loads() {
    use crate::files::{write_tree, ResPaths};
    use crate::scene::{load_scene, LoadConfig};
    let world = generate(Preset::Village, 3);
    let mut streamed = Vec::new();
    let expected = generate_each(WorldSize::Preset(Preset::Village), 3, |path, bytes| {
        streamed.push((path.to_string(), bytes));
        Ok::<(), ()>(())
    })
    .unwrap();
    streamed.sort();
    assert_eq!(streamed, world.files);
    assert_eq!(expected, world.expected);

    let dir = tempfile::tempdir().unwrap();
    let expected = generate_each(WorldSize::BenchChunks(2), 1, |path, bytes| {
        write_tree(dir.path(), &[(path.to_string(), bytes)])
    })
    .unwrap();
    assert_eq!((expected.chunks, expected.terrain_blocks), (4, 4));
    assert!(expected.instances >= 4 * 300, "{expected:?}");
    let scene = load_scene(&LoadConfig {
        res_paths: ResPaths::new(vec![dir.path().to_path_buf()]),
        space: "spaces/bench".into(),
        speedtrees: Default::default(),
    })
    .unwrap();
    assert!(scene.problems.is_empty(), "{:?}", scene.problems);
    assert_eq!(scene.stats().instances as u64, expected.instances);
    assert_eq!(scene.stats().triangles as u64, expected.triangles);
    assert!(scene.terrain.iter().all(|b| b.cells() == (128, 128)));
}

#[test]
fn stacked_copies_repeat_the_first_model_and_nothing_else() {
    let world = generate(Preset::Small, 1);
    let (path, chunk) = world
        .files
        .iter()
        .find(|(p, _)| p.ends_with(".chunk"))
        .unwrap();
    let count = |bytes: &[u8]| String::from_utf8_lossy(bytes).matches("<model>").count();
    let stacked = stack_first_model(chunk, 5).unwrap();
    assert_eq!(count(&stacked), count(chunk) + 4, "{path}");
    let root = crate::formats::parse_data_section(&stacked).unwrap();
    let parsed = crate::formats::chunk::parse(&root).unwrap();
    let first = &parsed.instances[0];
    assert!(parsed.instances[..5]
        .iter()
        .all(|m| m.resources == first.resources && m.transform == first.transform));
    assert_eq!(stack_first_model(b"<root></root>", 3), None);
}

#[test]
fn the_forest_holds_speedtrees_every_item_kind_and_packed_chunks() {
    let w = generate(Preset::Forest, 2);
    let e = w.expected;
    assert_eq!((e.chunks, e.terrain_blocks), (9, 9));
    assert_eq!(e.speedtree_proxies, 3, "a .model and two parametric shapes");
    assert_eq!(e.speedtrees_without_proxy, 0, "bake.xml covers every tree");
    let mut packed = 0;
    let mut kinds = BTreeSet::new();
    let mut forms = BTreeSet::new();
    for c in chunk_paths(&w) {
        let bytes = w.file(&c).unwrap();
        packed += usize::from(bytes.starts_with(&crate::formats::packed_xml::MAGIC));
        let root = crate::formats::parse_data_section(bytes).unwrap();
        kinds.extend(root.children.iter().map(|c| c.name.clone()));
        for tree in root.children_named("speedtree") {
            let transform = tree.child("transform").unwrap();
            forms.insert(transform.children.is_empty());
        }
        if c.ends_with(&format!("{}.chunk", world::chunk_name(1, 1))) {
            assert_eq!(root.children_named("speedtree").count(), 22);
            assert_eq!(root.children_named("model").count(), 0);
        }
    }
    assert_eq!(packed, 4, "the corner chunks");
    assert_eq!(forms.len(), 2, "twelve numbers and rows");
    for kind in [
        "speedtree",
        "model",
        "terrain",
        "vlo",
        "particles",
        "audio",
        "UserDataObject",
        "entity",
        "omniLight",
        "worldNavmesh",
        "flora",
        "ControlPoint",
    ] {
        assert!(kinds.contains(kind), "{kind}: {kinds:?}");
    }
    let settings = String::from_utf8(w.file(SETTINGS_FILE).unwrap().to_vec()).unwrap();
    assert!(settings.contains("<speedtrees>") && settings.contains("sets/gen/proxies/bush.model"));
    assert!(
        w.file("sets/gen/proxies/bush.model").is_some(),
        "the proxy model is written"
    );
}
