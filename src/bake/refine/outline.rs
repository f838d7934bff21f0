//! The outline of a caster's footprint: the edges of the union of its
//! hittable triangles, those exactly one of them uses. Terrain blocks and
//! perspective lights probe the cells inside it and trace the small cells
//! it crosses, so a footprint as large as the world costs rays along its
//! edges, not over its area.

use crate::bake::config::BakeConfig;
use crate::formats::bake_settings::FaceCulling;
use crate::trace::TraceTriangle;
use glam::DVec3;

/// Whether rays of the light can hit triangle `t` under the face-culling
/// rule: a directional light's rays share one direction, so a culled face
/// is culled for all of them; a perspective light's may see either side.
pub(super) fn hittable(
    t: &TraceTriangle,
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> bool {
    let Some(direction) = direction else {
        return true;
    };
    let [a, b, c] = t.vertices.map(|v| v.as_dvec3());
    let back = (b - a).cross(c - a).dot(direction) > 0.0;
    double_sided
        || match config.face_culling {
            FaceCulling::Back => !back,
            FaceCulling::Front => back,
            FaceCulling::None => true,
        }
}

/// The edges (light-relative) of the union of the caster's hittable
/// triangles: edges that exactly one hittable triangle uses.
pub(super) fn outline_edges(
    run: &[TraceTriangle],
    direction: Option<DVec3>,
    double_sided: bool,
    config: &BakeConfig,
) -> Vec<(DVec3, DVec3)> {
    let bits = |v: glam::Vec3| v.to_array().map(f32::to_bits);
    // Every edge of every hittable triangle, keyed by its vertices' bits
    // (ordered: the six words packed in order into three), its uses
    // counted in an open-addressing table (a terrain block's many shared
    // edges are counted faster so than by sorting the keys): an edge used
    // once is on the outline. Edges are kept in the order first met (the
    // triangles'), so fixed: the work is the same run to run.
    type Key = (u64, u64, u64);
    let pack = |[a, b, c]: [u32; 3], [d, e, f]: [u32; 3]| -> Key {
        let word = |hi: u32, lo: u32| (u64::from(hi) << 32) | u64::from(lo);
        (word(a, b), word(c, d), word(e, f))
    };
    let slot_bits = (6 * run.len()).max(16).next_power_of_two().trailing_zeros();
    let slot_of = |(x, y, z): Key| {
        let mix = |h: u64, word: u64| {
            let h = (h ^ word).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            h ^ (h >> 29)
        };
        (mix(mix(mix(0, x), y), z) >> (64 - slot_bits)) as usize
    };
    let mut slots: Vec<u32> = vec![u32::MAX; 1 << slot_bits];
    let mut edges: Vec<(Key, u32, (glam::Vec3, glam::Vec3))> = Vec::new();
    for t in run
        .iter()
        .filter(|t| hittable(t, direction, double_sided, config))
    {
        for i in 0..3 {
            let (a, b) = (t.vertices[i], t.vertices[(i + 1) % 3]);
            let (ka, kb) = (bits(a), bits(b));
            let key = if ka <= kb { pack(ka, kb) } else { pack(kb, ka) };
            let mut at = slot_of(key);
            loop {
                match slots[at] {
                    u32::MAX => {
                        slots[at] = edges.len() as u32;
                        edges.push((key, 1, (a, b)));
                        break;
                    }
                    k if edges[k as usize].0 == key => {
                        edges[k as usize].1 += 1;
                        break;
                    }
                    _ => at = (at + 1) & (slots.len() - 1),
                }
            }
        }
    }
    edges
        .into_iter()
        .filter(|&(_, uses, _)| uses == 1)
        .map(|(_, _, (a, b))| (a.as_dvec3(), b.as_dvec3()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// `outline_edges` finds the edges exactly one hittable triangle uses,
    /// each once, as counting every edge against every other does: over
    /// seeded random height grids (shared vertices, as a terrain block's)
    /// with some triangles turned to face away from a sun straight down
    /// (not hittable, so holes with edges of their own), and loose
    /// triangles.
    #[test]
    fn the_outline_is_the_edges_one_hittable_triangle_uses() {
        use glam::Vec3;
        let config = BakeConfig::default();
        let down = Some(DVec3::new(0.0, -1.0, 0.0));
        let mut rng = Rng::new(41);
        for round in 0..60 {
            let n = 1 + rng.below(9);
            let height: Vec<f32> = (0..(n + 1) * (n + 1))
                .map(|_| rng.range(0.0, 3.0) as f32)
                .collect();
            let at = |i: usize, j: usize| Vec3::new(i as f32, height[j * (n + 1) + i], j as f32);
            let mut run = Vec::new();
            for j in 0..n {
                for i in 0..n {
                    let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                    for mut vertices in [[a, c, b], [a, d, c]] {
                        if rng.chance(0.2) {
                            vertices.swap(1, 2);
                        }
                        run.push(TraceTriangle {
                            vertices,
                            caster: 0,
                        });
                    }
                }
            }
            for _ in 0..round % 4 {
                let mut v = || {
                    Vec3::new(
                        rng.range(-5.0, 5.0) as f32,
                        0.0,
                        rng.range(-5.0, 5.0) as f32,
                    )
                };
                let vertices = [v(), v(), v()];
                run.push(TraceTriangle {
                    vertices,
                    caster: 0,
                });
            }
            let key = |a: Vec3, b: Vec3| {
                let (a, b) = (
                    a.to_array().map(f32::to_bits),
                    b.to_array().map(f32::to_bits),
                );
                if a <= b {
                    (a, b)
                } else {
                    (b, a)
                }
            };
            let kept: Vec<&TraceTriangle> = run
                .iter()
                .filter(|t| hittable(t, down, false, &config))
                .collect();
            let edges: Vec<(Vec3, Vec3)> = kept
                .iter()
                .flat_map(|t| (0..3).map(|i| (t.vertices[i], t.vertices[(i + 1) % 3])))
                .collect();
            let mut expected: Vec<_> = edges
                .iter()
                .filter(|&&(a, b)| {
                    edges
                        .iter()
                        .filter(|&&(c, d)| key(a, b) == key(c, d))
                        .count()
                        == 1
                })
                .map(|&(a, b)| key(a, b))
                .collect();
            let mut found: Vec<_> = outline_edges(&run, down, false, &config)
                .into_iter()
                .map(|(a, b)| key(a.as_vec3(), b.as_vec3()))
                .collect();
            expected.sort_unstable();
            found.sort_unstable();
            assert_eq!(found, expected, "round {round}");
            assert!(!found.is_empty() || kept.is_empty(), "round {round}");
        }
    }
}
