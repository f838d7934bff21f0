//! (feature `raster`) `xcheck --savings`: what culling saves a light's
//! shadow pass, measured rather than counted. The bake's savings table
//! counts draw calls and triangles; the game cares about time, which
//! depends on the driver, fill and overdraw. Per light this renders the
//! shadow pass as the game does (depth only, every caster group and
//! terrain block in the light's reach a draw call, face culling as the
//! settings say, double-sided groups drawn both ways) on the bake's own
//! grid (`LightSetup`: faces, tiles of at most [`super::DEFAULT_MAX_TILE`]
//! pixels), once with every caster and once with only those the bake's
//! masks keep, from one vertex buffer, several times each, alternating.
//! The medians of the GPU time (a `GL_TIME_ELAPSED` query around the pass)
//! and of the CPU time (submission to `glFinish`) are reported.
//!
//! Receiver-only groups are never drawn (they are not in a shadow map);
//! speedtrees without a proxy have no geometry. A point light's six faces
//! each draw every caster in the light's reach: the GPU clips what a face
//! does not see, as a game without per-face culling would.

use super::context::GlContext;
use super::{directional_far, face_view, link, tile_matrix, vertex_runs, Run, VERTEX};
use crate::bake::casters::CasterTable;
use crate::bake::setup::{BakeWorld, LightSetup};
use crate::bake::BakeConfig;
use crate::formats::bake_settings::FaceCulling;
use glow::HasContext;
use serde::Serialize;
use std::time::Instant;

/// Repetitions of each pass when the caller gives none.
pub const DEFAULT_REPETITIONS: u32 = 7;

/// A depth-only pass writes no colour: its fragment shader does nothing.
const DEPTH_ONLY: &str = "void main() {}\n";

/// How to measure.
#[derive(Debug, Clone, Copy)]
pub struct SavingsOptions {
    /// Timed renders of each pass (after one untimed warm-up of each).
    pub repetitions: u32,
    /// Largest tile side (pixels), capped by the driver's limit.
    pub max_tile: u32,
}

impl Default for SavingsOptions {
    fn default() -> Self {
        SavingsOptions {
            repetitions: DEFAULT_REPETITIONS,
            max_tile: super::DEFAULT_MAX_TILE,
        }
    }
}

/// One shadow pass: what it draws and how long it took.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PassTiming {
    /// Draw calls per tile: caster groups and terrain blocks drawn.
    pub draw_calls: u64,
    /// Triangles per tile.
    pub triangles: u64,
    /// Median GPU time of the whole pass (every tile), seconds.
    pub gpu_seconds: f64,
    /// Median CPU time from the first draw call to `glFinish`, seconds.
    pub cpu_seconds: f64,
    /// Every repetition's GPU time, in the order run.
    pub gpu_samples: Vec<f64>,
    pub cpu_samples: Vec<f64>,
}

/// One light's two passes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LightSavings {
    pub light: usize,
    pub name: String,
    /// Tiles a pass draws (faces × tiles of each face).
    pub tiles: u64,
    /// Every caster in reach.
    pub all: PassTiming,
    /// Only the casters the bake keeps.
    pub kept: PassTiming,
    /// `kept / all` of the median GPU times (1: no gain; `None` when the
    /// all-caster pass took no measurable time).
    pub gpu_ratio: Option<f64>,
    /// The same for the CPU times.
    pub cpu_ratio: Option<f64>,
}

/// `xcheck --savings` for every light.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SavingsReport {
    pub renderer: String,
    pub repetitions: u32,
    pub lights: Vec<LightSavings>,
    /// How to read the times on this renderer.
    pub notes: Vec<String>,
}

/// Mesa's software rasterizer: the work runs on CPU threads, and its timer
/// queries time only part of it.
const SOFTWARE_NOTE: &str = "llvmpipe renders on CPU threads: its CPU time (first draw to \
glFinish) is the cost of the pass; its GL_TIME_ELAPSED covers only part of the work and varies \
widely from run to run, so the GPU columns are for hardware renderers";

/// Measures every light of `config` on `world`, keeping for each light
/// the casters whose bit (`config.bit`) is set in `masks` (per caster id,
/// as `BakeResult::masks`).
pub fn measure(
    world: &BakeWorld,
    config: &BakeConfig,
    masks: &[u32],
    options: &SavingsOptions,
) -> Result<SavingsReport, String> {
    let ctx = GlContext::new()?;
    let gl = &ctx.gl;
    // SAFETY: every GL call runs on the thread where `ctx` is current, with
    // objects created in it and buffers sized from Rust slices.
    unsafe {
        let program = link(gl, VERTEX, DEPTH_ONLY)?;
        let target = DepthTarget::new(gl, options.max_tile)?;
        let query = gl.create_query()?;
        gl.use_program(Some(program));
        gl.enable(glow::DEPTH_TEST);
        gl.depth_func(glow::LESS);
        gl.depth_mask(true);
        gl.color_mask(false, false, false, false);
        gl.disable(glow::MULTISAMPLE);
        // As in the reference: CCW in the light's window is a back face.
        gl.front_face(glow::CW);
        gl.cull_face(match config.face_culling {
            FaceCulling::Front => glow::FRONT,
            _ => glow::BACK,
        });
        let mut lights = Vec::new();
        for (index, settings) in config.lights.iter().enumerate() {
            let bit = config.bit(index);
            let kept = |caster: u32| {
                masks
                    .get(caster as usize)
                    .is_some_and(|m| m >> bit & 1 != 0)
            };
            let pass = ShadowPass {
                gl,
                program,
                target: &target,
                query,
                casters: &world.casters,
                culling: config.face_culling != FaceCulling::None,
                repetitions: options.repetitions.max(1),
            };
            let measured = match LightSetup::new(world, config, index) {
                Ok(setup) => pass.light(world, &setup, &kept)?,
                Err(e) if e.is_nothing_to_trace() => Measured::default(),
                Err(e) => return Err(e.to_string()),
            };
            if gl.get_error() != glow::NO_ERROR {
                return Err(format!("OpenGL error while drawing light {index}"));
            }
            lights.push(LightSavings {
                light: index,
                name: settings.name.clone(),
                tiles: measured.tiles,
                gpu_ratio: ratio(measured.kept.gpu_seconds, measured.all.gpu_seconds),
                cpu_ratio: ratio(measured.kept.cpu_seconds, measured.all.cpu_seconds),
                all: measured.all,
                kept: measured.kept,
            });
        }
        gl.delete_query(query);
        target.delete(gl);
        gl.delete_program(program);
        let software = ctx.renderer.contains("llvmpipe") || ctx.renderer.contains("softpipe");
        Ok(SavingsReport {
            renderer: ctx.renderer.clone(),
            repetitions: options.repetitions.max(1),
            lights,
            notes: software
                .then(|| SOFTWARE_NOTE.to_string())
                .into_iter()
                .collect(),
        })
    }
}

fn ratio(part: f64, whole: f64) -> Option<f64> {
    (whole > 0.0).then(|| part / whole)
}

/// The median of `samples` (the mean of the middle two for an even count).
pub fn median(samples: &[f64]) -> f64 {
    let mut sorted = samples.to_vec();
    sorted.sort_by(f64::total_cmp);
    match sorted.len() {
        0 => 0.0,
        n if n % 2 == 1 => sorted[n / 2],
        n => (sorted[n / 2 - 1] + sorted[n / 2]) / 2.0,
    }
}

/// A depth-only framebuffer one tile large.
struct DepthTarget {
    fbo: glow::Framebuffer,
    depth: glow::Renderbuffer,
    vao: glow::VertexArray,
    vbo: glow::Buffer,
    tile: u32,
}

impl DepthTarget {
    unsafe fn new(gl: &glow::Context, max_tile: u32) -> Result<DepthTarget, String> {
        let limit = gl.get_parameter_i32(glow::MAX_RENDERBUFFER_SIZE).max(1) as u32;
        let tile = max_tile.max(1).min(limit);
        let fbo = gl.create_framebuffer()?;
        gl.bind_framebuffer(glow::FRAMEBUFFER, Some(fbo));
        let depth = gl.create_renderbuffer()?;
        gl.bind_renderbuffer(glow::RENDERBUFFER, Some(depth));
        // A shadow map's usual format.
        gl.renderbuffer_storage(
            glow::RENDERBUFFER,
            glow::DEPTH_COMPONENT32F,
            tile as i32,
            tile as i32,
        );
        gl.framebuffer_renderbuffer(
            glow::FRAMEBUFFER,
            glow::DEPTH_ATTACHMENT,
            glow::RENDERBUFFER,
            Some(depth),
        );
        gl.draw_buffers(&[glow::NONE]);
        gl.read_buffer(glow::NONE);
        if gl.check_framebuffer_status(glow::FRAMEBUFFER) != glow::FRAMEBUFFER_COMPLETE {
            return Err("the depth-only framebuffer is not complete".into());
        }
        let vao = gl.create_vertex_array()?;
        gl.bind_vertex_array(Some(vao));
        let vbo = gl.create_buffer()?;
        gl.bind_buffer(glow::ARRAY_BUFFER, Some(vbo));
        gl.enable_vertex_attrib_array(0);
        gl.vertex_attrib_pointer_f32(0, 3, glow::FLOAT, false, 12, 0);
        Ok(DepthTarget {
            fbo,
            depth,
            vao,
            vbo,
            tile,
        })
    }

    unsafe fn delete(self, gl: &glow::Context) {
        gl.delete_buffer(self.vbo);
        gl.delete_vertex_array(self.vao);
        gl.delete_renderbuffer(self.depth);
        gl.delete_framebuffer(self.fbo);
    }
}

/// Both passes of one light.
#[derive(Default)]
struct Measured {
    tiles: u64,
    all: PassTiming,
    kept: PassTiming,
}

/// One tile of a face: its matrix and its size.
struct Tile {
    clip_from_rel: [f32; 16],
    width: i32,
    height: i32,
}

/// What draws a light's shadow passes.
struct ShadowPass<'a> {
    gl: &'a glow::Context,
    program: glow::Program,
    target: &'a DepthTarget,
    query: glow::Query,
    casters: &'a CasterTable,
    culling: bool,
    repetitions: u32,
}

impl ShadowPass<'_> {
    unsafe fn light(
        &self,
        world: &BakeWorld,
        setup: &LightSetup,
        kept: &dyn Fn(u32) -> bool,
    ) -> Result<Measured, String> {
        let gl = self.gl;
        let geo = setup.reach_geometry(world);
        let (vertices, runs) = vertex_runs(&geo.triangles);
        gl.bind_buffer(glow::ARRAY_BUFFER, Some(self.target.vbo));
        gl.buffer_data_u8_slice(
            glow::ARRAY_BUFFER,
            super::bytes_of(&vertices),
            glow::STATIC_DRAW,
        );
        let casting: Vec<&Run> = runs
            .iter()
            .filter(|r| !self.casters.casters[r.caster as usize].receiver_only)
            .collect();
        let kept_runs: Vec<&Run> = casting.iter().copied().filter(|r| kept(r.caster)).collect();
        let tiles = self.tiles(setup, &geo.triangles);
        // One untimed warm-up of each, then the two alternate so that a
        // slow stretch of a shared machine falls on both.
        self.draw(&tiles, &casting)?;
        self.draw(&tiles, &kept_runs)?;
        let (mut all, mut only_kept) = (pass_of(&casting), pass_of(&kept_runs));
        for _ in 0..self.repetitions {
            for (pass, runs) in [(&mut all, &casting), (&mut only_kept, &kept_runs)] {
                let (gpu, cpu) = self.draw(&tiles, runs)?;
                pass.gpu_samples.push(gpu);
                pass.cpu_samples.push(cpu);
            }
        }
        for pass in [&mut all, &mut only_kept] {
            pass.gpu_seconds = median(&pass.gpu_samples);
            pass.cpu_seconds = median(&pass.cpu_samples);
        }
        Ok(Measured {
            tiles: tiles.len() as u64,
            all,
            kept: only_kept,
        })
    }

    /// Every tile of every face of the light's grid, as the reference
    /// tiles it.
    fn tiles(&self, setup: &LightSetup, triangles: &[crate::trace::TraceTriangle]) -> Vec<Tile> {
        let grid = &setup.grid;
        let far = directional_far(grid, triangles, grid.reference_point());
        let tile = self.target.tile;
        let (w, h) = (grid.width(), grid.height());
        let mut tiles = Vec::new();
        for face in 0..grid.faces() {
            let view = face_view(grid, face, (-1.0, far));
            for y0 in (0..h).step_by(tile as usize) {
                for x0 in (0..w).step_by(tile as usize) {
                    let (tw, th) = (tile.min(w - x0), tile.min(h - y0));
                    let m = tile_matrix(
                        w as f64, h as f64, x0 as f64, y0 as f64, tw as f64, th as f64,
                    ) * view.clip_from_rel;
                    tiles.push(Tile {
                        clip_from_rel: m.as_mat4().to_cols_array(),
                        width: tw as i32,
                        height: th as i32,
                    });
                }
            }
        }
        tiles
    }

    /// Draws `runs` into every tile; returns the GPU and CPU seconds.
    unsafe fn draw(&self, tiles: &[Tile], runs: &[&Run]) -> Result<(f64, f64), String> {
        let gl = self.gl;
        let matrix = gl.get_uniform_location(self.program, "clip_from_rel");
        gl.finish();
        let started = Instant::now();
        gl.begin_query(glow::TIME_ELAPSED, self.query);
        for tile in tiles {
            gl.uniform_matrix_4_f32_slice(matrix.as_ref(), false, &tile.clip_from_rel);
            gl.viewport(0, 0, tile.width, tile.height);
            gl.clear_depth_f64(1.0);
            gl.clear(glow::DEPTH_BUFFER_BIT);
            for r in runs {
                let caster = &self.casters.casters[r.caster as usize];
                if self.culling && !caster.double_sided {
                    gl.enable(glow::CULL_FACE);
                } else {
                    gl.disable(glow::CULL_FACE);
                }
                gl.draw_arrays(glow::TRIANGLES, r.first, r.count);
            }
        }
        gl.end_query(glow::TIME_ELAPSED);
        gl.finish();
        let cpu = started.elapsed().as_secs_f64();
        let mut nanoseconds: u64 = 0;
        gl.get_query_parameter_u64_with_offset(
            self.query,
            glow::QUERY_RESULT,
            &mut nanoseconds as *mut u64 as usize,
        );
        if gl.get_error() != glow::NO_ERROR {
            return Err("OpenGL error in the timed shadow pass (timer queries?)".into());
        }
        Ok((nanoseconds as f64 * 1e-9, cpu))
    }
}

/// A pass's draw calls and triangles per tile, its times still to come.
fn pass_of(runs: &[&Run]) -> PassTiming {
    PassTiming {
        draw_calls: runs.len() as u64,
        triangles: runs.iter().map(|r| r.count as u64 / 3).sum(),
        ..PassTiming::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_is_the_middle_sample() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert_eq!(median(&[]), 0.0);
        assert_eq!(ratio(1.0, 4.0), Some(0.25));
        assert_eq!(ratio(1.0, 0.0), None);
    }
}
