//! The rasterized reference against the ray-cast bake on the generated
//! `bench` world (seed 1), light by light on the same grids (both prepare
//! each light with `LightSetup`), in one run: the sun at texel sizes 0.98
//! (the world's own), 0.25 and 0.1 m, then the spot and the point light.
//! Each side is timed from the loaded scene to its masks (bottom levels or
//! reach, geometry, BVH or vertex upload, all passes); the medians of
//! `SHADOWCULL_BENCH_RUNS` runs (default 3) and their ratio are printed.
//! Needs the `raster` feature and an OpenGL 4.3 driver (Mesa's llvmpipe on a
//! machine without a GPU):
//! `cargo bench --features raster --bench reference`.

use shadowcull::bake::setup::BakeWorld;
use shadowcull::bake::{self, BakeConfig, Silent};
use shadowcull::formats::bake_settings::{LightKind, LightSettings};
use shadowcull::raster::{self, RasterOptions};
use std::time::Instant;

mod common;
use common::bench_world;

/// The sun's texel sizes (metres).
const SUN_TEXELS: [f64; 3] = [0.9765625, 0.25, 0.1];

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn timed(runs: usize, mut f: impl FnMut()) -> f64 {
    median(
        (0..runs)
            .map(|_| {
                let started = Instant::now();
                f();
                started.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// The lights measured: the sun at each of [`SUN_TEXELS`], then the other
/// lights as the world has them.
fn lights(all: &BakeConfig) -> Vec<(String, LightSettings)> {
    let mut out = Vec::new();
    for light in &all.lights {
        match &light.kind {
            LightKind::Directional { direction, .. } => {
                for texel_size in SUN_TEXELS {
                    let mut sun = light.clone();
                    sun.kind = LightKind::Directional {
                        direction: *direction,
                        texel_size,
                    };
                    out.push((format!("{} at {texel_size} m", light.name), sun));
                }
            }
            _ => out.push((light.name.clone(), light.clone())),
        }
    }
    out
}

fn main() {
    // `cargo bench` passes `--bench`; a filter argument is not supported.
    let runs: usize = std::env::var("SHADOWCULL_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3)
        .max(1);
    let (_dir, settings, scene) = bench_world();
    let all = BakeConfig::from_settings(&settings);
    println!("reference bench: medians of {runs} run(s), seconds");
    println!(
        "{:<20} {:>10} {:>10} {:>14}",
        "light", "ray cast", "raster", "raster / ray"
    );
    let mut renderer = String::new();
    for (name, light) in lights(&all) {
        let config = BakeConfig {
            lights: vec![light],
            ..all.clone()
        };
        let ray = timed(runs, || {
            bake::bake(&scene, &config, &Silent).expect("bake");
        });
        let ras = timed(runs, || {
            let world = BakeWorld::new(&scene);
            let result = raster::raster(&world, &config, &RasterOptions::default())
                .unwrap_or_else(|e| panic!("the rasterized method failed: {e}"));
            renderer = result.renderer;
        });
        println!("{name:<20} {ray:>10.2} {ras:>10.2} {:>14.1}", ras / ray);
    }
    println!("renderer: {renderer}");
}
