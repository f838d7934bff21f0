//! Procedural meshes for the synthetic world. Every solid is closed and has
//! outward front faces by the contract's rule (front = side of (v1 − v0) × (v2 − v0)),
//! because the bake's face culling and hit counting depend on it; cards are
//! the deliberate exception and are only ever given double-sided materials.

use crate::formats::primitives::PrimitiveGroup;

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalize(a: V3) -> V3 {
    let l = dot(a, a).sqrt();
    if l > 0.0 {
        [a[0] / l, a[1] / l, a[2] / l]
    } else {
        [0.0, 1.0, 0.0]
    }
}

fn f32s(a: V3) -> [f32; 3] {
    [a[0] as f32, a[1] as f32, a[2] as f32]
}

/// Geometry of one model: vertices, a triangle list and its primitive groups
/// (each group owns a contiguous run of vertices and indices).
#[derive(Debug, Clone, Default)]
pub(crate) struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
    pub groups: Vec<PrimitiveGroup>,
    /// Per group: whether it is a closed solid (cards are not).
    pub closed: Vec<bool>,
    group_start: Option<(u32, u32)>,
}

impl Mesh {
    pub(crate) fn begin_group(&mut self) {
        self.group_start = Some((self.indices.len() as u32, self.positions.len() as u32));
    }

    pub(crate) fn end_group(&mut self, closed: bool) {
        let (si, sv) = self.group_start.take().unwrap_or((0, 0));
        self.groups.push(PrimitiveGroup {
            start_index: si,
            n_primitives: (self.indices.len() as u32 - si) / 3,
            start_vertex: sv,
            n_vertices: self.positions.len() as u32 - sv,
        });
        self.closed.push(closed);
    }

    pub(crate) fn triangles(&self) -> usize {
        self.indices.len() / 3
    }

    fn vertex(&mut self, p: V3, n: V3) -> u32 {
        self.positions.push(f32s(p));
        self.normals.push(f32s(normalize(n)));
        (self.positions.len() - 1) as u32
    }

    /// A flat quad p0 p1 p2 p3, front face towards (p1 − p0) × (p2 − p0).
    fn quad(&mut self, p: [V3; 4]) {
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        let i: Vec<u32> = p.iter().map(|&q| self.vertex(q, n)).collect();
        self.indices
            .extend_from_slice(&[i[0], i[1], i[2], i[0], i[2], i[3]]);
    }

    fn tri(&mut self, p: [V3; 3]) {
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        for q in p {
            let i = self.vertex(q, n);
            self.indices.push(i);
        }
    }

    /// Axis-aligned box. Corner coordinates are picked from `min`/`max`
    /// directly, so faces sharing a corner share its exact bits (the closedness
    /// test welds by bits).
    pub(crate) fn add_box(&mut self, min: V3, max: V3) {
        // (normal axis, normal sign, u axis, u sign, v axis, v sign) with
        // u × v = normal; corners -u-v, +u-v, +u+v, -u+v.
        const FACES: [(usize, f64, usize, f64, usize, f64); 6] = [
            (0, 1.0, 1, 1.0, 2, 1.0),
            (0, -1.0, 2, 1.0, 1, 1.0),
            (1, 1.0, 2, 1.0, 0, 1.0),
            (1, -1.0, 0, 1.0, 2, 1.0),
            (2, 1.0, 0, 1.0, 1, 1.0),
            (2, -1.0, 1, 1.0, 0, 1.0),
        ];
        for (na, ns, ua, us, va, vs) in FACES {
            let corner = |cu: f64, cv: f64| {
                let mut s = [0.0; 3];
                s[na] = ns;
                s[ua] = cu * us;
                s[va] = cv * vs;
                [0, 1, 2].map(|k| if s[k] > 0.0 { max[k] } else { min[k] })
            };
            self.quad([
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            ]);
        }
    }

    /// Vertical cylinder standing on `base`, flat sides, capped.
    pub(crate) fn add_cylinder(&mut self, base: V3, radius: f64, height: f64, segments: usize) {
        let ring = |y: f64| -> Vec<V3> {
            (0..segments)
                .map(|k| {
                    let t = std::f64::consts::TAU * k as f64 / segments as f64;
                    [base[0] + radius * t.cos(), y, base[2] + radius * t.sin()]
                })
                .collect()
        };
        let bottom = ring(base[1]);
        let top = ring(base[1] + height);
        for k in 0..segments {
            let j = (k + 1) % segments;
            self.quad([bottom[k], top[k], top[j], bottom[j]]);
        }
        let ct = [base[0], base[1] + height, base[2]];
        let cb = base;
        for k in 0..segments {
            let j = (k + 1) % segments;
            self.tri([ct, top[j], top[k]]);
            self.tri([cb, bottom[k], bottom[j]]);
        }
    }

    /// UV sphere with shared, smooth vertices and single pole vertices.
    /// `wobble` (0 = round) displaces each vertex radially, for rocks.
    pub(crate) fn add_sphere(
        &mut self,
        center: V3,
        radius: f64,
        stacks: usize,
        slices: usize,
        wobble: &dyn Fn(usize, usize) -> f64,
    ) {
        let first = self.positions.len() as u32;
        let top = self.vertex(
            [center[0], center[1] + radius * wobble(0, 0), center[2]],
            [0.0, 1.0, 0.0],
        );
        for i in 1..stacks {
            let phi = std::f64::consts::PI * i as f64 / stacks as f64;
            for j in 0..slices {
                let t = std::f64::consts::TAU * j as f64 / slices as f64;
                let n = [phi.sin() * t.cos(), phi.cos(), phi.sin() * t.sin()];
                let r = radius * wobble(i, j);
                self.vertex(
                    [
                        center[0] + r * n[0],
                        center[1] + r * n[1],
                        center[2] + r * n[2],
                    ],
                    n,
                );
            }
        }
        let bottom = self.vertex(
            [center[0], center[1] - radius * wobble(stacks, 0), center[2]],
            [0.0, -1.0, 0.0],
        );
        let at = |i: usize, j: usize| first + 1 + ((i - 1) * slices + j % slices) as u32;
        for j in 0..slices {
            self.indices
                .extend_from_slice(&[top, at(1, j + 1), at(1, j)]);
            self.indices
                .extend_from_slice(&[bottom, at(stacks - 1, j), at(stacks - 1, j + 1)]);
        }
        for i in 1..stacks - 1 {
            for j in 0..slices {
                let (a, b, c, d) = (at(i + 1, j), at(i, j), at(i, j + 1), at(i + 1, j + 1));
                self.indices.extend_from_slice(&[a, b, c, a, c, d]);
            }
        }
    }

    /// Torus standing upright (its axis along z), resting on `base`.
    pub(crate) fn add_torus(&mut self, base: V3, major: f64, minor: f64, ring: usize, tube: usize) {
        let first = self.positions.len() as u32;
        let cy = base[1] + major + minor;
        for j in 0..ring {
            let t = std::f64::consts::TAU * j as f64 / ring as f64;
            for i in 0..tube {
                let p = std::f64::consts::TAU * i as f64 / tube as f64;
                // Built around the y axis, then turned by +90° about x
                // ((x, y, z) → (x, −z, y)), a rotation, so orientation is kept.
                let n = [p.cos() * t.cos(), p.sin(), p.cos() * t.sin()];
                let q = [
                    (major + minor * p.cos()) * t.cos(),
                    minor * p.sin(),
                    (major + minor * p.cos()) * t.sin(),
                ];
                self.vertex(
                    [base[0] + q[0], cy - q[2], base[2] + q[1]],
                    [n[0], -n[2], n[1]],
                );
            }
        }
        let at = |j: usize, i: usize| first + ((j % ring) * tube + i % tube) as u32;
        for j in 0..ring {
            for i in 0..tube {
                let (a, b, c, d) = (at(j, i), at(j, i + 1), at(j + 1, i + 1), at(j + 1, i));
                self.indices.extend_from_slice(&[a, b, c, a, c, d]);
            }
        }
    }

    /// Gable roof: a triangular prism along z over x0..x1, eaves at y0,
    /// ridge at y1.
    pub(crate) fn add_roof(&mut self, x0: f64, x1: f64, y0: f64, y1: f64, z0: f64, z1: f64) {
        let xm = 0.5 * (x0 + x1);
        let (l0, r0, t0) = ([x0, y0, z0], [x1, y0, z0], [xm, y1, z0]);
        let (l1, r1, t1) = ([x0, y0, z1], [x1, y0, z1], [xm, y1, z1]);
        self.tri([l1, r1, t1]);
        self.tri([l0, t0, r0]);
        self.quad([l0, l1, t1, t0]);
        self.quad([r0, t0, t1, r1]);
        self.quad([l0, r0, r1, l1]);
    }

    /// Vertical cards through the axis at `base`, evenly turned, plus one
    /// horizontal card: a tree canopy. Not closed; needs a double-sided
    /// material.
    pub(crate) fn add_cards(&mut self, base: V3, half_width: f64, y0: f64, y1: f64, count: usize) {
        for k in 0..count {
            let t = std::f64::consts::PI * k as f64 / count as f64;
            let (dx, dz) = (half_width * t.cos(), half_width * t.sin());
            self.quad([
                [base[0] - dx, base[1] + y0, base[2] - dz],
                [base[0] + dx, base[1] + y0, base[2] + dz],
                [base[0] + dx, base[1] + y1, base[2] + dz],
                [base[0] - dx, base[1] + y1, base[2] - dz],
            ]);
        }
        let ym = base[1] + 0.5 * (y0 + y1);
        let h = half_width;
        self.quad([
            [base[0] - h, ym, base[2] - h],
            [base[0] - h, ym, base[2] + h],
            [base[0] + h, ym, base[2] + h],
            [base[0] + h, ym, base[2] - h],
        ]);
    }

    /// One vertical card (a banner) in the x-y plane.
    pub(crate) fn add_panel(&mut self, half_width: f64, y0: f64, y1: f64) {
        self.quad([
            [-half_width, y0, 0.0],
            [half_width, y0, 0.0],
            [half_width, y1, 0.0],
            [-half_width, y1, 0.0],
        ]);
    }

    /// The triangles of group `g` as vertex positions.
    #[cfg(test)]
    pub(crate) fn group_triangles(&self, g: usize) -> Vec<[[f32; 3]; 3]> {
        let Some(grp) = self.groups.get(g) else {
            return Vec::new();
        };
        let s = grp.start_index as usize;
        let e = s + 3 * grp.n_primitives as usize;
        self.indices[s..e]
            .chunks_exact(3)
            .map(|t| [0, 1, 2].map(|k| self.positions[t[k] as usize]))
            .collect()
    }

    /// Bounds of all vertices after the affine map `m` (rows 0–2 basis,
    /// row 3 translation, row-vector convention).
    pub(crate) fn bounds(&self, m: &[[f64; 3]; 4]) -> (V3, V3) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            let q = transform_point(m, [p[0] as f64, p[1] as f64, p[2] as f64]);
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        (lo, hi)
    }
}

pub(crate) fn transform_point(m: &[[f64; 3]; 4], p: V3) -> V3 {
    [0, 1, 2].map(|k| p[0] * m[0][k] + p[1] * m[1][k] + p[2] * m[2][k] + m[3][k])
}

pub(crate) const IDENTITY: [[f64; 3]; 4] = [
    [1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, 0.0],
];

/// Signed volume of a triangle soup (positive for a closed mesh with
/// outward front faces).
#[cfg(test)]
pub(crate) fn signed_volume(tris: &[[[f32; 3]; 3]]) -> f64 {
    tris.iter()
        .map(|t| {
            let [a, b, c] = t.map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]);
            dot(a, cross(b, c)) / 6.0
        })
        .sum()
}

/// Whether every edge (positions welded by exact bits) is used by exactly two
/// triangles, once in each direction: closed, consistently oriented.
#[cfg(test)]
pub(crate) fn is_closed_and_consistent(tris: &[[[f32; 3]; 3]]) -> Result<(), String> {
    use std::collections::HashMap;
    let key = |p: [f32; 3]| p.map(f32::to_bits);
    let mut edges: HashMap<([u32; 3], [u32; 3]), u32> = HashMap::new();
    for t in tris {
        for k in 0..3 {
            let e = (key(t[k]), key(t[(k + 1) % 3]));
            if e.0 == e.1 {
                return Err(format!("degenerate edge at {:?}", t[k]));
            }
            *edges.entry(e).or_insert(0) += 1;
        }
    }
    for (&(a, b), &n) in &edges {
        if n != 1 {
            return Err(format!("directed edge {a:?}->{b:?} used {n} times"));
        }
        if edges.get(&(b, a)) != Some(&1) {
            return Err(format!("edge {a:?}->{b:?} has no opposite twin"));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_solid(m: &Mesh) {
        for g in 0..m.groups.len() {
            let tris = m.group_triangles(g);
            assert!(!tris.is_empty());
            is_closed_and_consistent(&tris).unwrap();
            assert!(signed_volume(&tris) > 0.0, "group {g} inward");
        }
    }

    #[test]
    fn box_is_closed_outward_with_exact_volume() {
        let mut m = Mesh::default();
        m.begin_group();
        m.add_box([-1.0, 0.0, -2.0], [1.0, 3.0, 2.0]);
        m.end_group(true);
        check_solid(&m);
        assert_eq!(m.triangles(), 12);
        let v = signed_volume(&m.group_triangles(0));
        assert!((v - 2.0 * 3.0 * 4.0).abs() < 1e-9, "{v}");
    }

    #[test]
    fn stored_normals_agree_with_geometric_normals() {
        let mut m = Mesh::default();
        m.begin_group();
        m.add_box([0.0; 3], [1.0; 3]);
        m.add_sphere([5.0, 0.0, 0.0], 1.0, 6, 8, &|_, _| 1.0);
        m.add_torus([10.0, 0.0, 0.0], 1.0, 0.3, 12, 8);
        m.add_cylinder([20.0, 0.0, 0.0], 0.5, 2.0, 10);
        m.add_roof(30.0, 32.0, 0.0, 1.0, 0.0, 3.0);
        m.end_group(true);
        for t in m.indices.chunks_exact(3) {
            let p = [t[0], t[1], t[2]].map(|i| m.positions[i as usize].map(f64::from));
            let g = cross(sub(p[1], p[0]), sub(p[2], p[0]));
            for &i in t {
                let n = m.normals[i as usize].map(f64::from);
                assert!(dot(g, n) > 0.0, "normal disagrees at {p:?}");
            }
        }
    }

    #[test]
    fn round_solids_are_closed_outward() {
        let mut m = Mesh::default();
        m.begin_group();
        m.add_sphere([0.0; 3], 2.0, 8, 12, &|i, j| {
            1.0 + 0.1 * ((i * 7 + j * 3) % 5) as f64
        });
        m.end_group(true);
        m.begin_group();
        m.add_torus([0.0; 3], 1.2, 0.3, 16, 8);
        m.end_group(true);
        m.begin_group();
        m.add_cylinder([0.0; 3], 0.4, 3.0, 12);
        m.end_group(true);
        m.begin_group();
        m.add_roof(-3.0, 3.0, 4.0, 6.0, -4.0, 4.0);
        m.end_group(true);
        check_solid(&m);
        // Torus volume 2π²Rr² within polygonisation error.
        let v = signed_volume(&m.group_triangles(1));
        let exact = 2.0 * std::f64::consts::PI.powi(2) * 1.2 * 0.09;
        assert!(v > 0.8 * exact && v < exact, "{v} vs {exact}");
        // Prism: base 6 × height 2 / 2 × length 8.
        let v = signed_volume(&m.group_triangles(3));
        assert!((v - 48.0).abs() < 1e-4, "{v}");
    }

    #[test]
    fn open_cards_are_detected_as_open() {
        let mut m = Mesh::default();
        m.begin_group();
        m.add_cards([0.0; 3], 1.0, 1.0, 3.0, 3);
        m.end_group(false);
        assert!(is_closed_and_consistent(&m.group_triangles(0)).is_err());
        assert_eq!(m.triangles(), 8);
    }

    #[test]
    fn flipped_solid_is_rejected_by_volume() {
        let mut m = Mesh::default();
        m.begin_group();
        m.add_box([0.0; 3], [1.0; 3]);
        m.end_group(true);
        let flipped: Vec<_> = m
            .group_triangles(0)
            .into_iter()
            .map(|[a, b, c]| [a, c, b])
            .collect();
        assert!(signed_volume(&flipped) < 0.0);
    }
}
