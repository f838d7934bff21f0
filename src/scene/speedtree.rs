//! The geometry of a parametric speedtree proxy (docs/contract.md §3): a
//! closed opaque trunk and a closed alpha-tested crown, outward-wound by
//! the contract's winding rule (§2), in tree space. One [`Model`] per
//! distinct parameter set, however many trees use it: memory grows with
//! distinct geometry, not with placements.

use super::{Group, Model};
use crate::formats::bake_settings::{CrownShape, ParametricTree};
use glam::Vec3;
use std::f64::consts::TAU;

/// Sides of the trunk's prism and of every ring of the crown.
pub const SEGMENTS: u32 = 8;
/// Bands of latitude of an ellipsoid crown.
pub const ELLIPSOID_BANDS: u32 = 6;

/// The proxy model of `tree`: one render set, one geometry, two groups
/// (group 0 the trunk, opaque; group 1 the crown, alpha-tested), named
/// [`ParametricTree::name`].
pub fn parametric_model(tree: &ParametricTree) -> Model {
    let mut mesh = Mesh::default();
    mesh.prism(tree.trunk_radius, 0.0, tree.trunk_height);
    let trunk = mesh.triangles.len();
    match tree.crown_shape {
        CrownShape::Ellipsoid => mesh.ellipsoid(
            tree.crown_radius,
            tree.crown_base,
            tree.crown_base + tree.crown_height,
        ),
        CrownShape::Cone => mesh.cone(
            tree.crown_radius,
            tree.crown_base,
            tree.crown_base + tree.crown_height,
        ),
    }
    let group = |primitive_group: usize, triangles, alpha_tested| Group {
        render_set: 0,
        geometry: 0,
        primitive_group,
        triangles,
        alpha_tested,
        double_sided: false,
    };
    Model {
        resource: tree.name(),
        file: Default::default(),
        groups: vec![
            group(0, 0..trunk, false),
            group(1, trunk..mesh.triangles.len(), true),
        ],
        positions: mesh.positions,
        triangles: mesh.triangles,
        layout: vec![vec![2]],
        parametric: true,
    }
}

/// Indexed triangles: closed solids share their vertices, so every edge
/// is one segment for the watertight ray test.
#[derive(Default)]
struct Mesh {
    positions: Vec<Vec3>,
    triangles: Vec<[u32; 3]>,
}

impl Mesh {
    fn vertex(&mut self, x: f64, y: f64, z: f64) -> u32 {
        self.positions.push(Vec3::new(x as f32, y as f32, z as f32));
        self.positions.len() as u32 - 1
    }

    /// A ring of [`SEGMENTS`] vertices of radius `radius` at height `y`;
    /// returns its first index.
    fn ring(&mut self, radius: f64, y: f64) -> u32 {
        let first = self.positions.len() as u32;
        for i in 0..SEGMENTS {
            let angle = TAU * f64::from(i) / f64::from(SEGMENTS);
            self.vertex(radius * angle.cos(), y, radius * angle.sin());
        }
        first
    }

    /// The band between two rings, `lower` below `upper`, facing out.
    fn band(&mut self, lower: u32, upper: u32) {
        for i in 0..SEGMENTS {
            let next = (i + 1) % SEGMENTS;
            let (a, b) = (lower + i, lower + next);
            let (c, d) = (upper + i, upper + next);
            self.triangles.push([a, c, b]);
            self.triangles.push([b, c, d]);
        }
    }

    /// A fan closing `ring` at `apex`: facing down when `apex` is below
    /// the rest of the solid, up when above.
    fn fan(&mut self, ring: u32, apex: u32, facing_up: bool) {
        for i in 0..SEGMENTS {
            let (a, b) = (ring + i, ring + (i + 1) % SEGMENTS);
            self.triangles.push(if facing_up {
                [apex, b, a]
            } else {
                [apex, a, b]
            });
        }
    }

    /// A closed prism from `y0` to `y1`.
    fn prism(&mut self, radius: f64, y0: f64, y1: f64) {
        let bottom_centre = self.vertex(0.0, y0, 0.0);
        let top_centre = self.vertex(0.0, y1, 0.0);
        let bottom = self.ring(radius, y0);
        let top = self.ring(radius, y1);
        self.band(bottom, top);
        self.fan(bottom, bottom_centre, false);
        self.fan(top, top_centre, true);
    }

    /// A closed cone: a disc at `y0`, its apex at `y1`.
    fn cone(&mut self, radius: f64, y0: f64, y1: f64) {
        let centre = self.vertex(0.0, y0, 0.0);
        let apex = self.vertex(0.0, y1, 0.0);
        let base = self.ring(radius, y0);
        self.fan(base, centre, false);
        self.fan(base, apex, true);
    }

    /// A closed ellipsoid filling the box of `radius` around the y axis
    /// from `y0` to `y1`: poles joined by [`ELLIPSOID_BANDS`] bands.
    fn ellipsoid(&mut self, radius: f64, y0: f64, y1: f64) {
        let (centre, half) = (0.5 * (y0 + y1), 0.5 * (y1 - y0));
        let south = self.vertex(0.0, y0, 0.0);
        let north = self.vertex(0.0, y1, 0.0);
        let rings: Vec<u32> = (1..ELLIPSOID_BANDS)
            .map(|k| {
                let polar = std::f64::consts::PI * f64::from(k) / f64::from(ELLIPSOID_BANDS);
                self.ring(radius * polar.sin(), centre - half * polar.cos())
            })
            .collect();
        self.fan(rings[0], south, false);
        for pair in rings.windows(2) {
            self.band(pair[0], pair[1]);
        }
        self.fan(rings[rings.len() - 1], north, true);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn tree(shape: CrownShape) -> ParametricTree {
        ParametricTree {
            trunk_radius: 0.3,
            trunk_height: 6.0,
            crown_radius: 3.0,
            crown_height: 5.0,
            crown_base: 2.0,
            crown_shape: shape,
        }
    }

    /// Every edge of a group is used once in each direction (closed and
    /// consistently wound), and the volume it encloses is positive (wound
    /// outward by docs/contract.md §2's rule): returns that volume.
    fn closed_outward_volume(model: &Model, group: usize) -> f64 {
        let triangles = &model.triangles[model.groups[group].triangles.clone()];
        let mut edges: BTreeMap<(u32, u32), i32> = BTreeMap::new();
        let mut volume = 0.0;
        for t in triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
            let [a, b, c] = t.map(|i| model.positions[i as usize].as_dvec3());
            volume += a.dot(b.cross(c)) / 6.0;
        }
        for (&(a, b), &n) in &edges {
            assert_eq!(n, 1, "edge {a}-{b} used {n} times one way");
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
        }
        volume
    }

    #[test]
    fn trunk_and_crown_are_closed_outward_and_near_their_solids() {
        let model = parametric_model(&tree(CrownShape::Ellipsoid));
        assert_eq!(model.layout, vec![vec![2]]);
        assert!(!model.groups[0].alpha_tested && model.groups[1].alpha_tested);
        assert!(model.parametric);
        let prism = 0.5 * 8.0 * 0.3f64.powi(2) * (TAU / 8.0).sin() * 6.0;
        let trunk = closed_outward_volume(&model, 0);
        assert!((trunk - prism).abs() < 1e-4, "{trunk} vs {prism}");
        let crown = closed_outward_volume(&model, 1);
        let solid = 4.0 / 3.0 * std::f64::consts::PI * 3.0 * 3.0 * 2.5;
        assert!(crown > 0.6 * solid && crown < solid, "{crown} vs {solid}");
        let (min, max) = model.bounds().unwrap();
        assert_eq!((min.y, max.y), (0.0, 7.0));
        assert!(
            (max.x - 3.0).abs() < 1e-6,
            "the equator ring reaches the radius"
        );

        let cone = parametric_model(&tree(CrownShape::Cone));
        let volume = closed_outward_volume(&cone, 1);
        let octagonal = 0.5 * 8.0 * 9.0 * (TAU / 8.0).sin() * 5.0 / 3.0;
        assert!((volume - octagonal).abs() < 1e-3, "{volume} vs {octagonal}");
        assert_eq!(cone.bounds().unwrap().1.y, 7.0);
        assert_ne!(cone.resource, model.resource);
    }
}
