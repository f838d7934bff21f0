//! Ray casting cost of the per-light BVH and multi-hit traversal: BVH build
//! throughput over ~1M triangles, and rays/s of the multi-hit traversal
//! against closest-hit with the same watertight test and obvhs's own
//! closest-hit (its node and Möller–Trumbore triangle tests), on the same rays.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use glam::{vec3, Vec3};
use shadowcull::rng::Rng;
use shadowcull::trace::{Bvh, TraceRay, TraceTriangle};

const TRIANGLES: usize = 1 << 20;
const RAYS: usize = 20_000;

fn point(rng: &mut Rng, s: f64) -> Vec3 {
    vec3(
        rng.range(-s, s) as f32,
        rng.range(-s, s) as f32,
        rng.range(-s, s) as f32,
    )
}

/// Random triangles of edge ~5 in a 1000 m cube: a ray across it crosses a
/// handful of them.
fn soup(seed: u64) -> Vec<TraceTriangle> {
    let mut rng = Rng::new(seed);
    (0..TRIANGLES)
        .map(|i| {
            let c = point(&mut rng, 500.0);
            TraceTriangle {
                vertices: [
                    c + point(&mut rng, 3.0),
                    c + point(&mut rng, 3.0),
                    c + point(&mut rng, 3.0),
                ],
                caster: i as u32 / 64,
            }
        })
        .collect()
}

/// A 724×724-cell rolling height field (~1M triangles, 1 m cells), like
/// terrain under a directional light.
fn terrain() -> Vec<TraceTriangle> {
    let n = 724;
    let h = |x: usize, z: usize| ((x as f32 * 0.05).sin() + (z as f32 * 0.07).cos()) * 10.0;
    let p = |x: usize, z: usize| vec3(x as f32 - 362.0, h(x, z), z as f32 - 362.0);
    let mut tris = Vec::with_capacity(2 * n * n);
    for x in 0..n {
        for z in 0..n {
            let caster = ((x / 64) * 16 + z / 64) as u32;
            let (a, b, c, d) = (p(x, z), p(x + 1, z), p(x + 1, z + 1), p(x, z + 1));
            tris.push(TraceTriangle {
                vertices: [a, c, b],
                caster,
            });
            tris.push(TraceTriangle {
                vertices: [a, d, c],
                caster,
            });
        }
    }
    tris
}

fn soup_rays(seed: u64) -> Vec<TraceRay> {
    let mut rng = Rng::new(seed);
    (0..RAYS)
        .map(|_| {
            let target = point(&mut rng, 500.0);
            let origin = point(&mut rng, 500.0) * 2.0;
            TraceRay {
                origin,
                direction: (target - origin).normalize(),
                t_min: 0.0,
                t_max: f32::INFINITY,
            }
        })
        .collect()
}

/// Parallel rays from above, like one directional light's texels.
fn light_rays(seed: u64) -> Vec<TraceRay> {
    let mut rng = Rng::new(seed);
    let direction = vec3(0.3, -1.0, 0.2).normalize();
    (0..RAYS)
        .map(|_| {
            let ground = vec3(
                rng.range(-300.0, 300.0) as f32,
                0.0,
                rng.range(-300.0, 300.0) as f32,
            );
            TraceRay {
                origin: ground - direction * 100.0,
                direction,
                t_min: 0.0,
                t_max: f32::INFINITY,
            }
        })
        .collect()
}

fn build(c: &mut Criterion) {
    let tris = soup(1);
    let mut group = c.benchmark_group("trace_build");
    group.sample_size(10);
    group.throughput(Throughput::Elements(tris.len() as u64));
    group.bench_function("soup_1M", |b| b.iter(|| Bvh::build(&tris)));
    group.finish();
}

fn rays(c: &mut Criterion) {
    for (scene, tris, rays) in [
        ("soup", soup(2), soup_rays(3)),
        ("terrain", terrain(), light_rays(4)),
    ] {
        let bvh = Bvh::build(&tris);
        let mut hits = 0usize;
        for ray in &rays {
            bvh.for_each_hit(ray, |_| {
                hits += 1;
                f32::INFINITY
            });
        }
        eprintln!(
            "{scene}: {} triangles, {} rays, {:.2} hits per ray",
            bvh.triangle_count(),
            rays.len(),
            hits as f64 / rays.len() as f64
        );
        let mut group = c.benchmark_group(format!("trace_rays_{scene}"));
        group.sample_size(10);
        group.throughput(Throughput::Elements(rays.len() as u64));
        group.bench_function(BenchmarkId::new("for_each_hit_all", scene), |b| {
            let mut all = Vec::new();
            b.iter(|| {
                all.clear();
                for ray in &rays {
                    bvh.for_each_hit(ray, |h| {
                        all.push(h);
                        f32::INFINITY
                    });
                }
                all.len()
            })
        });
        group.bench_function(BenchmarkId::new("closest_hit", scene), |b| {
            b.iter(|| rays.iter().filter_map(|r| bvh.closest_hit(r)).count())
        });
        group.bench_function(BenchmarkId::new("closest_hit_obvhs", scene), |b| {
            b.iter(|| rays.iter().filter_map(|r| bvh.closest_hit_obvhs(r)).count())
        });
        group.finish();
    }
}

criterion_group!(benches, build, rays);
criterion_main!(benches);
