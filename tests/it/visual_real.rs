//! The `.model` and `.visual` readers on every real file, checked against
//! facts read by hand from the files and from the arctic README's table.

use crate::support::realdata;
use crate::xml_real::files_with_extensions;
use shadowcull::formats::model::{parse_model, visual_candidates, ModelFile, VisualKind};
use shadowcull::formats::visual::{
    node_to_root, parse_visual, primitives_name, split_section_resource, Visual,
};
use shadowcull::formats::{parse_data_section, Section};
use std::path::Path;

fn read(path: &Path) -> Section {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    parse_data_section(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A model, its visual's resource name and the visual, from a res root.
fn load(res: &Path, model: &str) -> (ModelFile, String, Visual) {
    let m = parse_model(&read(&res.join(model))).unwrap_or_else(|e| panic!("{model}: {e}"));
    let visual_name = visual_candidates(&m)
        .into_iter()
        .find(|c| res.join(c).is_file())
        .unwrap_or_else(|| panic!("{model}: no visual among {:?}", visual_candidates(&m)));
    let visual = parse_visual(&read(&res.join(&visual_name)))
        .unwrap_or_else(|e| panic!("{visual_name}: {e}"));
    (m, visual_name, visual)
}

fn groups(v: &Visual) -> Vec<&shadowcull::formats::visual::PrimitiveGroup> {
    v.render_sets
        .iter()
        .flat_map(|r| &r.geometries)
        .flat_map(|g| &g.groups)
        .collect()
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn every_real_model_and_visual_reads() {
    let Some(root) = realdata("every_real_model_and_visual_reads") else {
        return;
    };
    let mut models = 0;
    let mut visuals = 0;
    for set in ["bigworld-14.4.1/res", "fantasydemo-arctic/res"] {
        let res = root.join(set);
        for path in files_with_extensions(&res, &[".model"]) {
            let rel = path
                .strip_prefix(&res)
                .unwrap()
                .to_str()
                .unwrap()
                .to_string();
            let (_, visual_name, visual) = load(&res, &rel);
            models += 1;
            // Every geometry section resolves to a .primitives file name the
            // way the engine resolves it.
            let own = primitives_name(&visual_name);
            for g in visual.render_sets.iter().flat_map(|r| &r.geometries) {
                for name in [&g.vertices, &g.primitive] {
                    let (file, section) = split_section_resource(&own, name)
                        .unwrap_or_else(|| panic!("{visual_name}: cannot split {name}"));
                    assert!(file.ends_with(".primitives") && !section.is_empty());
                    // The 14.4.1 set ships its .primitives: they must exist.
                    if set.starts_with("bigworld") {
                        assert!(res.join(&file).is_file(), "{visual_name}: {file} missing");
                    }
                }
            }
        }
        for path in files_with_extensions(&res, &[".visual"]) {
            let v =
                parse_visual(&read(&path)).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert!(!v.render_sets.is_empty(), "{}", path.display());
            for set in &v.render_sets {
                assert!(!set.geometries.is_empty(), "{}", path.display());
                assert!(set.first_node < v.nodes.len());
            }
            visuals += 1;
        }
    }
    // bigworld-14.4.1: 26 models and visuals; arctic: 20 of each.
    assert_eq!((models, visuals), (46, 46));
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn bigworld_facts() {
    let Some(root) = realdata("bigworld_facts") else {
        return;
    };
    let res = root.join("bigworld-14.4.1/res");

    let (tree, name, v) = load(&res, "sets/minspec/props/tree/model/tree.model");
    assert_eq!(tree.kind, VisualKind::Nodeless);
    assert_eq!(name, "sets/minspec/props/tree/model/tree.visual");
    assert_eq!(
        tree.parent.as_deref(),
        Some("sets/minspec/props/tree/model/tree_lod1")
    );
    let g = groups(&v);
    assert_eq!(g.len(), 1);
    assert!(g[0].alpha_tested() && g[0].double_sided());

    let (axe, name, v) = load(&res, "sets/town/props/axe.model");
    assert_eq!(axe.kind, VisualKind::Nodefull);
    assert_eq!(name, "sets/town/props/axe.visual");
    assert_eq!(
        axe.parent.as_deref(),
        Some("sets/town/props/lods/axe_lod01")
    );
    let g = groups(&v);
    assert_eq!(g.iter().map(|g| g.index).collect::<Vec<_>>(), [0, 1]);
    assert_eq!(g[0].material_identifier, "axehead");
    assert_eq!(g[1].material_identifier, "axehandle");
    assert!(g.iter().all(|g| !g.alpha_tested() && !g.double_sided()));
    // Scene Root is identity with children axe_lod0, HP_right_hand,
    // HP_axe_head; HP_axe_head's row3 is 0.147664 0.065944 0.025429.
    assert_eq!(v.nodes.len(), 4);
    assert_eq!(v.nodes[3].identifier, "HP_axe_head");
    assert_eq!(v.nodes[3].parent, Some(0));
    let p = node_to_root(&v, "HP_axe_head")
        .unwrap()
        .transform_point3(glam::DVec3::ZERO);
    assert!((p - glam::DVec3::new(0.147664, 0.065944, 0.025429)).length() < 1e-9);
    assert_eq!(v.render_sets[0].nodes, ["Scene Root"]);
    assert!(!v.render_sets[0].treat_as_world_space_object);

    // Skinned characters.
    for model in [
        "characters/npc/chicken/chicken.model",
        "characters/avatars/ranger/ranger_body.model",
    ] {
        let (m, _, v) = load(&res, model);
        assert_eq!(m.kind, VisualKind::Nodefull);
        assert!(
            v.render_sets.iter().all(|r| r.treat_as_world_space_object),
            "{model}"
        );
        assert!(v.nodes.len() > 1, "{model}");
    }
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn arctic_readme_table() {
    let Some(root) = realdata("arctic_readme_table") else {
        return;
    };
    let res = root.join("fantasydemo-arctic/res");
    // (model, primitive groups, alpha-tested, double-sided) from README.md.
    let table: [(&str, usize, bool, bool); 20] = [
        ("sets/items/upperskull.model", 1, false, false),
        ("sets/t_ice/props/ice_rock_02.model", 1, false, false),
        ("sets/t_ice/props/pine_snow01.model", 2, true, true),
        ("sets/dungeon/props/web03.model", 1, false, true),
        ("sets/dungeon/props/flameplane.model", 1, false, false),
        ("sets/t_ice/props/pine_substitute_snow.model", 2, true, true),
        ("sets/dungeon/props/web01.model", 1, false, true),
        ("sets/dungeon/props/web02.model", 1, false, true),
        ("sets/town/props/t_candle.model", 2, true, true),
        (
            "sets/minspec/props/dungeon_misc/models/torch_dungeon.model",
            1,
            false,
            false,
        ),
        ("sets/temperate/props/brush.model", 1, true, true),
        ("sets/dungeon/props/projector_light.model", 1, false, false),
        ("sets/town/props/t_table.model", 1, false, false),
        ("sets/town/props/t_table_lod01.model", 1, false, false),
        (
            "sets/temperate/props/dungeon/entrance/dungeon_facade.model",
            2,
            false,
            false,
        ),
        (
            "sets/temperate/props/dungeon/entrance/dungeon_facade_lod01.model",
            2,
            false,
            false,
        ),
        (
            "sets/temperate/shells/teleport_room/teleport_room.model",
            7,
            false,
            false,
        ),
        (
            "sets/temperate/shells/dungeon/entrance_connector.model",
            2,
            false,
            false,
        ),
        (
            "sets/temperate/shells/dungeon/tunnel_damaged.model",
            2,
            false,
            false,
        ),
        (
            "sets/temperate/shells/dungeon/exit_shell.model",
            1,
            false,
            false,
        ),
    ];
    for (model, count, at, ds) in table {
        let (_, _, v) = load(&res, model);
        let g = groups(&v);
        assert_eq!(g.len(), count, "{model}");
        assert_eq!(g.iter().any(|g| g.alpha_tested()), at, "{model} AT");
        assert_eq!(g.iter().any(|g| g.double_sided()), ds, "{model} DS");
    }

    // "2 renderSets, skinned"; the leaves (Plane02) are the alpha-tested set.
    let (_, _, pine) = load(&res, "sets/t_ice/props/pine_snow01.model");
    assert_eq!(pine.render_sets.len(), 2);
    assert!(pine
        .render_sets
        .iter()
        .all(|r| r.treat_as_world_space_object));
    assert_eq!(
        pine.render_sets[0].geometries[0].vertices,
        "Plane02.vertices"
    );
    let leaves = &pine.render_sets[0].geometries[0].groups[0];
    assert!(leaves.alpha_tested() && leaves.double_sided());
    let trunk = &pine.render_sets[1].geometries[0].groups[0];
    assert!(!trunk.alpha_tested() && !trunk.double_sided());

    // Models naming `V = ….static` find `V.visual` = `*.static.visual`,
    // and their full-path sections resolve as PRIMITIVES_NEEDED.txt lists.
    let (m, name, v) = load(&res, "sets/items/upperskull.model");
    assert_eq!(m.visual, "sets/items/upperskull.static");
    assert_eq!(name, "sets/items/upperskull.static.visual");
    let g = &v.render_sets[0].geometries[0];
    assert_eq!(
        split_section_resource(&primitives_name(&name), &g.vertices),
        Some((
            "sets/items/upperskull.static.primitives".to_string(),
            "vertices".to_string()
        ))
    );
    let (_, name, v) = load(&res, "sets/town/props/t_candle.model");
    assert_eq!(v.render_sets.len(), 2);
    let g = &v.render_sets[0].geometries[0];
    let (file, _) = split_section_resource(&primitives_name(&name), &g.primitive).unwrap();
    assert_eq!(file, "sets/town/props/t_candle.primitives");

    // LOD chain: t_table → t_table_lod01; shells have no <extent>.
    let (t_table, _, _) = load(&res, "sets/town/props/t_table.model");
    assert_eq!(
        t_table.parent.as_deref(),
        Some("sets/town/props/t_table_lod01")
    );
    assert_eq!(t_table.extent, Some(10.0));
    let (shell, _, _) = load(&res, "sets/temperate/shells/dungeon/exit_shell.model");
    assert_eq!(shell.extent, None);
}
