//! The generator's model catalog: each procedural mesh with its materials,
//! written as the `.model` / `.visual` / `.primitives` triple the engine's
//! exporter produces, and summarised for the `Expected` oracle.

use super::mesh::{Mesh, IDENTITY};
use super::xml::{f6, v3, XmlOut};
use crate::formats::{binsection, primitives};

/// Material flags the bake cares about, per primitive group.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Material {
    pub identifier: &'static str,
    pub alpha_test: bool,
    pub double_sided: bool,
}

const OPAQUE: fn(&'static str) -> Material = |identifier| Material {
    identifier,
    alpha_test: false,
    double_sided: false,
};

/// Which of the catalog's models a placement refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub(crate) enum Kind {
    Crate,
    Pillar,
    Boulder,
    Ring,
    Tree,
    House,
    Banner,
    Signpost,
    /// The `.model` a studio exports as the proxy of its bushes' `.spt`s:
    /// only the forest preset's settings name it, never a chunk.
    Bush,
}

impl Kind {
    #[cfg(test)]
    pub(crate) const ALL: [Kind; 9] = [
        Kind::Crate,
        Kind::Pillar,
        Kind::Boulder,
        Kind::Ring,
        Kind::Tree,
        Kind::House,
        Kind::Banner,
        Kind::Signpost,
        Kind::Bush,
    ];

    /// Resource path without extension.
    pub(crate) fn base(self) -> &'static str {
        match self {
            Kind::Crate => "sets/gen/props/crate",
            Kind::Pillar => "sets/gen/props/pillar",
            Kind::Boulder => "sets/gen/props/boulder",
            Kind::Ring => "sets/gen/props/ring",
            Kind::Tree => "sets/gen/trees/tree",
            Kind::House => "sets/gen/buildings/house",
            Kind::Banner => "sets/gen/props/banner",
            Kind::Signpost => "sets/gen/props/signpost",
            Kind::Bush => "sets/gen/proxies/bush",
        }
    }

    pub(crate) fn resource(self) -> String {
        format!("{}.model", self.base())
    }
}

pub(crate) struct ModelDef {
    pub kind: Kind,
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    /// Transform of the renderSet's node under `Scene Root`; `Some` makes the
    /// model nodefull.
    pub node: Option<[[f64; 3]; 4]>,
}

/// Per placement of a model: what it adds to the `Expected` counts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct ModelStats {
    pub groups: u64,
    pub triangles: u64,
    pub alpha_tested_groups: u64,
    pub double_sided_groups: u64,
}

impl ModelDef {
    pub(crate) fn stats(&self) -> ModelStats {
        ModelStats {
            groups: self.mesh.groups.len() as u64,
            triangles: self.mesh.triangles() as u64,
            alpha_tested_groups: self.materials.iter().filter(|m| m.alpha_test).count() as u64,
            double_sided_groups: self.materials.iter().filter(|m| m.double_sided).count() as u64,
        }
    }
}

/// Builds the catalog. `detail` scales tessellation (bench uses finer
/// meshes so that placements add up to millions of triangles).
pub(crate) fn catalog(detail: usize) -> Vec<ModelDef> {
    let d = detail.max(1);
    vec![
        one_group(Kind::Crate, OPAQUE("crate"), |m| {
            m.add_box([-0.5, 0.0, -0.5], [0.5, 1.0, 0.5])
        }),
        one_group(Kind::Pillar, OPAQUE("stone"), |m| {
            m.add_cylinder([0.0; 3], 0.3, 3.0, 12 * d)
        }),
        one_group(Kind::Boulder, OPAQUE("rock"), |m| {
            // A lumpy sphere: the fixed bumps make it a star-shaped, still
            // closed rock.
            let bumps =
                |i: usize, j: usize| 1.0 + 0.08 * (((i * 5 + j * 3) % 7) as f64 / 6.0 - 0.5);
            m.add_sphere([0.0, 0.6, 0.0], 1.0, 8 * d, 12 * d, &bumps)
        }),
        one_group(Kind::Ring, OPAQUE("bronze"), |m| {
            m.add_torus([0.0; 3], 1.2, 0.35, 16 * d, 8 * d)
        }),
        tree(d),
        house(),
        banner(),
        signpost(),
        one_group(Kind::Bush, OPAQUE("leaves"), |m| {
            // A ball of leaves resting on the ground.
            let round = |_: usize, _: usize| 1.0;
            m.add_sphere([0.0, 0.9, 0.0], 1.0, 6 * d, 10 * d, &round)
        }),
    ]
}

/// A model of one closed, opaque group.
fn one_group(kind: Kind, material: Material, add: impl FnOnce(&mut Mesh)) -> ModelDef {
    let mut m = Mesh::default();
    m.begin_group();
    add(&mut m);
    m.end_group(true);
    ModelDef {
        kind,
        mesh: m,
        materials: vec![material],
        node: None,
    }
}

/// A closed trunk and open crossed cards of alpha-tested, double-sided
/// leaves.
fn tree(d: usize) -> ModelDef {
    let mut m = Mesh::default();
    m.begin_group();
    m.add_cylinder([0.0; 3], 0.25, 4.0, 8 * d);
    m.end_group(true);
    m.begin_group();
    m.add_cards([0.0; 3], 2.5, 2.5, 7.5, 3);
    m.end_group(false);
    ModelDef {
        kind: Kind::Tree,
        mesh: m,
        materials: vec![
            OPAQUE("bark"),
            Material {
                identifier: "leaves",
                alpha_test: true,
                double_sided: true,
            },
        ],
        node: None,
    }
}

/// Walls, roof and chimney: three closed groups.
fn house() -> ModelDef {
    let mut m = Mesh::default();
    m.begin_group();
    m.add_box([-3.0, 0.0, -4.0], [3.0, 4.0, 4.0]);
    m.end_group(true);
    m.begin_group();
    m.add_roof(-3.4, 3.4, 4.0, 6.5, -4.4, 4.4);
    m.end_group(true);
    m.begin_group();
    m.add_box([1.2, 4.5, 1.5], [1.9, 7.2, 2.2]);
    m.end_group(true);
    ModelDef {
        kind: Kind::House,
        mesh: m,
        materials: vec![OPAQUE("walls"), OPAQUE("roof"), OPAQUE("chimney")],
        node: None,
    }
}

/// One open, double-sided panel of cloth.
fn banner() -> ModelDef {
    let mut m = Mesh::default();
    m.begin_group();
    m.add_panel(1.0, 0.5, 3.5);
    m.end_group(false);
    ModelDef {
        kind: Kind::Banner,
        mesh: m,
        materials: vec![Material {
            identifier: "cloth",
            alpha_test: false,
            double_sided: true,
        }],
        node: None,
    }
}

/// Nodefull: the board is modelled at the origin and lifted, turned and
/// scaled by its node, so a reader that skips node transforms puts it in
/// the wrong place.
fn signpost() -> ModelDef {
    let mut m = Mesh::default();
    m.begin_group();
    m.add_box([-0.8, -0.4, -0.1], [0.8, 0.4, 0.1]);
    m.end_group(true);
    let (a, s) = (30f64.to_radians(), 1.5);
    ModelDef {
        kind: Kind::Signpost,
        mesh: m,
        materials: vec![OPAQUE("board")],
        node: Some([
            [s * a.cos(), 0.0, -s * a.sin()],
            [0.0, s, 0.0],
            [s * a.sin(), 0.0, s * a.cos()],
            [0.0, 2.2, 0.0],
        ]),
    }
}

/// The three files of a model, paths relative to the res root.
pub(crate) fn files(def: &ModelDef) -> Vec<(String, Vec<u8>)> {
    let base = def.kind.base();
    let leaf = base.rsplit('/').next().unwrap_or(base);
    let node = def.node.unwrap_or(IDENTITY);
    let (lo, hi) = def.mesh.bounds(&node);

    let mut model = XmlOut::new(&format!("{leaf}.model"));
    let visual_tag = if def.node.is_some() {
        "nodefullVisual"
    } else {
        "nodelessVisual"
    };
    model.leaf(visual_tag, base);
    model.leaf("materialNames", "");
    model.open("visibilityBox");
    model.leaf("min", &v3(lo));
    model.leaf("max", &v3(hi));
    model.close();
    model.open("metaData");
    model.leaf("copyright", "Generated by shadowcull gen");
    model.close();

    let mut vis = XmlOut::new(&format!("{leaf}.visual"));
    vis.open("node");
    vis.leaf("identifier", "Scene Root");
    vis.transform(&IDENTITY);
    if let Some(m) = &def.node {
        vis.open("node");
        vis.leaf("identifier", "gen_pivot");
        vis.transform(m);
        vis.close();
    }
    vis.close();
    vis.open("renderSet");
    vis.leaf("treatAsWorldSpaceObject", "false");
    vis.leaf(
        "node",
        if def.node.is_some() {
            "gen_pivot"
        } else {
            "Scene Root"
        },
    );
    vis.open("geometry");
    vis.leaf("vertices", "vertices");
    vis.leaf("primitive", "indices");
    for (g, mat) in def.materials.iter().enumerate() {
        vis.open_value("primitiveGroup", &g.to_string());
        vis.open("material");
        vis.leaf("identifier", mat.identifier);
        vis.leaf("fx", "shaders/std_effects/lightonly.fx");
        vis.leaf("collisionFlags", "0");
        vis.leaf("materialKind", "0");
        if mat.alpha_test {
            vis.open_value("property", "alphaReference");
            vis.leaf("Int", "128");
            vis.close();
            vis.open_value("property", "alphaTestEnable");
            vis.leaf("Bool", "true");
            vis.close();
        }
        if mat.double_sided {
            vis.open_value("property", "doubleSided");
            vis.leaf("Bool", "true");
            vis.close();
        }
        vis.open_value("property", "diffuseMap");
        vis.leaf("Texture", &format!("sets/gen/maps/{}.dds", mat.identifier));
        vis.close();
        vis.open_value("property", "selfIllumination");
        vis.leaf("Float", &f6(0.0));
        vis.close();
        vis.close();
        vis.close();
    }
    vis.close();
    vis.close();
    vis.open("boundingBox");
    vis.leaf("min", &v3(lo));
    vis.leaf("max", &v3(hi));
    vis.close();

    let vertices = primitives::write_vertices(&def.mesh.positions, &def.mesh.normals);
    let indices = primitives::write_indices(&def.mesh.indices, &def.mesh.groups);
    let prims = binsection::write(&[("vertices", &vertices), ("indices", &indices)]);

    vec![
        (format!("{base}.model"), model.finish()),
        (format!("{base}.visual"), vis.finish()),
        (format!("{base}.primitives"), prims),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gen::mesh::{is_closed_and_consistent, signed_volume};

    #[test]
    fn every_catalog_solid_is_closed_and_outward() {
        for detail in [1, 2] {
            for def in catalog(detail) {
                assert_eq!(def.materials.len(), def.mesh.groups.len(), "{:?}", def.kind);
                for (g, &closed) in def.mesh.closed.iter().enumerate() {
                    let tris = def.mesh.group_triangles(g);
                    if closed {
                        is_closed_and_consistent(&tris)
                            .unwrap_or_else(|e| panic!("{:?} group {g}: {e}", def.kind));
                        assert!(signed_volume(&tris) > 0.0, "{:?} group {g}", def.kind);
                    } else {
                        // Open cards must never be single-sided: a one-sided
                        // card would be culled from half the directions.
                        assert!(def.materials[g].double_sided, "{:?} group {g}", def.kind);
                    }
                }
            }
        }
    }

    #[test]
    fn catalog_covers_the_required_features() {
        let cat = catalog(1);
        assert_eq!(cat.len(), Kind::ALL.len());
        assert!(cat.iter().any(|d| d.node.is_some()));
        assert!(cat.iter().any(|d| d.mesh.groups.len() >= 3));
        let tree = cat.iter().find(|d| d.kind == Kind::Tree).unwrap().stats();
        assert_eq!(tree.groups, 2);
        assert_eq!(tree.alpha_tested_groups, 1);
        assert_eq!(tree.double_sided_groups, 1);
        // Opaque but double-sided exists too (the banner).
        assert!(cat
            .iter()
            .flat_map(|d| &d.materials)
            .any(|m| m.double_sided && !m.alpha_test));
    }

    #[test]
    fn nodefull_node_transform_is_not_identity_and_keeps_orientation() {
        let cat = catalog(1);
        let sign = cat.iter().find(|d| d.kind == Kind::Signpost).unwrap();
        let m = sign.node.unwrap();
        assert_ne!(m, IDENTITY);
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        assert!(det > 0.0);
        let vis = String::from_utf8(files(sign)[1].1.clone()).unwrap();
        assert!(vis.contains("<node>\tgen_pivot\t</node>"));
        assert!(vis.contains("<row3>\t0.000000 2.200000 0.000000\t</row3>"));
        let model = String::from_utf8(files(sign)[0].1.clone()).unwrap();
        assert!(model.starts_with(
            "<signpost.model>\n\t<nodefullVisual>\tsets/gen/props/signpost\t</nodefullVisual>\n"
        ));
    }

    #[test]
    fn alpha_material_uses_the_real_property_layout() {
        let cat = catalog(1);
        let tree = cat.iter().find(|d| d.kind == Kind::Tree).unwrap();
        let vis = String::from_utf8(files(tree)[1].1.clone()).unwrap();
        assert!(vis.contains("<property>\talphaTestEnable\n\t\t\t\t\t\t<Bool>\ttrue\t</Bool>\n"));
        assert!(vis.contains("<property>\tdoubleSided\n\t\t\t\t\t\t<Bool>\ttrue\t</Bool>\n"));
        assert_eq!(vis.matches("<primitiveGroup>").count(), 2);
    }
}
