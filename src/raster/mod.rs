//! The rasterized reference: the occlusion-query method the ray-cast bake
//! replaces, run through OpenGL (Mesa's llvmpipe where there is no GPU) on
//! the same light frusta and texel grids (pixel centres = texel centres), so
//! users can cross-check the bake against it (`shadowcull xcheck`).
//!
//! Per light, face and tile of the shadow map, and per alpha variant (all
//! groups; alpha-tested groups left out), OR-ed:
//! - pass 1: every caster triangle with depth LESS and depth writes; the
//!   stencil is incremented by every fragment that survives face culling and
//!   the fragment tests, whether it passes depth or not; then receiver-only
//!   instances, which are not drawn into the shadow map: no depth writes, and
//!   they count only where they are not in front of the nearest caster
//!   (depth GEQUAL), as SPEC §4's "receiver-only hits that are not in front
//!   of the front set"; they are never queried;
//! - pass 2: per caster (primitive group, terrain block), an occlusion query
//!   with depth LEQUAL against pass 1 where stencil > 1, no writes; a caster
//!   is useful if any sample passes.
//!
//! The fragment shader applies what a depth-clipped rasterizer would not:
//! spot and point lights keep fragments whose *distance* from the light is in
//! [near, far] (the ray caster's rule; the clip planes are set wider and
//! discard does the rest), and non-terrain fragments below the terrain −
//! heightBias are discarded, with every terrain block in an atlas
//! (`ground_atlas.rs`) and the engine's per-cell diagonal.
//!
//! Occlusion queries are read back in batches ([`QUERY_BATCH`]), and every
//! tile checks that its queries add up to the samples pass 2 drew (counted
//! by additive blending into the colour buffer): a driver whose queries
//! miscount fails the run instead of skewing the comparison.
//!
//! Known differences from the ray cast (and why `xcheck` explains them
//! rather than hides them): rasterization rules at triangle edges vs the
//! ray test's tie rule, f32 depth quantization and interpolated positions
//! vs exact ray distances, and ε ties (LEQUAL ties only exactly equal
//! depths).

pub mod context;
pub mod ground_atlas;
pub mod xcheck;

use crate::bake::casters::CasterTable;
use crate::bake::geometry;
use crate::bake::BakeConfig;
use crate::formats::bake_settings::FaceCulling;
use crate::light::TexelGrid;
use crate::scene::Scene;
use context::GlContext;
use glam::{DMat4, DVec3, DVec4};
use glow::HasContext;
use ground_atlas::GroundAtlas;

/// Largest tile side (pixels); smaller values force tiling (tests).
pub const DEFAULT_MAX_TILE: u32 = 2048;

/// Occlusion queries issued before their results are read. Mesa 22.3's
/// llvmpipe returns wrong samples-passed counts (thousands of samples for a
/// group that drew none, varying from run to run) when a few hundred
/// queries are outstanding: on the `bench` sun, batches of 4096 miscounted
/// 20 groups, 256 one, and 16 to 160 none. 64 keeps a margin; the per-tile
/// self-check in [`raster`] catches a driver that still miscounts.
const QUERY_BATCH: usize = 64;

#[derive(Debug, Clone)]
pub struct RasterResult {
    pub casters: CasterTable,
    /// Per caster id: bit i set = useful for light i (receiver-only: 0).
    pub masks: Vec<u32>,
    /// Per light, per caster: samples (one per texel) that passed its
    /// query in the All variant.
    pub texels: Vec<Vec<u64>>,
    /// The same in the Opaque variant (alpha-tested groups left out); all
    /// zero for a light that reaches no alpha-tested group.
    pub texels_opaque: Vec<Vec<u64>>,
    /// Per light: wall time in seconds.
    pub seconds: Vec<f64>,
    /// Why the below-ground test could not be applied, if so.
    pub ground_note: Option<String>,
    pub renderer: String,
}

const VERTEX: &str = r#"#version 330 core
layout(location = 0) in vec3 pos;
uniform mat4 clip_from_rel;
out vec3 rel;
invariant gl_Position;
void main() {
    rel = pos;
    gl_Position = clip_from_rel * vec4(pos, 1.0);
}
"#;

const FRAGMENT: &str = r#"#version 330 core
in vec3 rel;
uniform int by_distance;
uniform vec3 apex;
uniform float near_d;
uniform float far_d;
uniform int check_ground;
uniform sampler2D heights;
uniform usampler2D cells;
uniform sampler2D block_place;
uniform sampler2D block_frame;
uniform vec2 grid_origin;
uniform float chunk_size;
uniform ivec2 grid_count;
uniform float height_bias;
out vec4 colour;

// H(p) as bake::ground::Ground finds it (see ground_atlas.rs, whose
// `height` is this function in f64): the chunk of p's floor, then its
// neighbours for points on a border or in a hole.
bool ground_height(vec2 p, out float h) {
    ivec2 g0 = ivec2(floor((p - grid_origin) / chunk_size));
    for (int k = 0; k < 4; k++) {
        ivec2 g = g0 - ivec2(k & 1, k >> 1);
        if (any(lessThan(g, ivec2(0))) || any(greaterThanEqual(g, grid_count))) continue;
        vec4 place = texelFetch(block_place, g, 0);
        if (place.x < 0.0) continue;
        vec4 frame = texelFetch(block_frame, g, 0);
        vec2 l = p - frame.xy;
        if (any(lessThan(l, vec2(0.0))) || any(greaterThan(l, vec2(chunk_size)))) continue;
        ivec2 n = ivec2(place.zw);
        vec2 gl = l / frame.zw;
        ivec2 c = min(ivec2(max(floor(gl), vec2(0.0))), n - 1);
        vec2 t = clamp(gl - vec2(c), 0.0, 1.0);
        ivec2 a = ivec2(place.xy) + c;
        uint f = texelFetch(cells, a, 0).r;
        if ((f & 1u) == 0u) continue;
        float xf = t.x;
        float zf = t.y;
        float h00 = texelFetch(heights, a, 0).r;
        float h10 = texelFetch(heights, a + ivec2(1, 0), 0).r;
        float h01 = texelFetch(heights, a + ivec2(0, 1), 0).r;
        float h11 = texelFetch(heights, a + ivec2(1, 1), 0).r;
        if ((f & 2u) != 0u) {
            if ((1.0 - xf) > zf) h = h00 + (h10 - h00) * xf + (h01 - h00) * zf;
            else h = h11 + (h01 - h11) * (1.0 - xf) + (h10 - h11) * (1.0 - zf);
        } else if (xf > zf) {
            h = h10 + (h00 - h10) * (1.0 - xf) + (h11 - h10) * zf;
        } else {
            h = h01 + (h11 - h01) * xf + (h00 - h01) * (1.0 - zf);
        }
        return true;
    }
    return false;
}

void main() {
    if (by_distance == 1) {
        float d = length(rel - apex);
        if (d < near_d || d > far_d) discard;
    }
    if (check_ground == 1) {
        float h;
        if (ground_height(rel.xz, h) && rel.y < h - height_bias) discard;
    }
    colour = vec4(1.0);
}
"#;

/// A contiguous run of one caster's triangles in the vertex buffer.
#[derive(Debug, Clone, Copy)]
struct Run {
    caster: u32,
    first: i32,
    count: i32,
}

/// How one face of a light maps light-relative points to the shadow map.
struct FaceView {
    /// Clip coordinates from light-relative ones, for the whole face (tiles
    /// compose a scale and offset on top).
    clip_from_rel: DMat4,
    perspective: Option<(DVec3, f64, f64)>,
}

fn face_view(grid: &TexelGrid, face: usize, depth_range: (f64, f64)) -> FaceView {
    let reference = grid.reference_point();
    let (w, h) = (grid.width() as f64, grid.height() as f64);
    let centre = grid.ray_through(face, w / 2.0, h / 2.0);
    if centre.t_min == 0.0 && grid.faces() == 1 && is_orthographic(grid) {
        let o0 = grid.ray_through(face, 0.0, 0.0).origin - reference;
        let uw = grid.ray_through(face, w, 0.0).origin - reference - o0;
        let vh = grid.ray_through(face, 0.0, h).origin - reference - o0;
        let d = centre.direction;
        let (near, far) = depth_range;
        // Texel units X = (q − o0)·uw/|uw|²·w, then NDC over the full face.
        let sx = uw / uw.length_squared() * 2.0;
        let sy = vh / vh.length_squared() * 2.0;
        let sz = d * (2.0 / (far - near));
        let rows = [
            DVec4::new(sx.x, sx.y, sx.z, -sx.dot(o0) - 1.0),
            DVec4::new(sy.x, sy.y, sy.z, -sy.dot(o0) - 1.0),
            DVec4::new(
                sz.x,
                sz.y,
                sz.z,
                -sz.dot(o0) - 2.0 * near / (far - near) - 1.0,
            ),
            DVec4::new(0.0, 0.0, 0.0, 1.0),
        ];
        return FaceView {
            clip_from_rel: DMat4::from_cols(rows[0], rows[1], rows[2], rows[3]).transpose(),
            perspective: None,
        };
    }
    let apex = centre.origin - reference;
    let f = centre.direction;
    let edge_u = grid.ray_through(face, w, h / 2.0).direction;
    let edge_v = grid.ray_through(face, w / 2.0, h).direction;
    let ku = edge_u / edge_u.dot(f) - f;
    let kv = edge_v / edge_v.dot(f) - f;
    let su = ku / ku.length_squared();
    let sv = kv / kv.length_squared();
    let k2 = ku.length_squared().max(kv.length_squared());
    let (near, far) = (centre.t_min, centre.t_max);
    // The clip planes bound depth along the axis, which is at most the
    // distance; the shader keeps [near, far] by distance.
    let n = (near / (1.0 + 2.0 * k2).sqrt() * 0.999).max(1e-4);
    let fc = far * 1.001;
    let a = (fc + n) / (fc - n);
    let b = -2.0 * fc * n / (fc - n);
    // Rows act on q = p − apex; fold the translation into the last column.
    let row = |v: DVec3, c: f64| DVec4::new(v.x, v.y, v.z, -v.dot(apex) + c);
    let rows = [
        row(su, 0.0),
        row(sv, 0.0),
        DVec4::new(f.x * a, f.y * a, f.z * a, -f.dot(apex) * a + b),
        row(f, 0.0),
    ];
    FaceView {
        clip_from_rel: DMat4::from_cols(rows[0], rows[1], rows[2], rows[3]).transpose(),
        perspective: Some((apex, near, far)),
    }
}

/// A directional grid: every texel's ray has the same direction and its own
/// origin.
fn is_orthographic(grid: &TexelGrid) -> bool {
    let a = grid.ray_through(0, 0.0, 0.0);
    let b = grid.ray_through(0, grid.width() as f64, grid.height() as f64);
    a.origin != b.origin
}

/// The NDC window of texels [x0, x0 + tw) × [y0, y0 + th) of a face of
/// `w × h` texels, stretched to the full viewport.
fn tile_matrix(w: f64, h: f64, x0: f64, y0: f64, tw: f64, th: f64) -> DMat4 {
    // Face NDC n → texel X = (n + 1)/2·w → tile NDC 2(X − x0)/tw − 1.
    let sx = w / tw;
    let sy = h / th;
    DMat4::from_cols(
        DVec4::new(sx, 0.0, 0.0, 0.0),
        DVec4::new(0.0, sy, 0.0, 0.0),
        DVec4::new(0.0, 0.0, 1.0, 0.0),
        DVec4::new(sx - 2.0 * x0 / tw - 1.0, sy - 2.0 * y0 / th - 1.0, 0.0, 1.0),
    )
}

unsafe fn compile(gl: &glow::Context) -> Result<glow::Program, String> {
    let program = gl.create_program()?;
    for (kind, source) in [
        (glow::VERTEX_SHADER, VERTEX),
        (glow::FRAGMENT_SHADER, FRAGMENT),
    ] {
        let shader = gl.create_shader(kind)?;
        gl.shader_source(shader, source);
        gl.compile_shader(shader);
        if !gl.get_shader_compile_status(shader) {
            return Err(format!("shader: {}", gl.get_shader_info_log(shader)));
        }
        gl.attach_shader(program, shader);
    }
    gl.link_program(program);
    if !gl.get_program_link_status(program) {
        return Err(format!("link: {}", gl.get_program_info_log(program)));
    }
    Ok(program)
}

/// Runs the rasterized method for every light of `config` (its face
/// culling and height bias; supersampling and refinement do not apply).
pub fn raster(scene: &Scene, config: &BakeConfig, max_tile: u32) -> Result<RasterResult, String> {
    let ctx = GlContext::new()?;
    // SAFETY: every GL call below runs on the thread where `ctx` is current,
    // with objects created in it and buffers sized from Rust slices.
    unsafe { raster_in(&ctx, scene, config, max_tile.max(1)) }
}

unsafe fn raster_in(
    ctx: &GlContext,
    scene: &Scene,
    config: &BakeConfig,
    max_tile: u32,
) -> Result<RasterResult, String> {
    let gl = &ctx.gl;
    let casters = CasterTable::new(scene);
    let mut masks = vec![0u32; casters.len()];
    let mut texels = Vec::new();
    let mut texels_opaque = Vec::new();
    let mut seconds = Vec::new();
    let program = compile(gl)?;
    gl.use_program(Some(program));
    let u = |name: &str| gl.get_uniform_location(program, name);

    let max_texture = gl.get_parameter_i32(glow::MAX_TEXTURE_SIZE).max(1) as usize;
    let (atlas, ground_note) = match GroundAtlas::new(scene, max_texture) {
        Ok(a) => (a, None),
        Err(why) => (
            None,
            Some(format!("below-ground test off in the raster: {why}")),
        ),
    };

    let limit = gl.get_parameter_i32(glow::MAX_RENDERBUFFER_SIZE).max(1) as u32;
    let tile = max_tile.min(limit);
    let fbo = gl.create_framebuffer()?;
    gl.bind_framebuffer(glow::FRAMEBUFFER, Some(fbo));
    let colour_rb = gl.create_renderbuffer()?;
    gl.bind_renderbuffer(glow::RENDERBUFFER, Some(colour_rb));
    // Pass 2 also adds 1 per passing sample here (float blending is exact
    // to 2^24 per texel), so the queries can be checked against what was
    // drawn.
    gl.renderbuffer_storage(glow::RENDERBUFFER, glow::R32F, tile as i32, tile as i32);
    gl.framebuffer_renderbuffer(
        glow::FRAMEBUFFER,
        glow::COLOR_ATTACHMENT0,
        glow::RENDERBUFFER,
        Some(colour_rb),
    );
    let depth_rb = gl.create_renderbuffer()?;
    gl.bind_renderbuffer(glow::RENDERBUFFER, Some(depth_rb));
    gl.renderbuffer_storage(
        glow::RENDERBUFFER,
        glow::DEPTH32F_STENCIL8,
        tile as i32,
        tile as i32,
    );
    gl.framebuffer_renderbuffer(
        glow::FRAMEBUFFER,
        glow::DEPTH_STENCIL_ATTACHMENT,
        glow::RENDERBUFFER,
        Some(depth_rb),
    );
    if gl.check_framebuffer_status(glow::FRAMEBUFFER) != glow::FRAMEBUFFER_COMPLETE {
        return Err("the depth32f/stencil8 framebuffer is not complete".into());
    }
    gl.enable(glow::DEPTH_TEST);
    gl.enable(glow::STENCIL_TEST);
    gl.disable(glow::MULTISAMPLE);
    gl.blend_func(glow::ONE, glow::ONE);
    gl.pixel_store_i32(glow::PACK_ALIGNMENT, 4);
    let mut drawn = Vec::new();
    // CCW in the light's window (x along u, y along v, depth along u × v)
    // is a normal along the ray: a back face.
    gl.front_face(glow::CW);
    gl.cull_face(match config.face_culling {
        FaceCulling::Front => glow::FRONT,
        _ => glow::BACK,
    });
    let culling = config.face_culling != FaceCulling::None;

    let vao = gl.create_vertex_array()?;
    gl.bind_vertex_array(Some(vao));
    let vbo = gl.create_buffer()?;
    gl.bind_buffer(glow::ARRAY_BUFFER, Some(vbo));
    gl.enable_vertex_attrib_array(0);
    gl.vertex_attrib_pointer_f32(0, 3, glow::FLOAT, false, 12, 0);

    let ground_textures = [
        gl.create_texture()?,
        gl.create_texture()?,
        gl.create_texture()?,
        gl.create_texture()?,
    ];
    let bounds = geometry::world_bounds(scene);
    for (index, light) in config.lights.iter().enumerate() {
        let started = std::time::Instant::now();
        let mut counts = vec![0u64; casters.len()];
        let mut counts_opaque = vec![0u64; casters.len()];
        let Some(bounds) = bounds else {
            texels_opaque.push(counts.clone());
            texels.push(counts);
            seconds.push(0.0);
            continue;
        };
        let grid = match TexelGrid::new(light, bounds) {
            Ok(g) => g,
            Err(crate::light::GridError::EmptyWorld { .. }) => {
                texels_opaque.push(counts.clone());
                texels.push(counts);
                seconds.push(0.0);
                continue;
            }
            Err(e) => return Err(e.to_string()),
        };
        let reference = grid.reference_point();
        let geo = geometry::light_geometry(scene, &casters, &grid);
        let mut vertices: Vec<f32> = Vec::with_capacity(geo.triangles.len() * 9);
        let mut runs: Vec<Run> = Vec::new();
        for (i, t) in geo.triangles.iter().enumerate() {
            for v in &t.vertices {
                vertices.extend_from_slice(&[v.x, v.y, v.z]);
            }
            match runs.last_mut() {
                Some(r) if r.caster == t.caster => r.count += 3,
                _ => runs.push(Run {
                    caster: t.caster,
                    first: (i * 3) as i32,
                    count: 3,
                }),
            }
        }
        gl.buffer_data_u8_slice(glow::ARRAY_BUFFER, bytes_of(&vertices), glow::STATIC_DRAW);

        let ground_on = if let Some(atlas) = &atlas {
            upload_ground(gl, atlas, reference, ground_textures, &u);
            gl.uniform_1_f32(u("height_bias").as_ref(), config.height_bias as f32);
            true
        } else {
            false
        };

        // Depth range of a directional light: what the geometry spans along
        // the ray from the origin plane.
        let o0 = grid.ray_through(0, 0.0, 0.0);
        let d = o0.direction;
        let origin_rel = o0.origin - reference;
        let far = geo
            .triangles
            .iter()
            .flat_map(|t| t.vertices.iter())
            .map(|v| (v.as_dvec3() - origin_rel).dot(d))
            .fold(1.0f64, f64::max)
            * 1.01
            + 1.0;
        let variants: &[bool] = if geo.reaches_alpha_tested {
            &[false, true]
        } else {
            &[false]
        };
        let mut queries = Vec::new();
        for _ in 0..runs.len() {
            queries.push(gl.create_query()?);
        }
        let mut useful = vec![false; casters.len()];
        for face in 0..grid.faces() {
            let view = face_view(&grid, face, (-1.0, far));
            match view.perspective {
                Some((apex, near, far)) => {
                    gl.uniform_1_i32(u("by_distance").as_ref(), 1);
                    gl.uniform_3_f32(
                        u("apex").as_ref(),
                        apex.x as f32,
                        apex.y as f32,
                        apex.z as f32,
                    );
                    gl.uniform_1_f32(u("near_d").as_ref(), near as f32);
                    gl.uniform_1_f32(
                        u("far_d").as_ref(),
                        if far.is_finite() {
                            far as f32
                        } else {
                            f32::MAX
                        },
                    );
                }
                None => gl.uniform_1_i32(u("by_distance").as_ref(), 0),
            }
            let (w, h) = (grid.width(), grid.height());
            for y0 in (0..h).step_by(tile as usize) {
                for x0 in (0..w).step_by(tile as usize) {
                    let tw = tile.min(w - x0);
                    let th = tile.min(h - y0);
                    let m = tile_matrix(
                        w as f64, h as f64, x0 as f64, y0 as f64, tw as f64, th as f64,
                    ) * view.clip_from_rel;
                    gl.uniform_matrix_4_f32_slice(
                        u("clip_from_rel").as_ref(),
                        false,
                        &m.as_mat4().to_cols_array(),
                    );
                    gl.viewport(0, 0, tw as i32, th as i32);
                    for &opaque_only in variants {
                        let included = |r: &Run| {
                            !(opaque_only && casters.casters[r.caster as usize].alpha_tested)
                        };
                        gl.depth_mask(true);
                        gl.stencil_mask(0xff);
                        gl.color_mask(true, false, false, false);
                        gl.clear_depth_f64(1.0);
                        gl.clear_stencil(0);
                        gl.clear_color(0.0, 0.0, 0.0, 0.0);
                        gl.clear(
                            glow::DEPTH_BUFFER_BIT
                                | glow::STENCIL_BUFFER_BIT
                                | glow::COLOR_BUFFER_BIT,
                        );
                        gl.color_mask(false, false, false, false);
                        // Pass 1: casters write the nearest caster depth;
                        // every fragment counts in the stencil.
                        gl.depth_func(glow::LESS);
                        gl.stencil_func(glow::ALWAYS, 0, 0xff);
                        gl.stencil_op(glow::KEEP, glow::INCR, glow::INCR);
                        let receiver = |r: &Run| casters.casters[r.caster as usize].receiver_only;
                        for r in runs.iter().filter(|r| included(r) && !receiver(r)) {
                            draw_run(gl, &casters, r, culling, ground_on, &u);
                        }
                        // Receiver-only instances are not drawn into the
                        // shadow map (SPEC §2): they write no depth, and
                        // count only where they are not in front of the
                        // nearest caster (SPEC §4), i.e. depth GEQUAL.
                        gl.depth_mask(false);
                        gl.depth_func(glow::GEQUAL);
                        gl.stencil_op(glow::KEEP, glow::KEEP, glow::INCR);
                        for r in runs.iter().filter(|r| included(r) && receiver(r)) {
                            draw_run(gl, &casters, r, culling, ground_on, &u);
                        }
                        // Pass 2.
                        gl.depth_mask(false);
                        gl.stencil_mask(0);
                        gl.depth_func(glow::LEQUAL);
                        gl.stencil_func(glow::LESS, 1, 0xff);
                        gl.stencil_op(glow::KEEP, glow::KEEP, glow::KEEP);
                        gl.color_mask(true, false, false, false);
                        gl.enable(glow::BLEND);
                        let mut asked = Vec::new();
                        let mut counted = 0u64;
                        let tally = if opaque_only {
                            &mut counts_opaque
                        } else {
                            &mut counts
                        };
                        for (r, q) in runs.iter().zip(&queries) {
                            let caster = &casters.casters[r.caster as usize];
                            if !included(r) || caster.receiver_only {
                                continue;
                            }
                            gl.begin_query(glow::SAMPLES_PASSED, *q);
                            draw_run(gl, &casters, r, culling, ground_on, &u);
                            gl.end_query(glow::SAMPLES_PASSED);
                            asked.push((r.caster, *q));
                            if asked.len() >= QUERY_BATCH {
                                counted += read_queries(gl, &mut asked, &mut useful, |c, n| {
                                    tally[c] += n;
                                });
                            }
                        }
                        counted += read_queries(gl, &mut asked, &mut useful, |c, n| {
                            tally[c] += n;
                        });
                        gl.disable(glow::BLEND);
                        // The queries must add up to the samples drawn.
                        drawn.resize(tw as usize * th as usize, 0f32);
                        gl.read_pixels(
                            0,
                            0,
                            tw as i32,
                            th as i32,
                            glow::RED,
                            glow::FLOAT,
                            glow::PixelPackData::Slice(Some(bytes_of_mut(&mut drawn))),
                        );
                        let samples: u64 = drawn.iter().map(|&n| n as u64).sum();
                        if samples != counted {
                            return Err(format!(
                                "the OpenGL driver's occlusion queries counted {counted} samples \
                                 where it drew {samples} (light {index}, face {face}, tile at \
                                 texel {x0}, {y0}); its query results cannot be trusted (a driver bug: \
                                 try another driver, e.g. a GPU's or Mesa's llvmpipe with LIBGL_ALWAYS_SOFTWARE=1)"
                            ));
                        }
                    }
                }
            }
        }
        for q in queries {
            gl.delete_query(q);
        }
        if gl.get_error() != glow::NO_ERROR {
            return Err(format!("OpenGL error while rasterizing light {index}"));
        }
        for (id, u) in useful.iter().enumerate() {
            if *u && !casters.casters[id].receiver_only {
                masks[id] |= 1 << index;
            }
        }
        texels.push(counts);
        texels_opaque.push(counts_opaque);
        seconds.push(started.elapsed().as_secs_f64());
    }
    for texture in ground_textures {
        gl.delete_texture(texture);
    }
    gl.delete_buffer(vbo);
    gl.delete_vertex_array(vao);
    gl.delete_renderbuffer(colour_rb);
    gl.delete_renderbuffer(depth_rb);
    gl.delete_framebuffer(fbo);
    gl.delete_program(program);
    Ok(RasterResult {
        casters,
        masks,
        texels,
        texels_opaque,
        seconds,
        ground_note,
        renderer: ctx.renderer.clone(),
    })
}

unsafe fn draw_run(
    gl: &glow::Context,
    casters: &CasterTable,
    r: &Run,
    culling: bool,
    ground_on: bool,
    u: &dyn Fn(&str) -> Option<glow::UniformLocation>,
) {
    let caster = &casters.casters[r.caster as usize];
    if culling && !caster.double_sided {
        gl.enable(glow::CULL_FACE);
    } else {
        gl.disable(glow::CULL_FACE);
    }
    gl.uniform_1_i32(
        u("check_ground").as_ref(),
        i32::from(ground_on && !caster.is_terrain()),
    );
    gl.draw_arrays(glow::TRIANGLES, r.first, r.count);
}

/// Reads (and forgets) the results of `asked`, marking passing casters
/// useful and handing each count to `count`; returns the samples counted.
unsafe fn read_queries(
    gl: &glow::Context,
    asked: &mut Vec<(u32, glow::Query)>,
    useful: &mut [bool],
    mut count: impl FnMut(usize, u64),
) -> u64 {
    let mut total = 0;
    for (caster, q) in asked.drain(..) {
        let n = u64::from(gl.get_query_parameter_u32(q, glow::QUERY_RESULT));
        if n > 0 {
            useful[caster as usize] = true;
        }
        count(caster as usize, n);
        total += n;
    }
    total
}

/// Puts the ground atlas into texture units 0–3 (heights, cell flags, block
/// placement, block frame), relative to `reference`, and sets the
/// shader's ground uniforms but the bias.
unsafe fn upload_ground(
    gl: &glow::Context,
    atlas: &GroundAtlas,
    reference: DVec3,
    textures: [glow::Texture; 4],
    u: &dyn Fn(&str) -> Option<glow::UniformLocation>,
) {
    let heights: Vec<f32> = atlas
        .heights
        .iter()
        .map(|h| (h - reference.y) as f32)
        .collect();
    let mut place = Vec::with_capacity(atlas.index.len() * 4);
    let mut frame = Vec::with_capacity(atlas.index.len() * 4);
    for entry in &atlas.index {
        match entry {
            Some(p) => {
                place.extend([p.atlas.0, p.atlas.1, p.cells.0, p.cells.1].map(|v| v as f32));
                frame.extend(
                    [
                        p.origin.0 - reference.x,
                        p.origin.1 - reference.z,
                        p.spacing.0,
                        p.spacing.1,
                    ]
                    .map(|v| v as f32),
                );
            }
            None => {
                place.extend([-1.0f32; 4]);
                frame.extend([0.0f32, 0.0, 1.0, 1.0]);
            }
        }
    }
    let (aw, ah) = (atlas.size.0 as i32, atlas.size.1 as i32);
    let (gw, gh) = (atlas.grid_count.0 as i32, atlas.grid_count.1 as i32);
    gl.pixel_store_i32(glow::UNPACK_ALIGNMENT, 1);
    // (internal format, size, pixel format, pixel type, data) per unit.
    let atlas_size = (aw, ah);
    let grid_size = (gw, gh);
    let uploads = [
        (
            glow::R32F,
            atlas_size,
            glow::RED,
            glow::FLOAT,
            bytes_of(&heights),
        ),
        (
            glow::R8UI,
            atlas_size,
            glow::RED_INTEGER,
            glow::UNSIGNED_BYTE,
            &atlas.flags[..],
        ),
        (
            glow::RGBA32F,
            grid_size,
            glow::RGBA,
            glow::FLOAT,
            bytes_of(&place),
        ),
        (
            glow::RGBA32F,
            grid_size,
            glow::RGBA,
            glow::FLOAT,
            bytes_of(&frame),
        ),
    ];
    for (unit, (texture, (internal, (w, h), format, kind, data))) in
        textures.into_iter().zip(uploads).enumerate()
    {
        gl.active_texture(glow::TEXTURE0 + unit as u32);
        gl.bind_texture(glow::TEXTURE_2D, Some(texture));
        gl.tex_image_2d(
            glow::TEXTURE_2D,
            0,
            internal as i32,
            w,
            h,
            0,
            format,
            kind,
            glow::PixelUnpackData::Slice(Some(data)),
        );
        set_nearest(gl);
    }
    for (unit, name) in ["heights", "cells", "block_place", "block_frame"]
        .iter()
        .enumerate()
    {
        gl.uniform_1_i32(u(name).as_ref(), unit as i32);
    }
    gl.uniform_2_f32(
        u("grid_origin").as_ref(),
        (f64::from(atlas.grid_min.0) * atlas.chunk_size - reference.x) as f32,
        (f64::from(atlas.grid_min.1) * atlas.chunk_size - reference.z) as f32,
    );
    gl.uniform_1_f32(u("chunk_size").as_ref(), atlas.chunk_size as f32);
    gl.uniform_2_i32(u("grid_count").as_ref(), gw, gh);
}

unsafe fn set_nearest(gl: &glow::Context) {
    gl.tex_parameter_i32(
        glow::TEXTURE_2D,
        glow::TEXTURE_MIN_FILTER,
        glow::NEAREST as i32,
    );
    gl.tex_parameter_i32(
        glow::TEXTURE_2D,
        glow::TEXTURE_MAG_FILTER,
        glow::NEAREST as i32,
    );
}

fn bytes_of(v: &[f32]) -> &[u8] {
    // SAFETY: f32 has no padding, and any byte is a valid u8.
    unsafe { std::slice::from_raw_parts(v.as_ptr().cast(), std::mem::size_of_val(v)) }
}

fn bytes_of_mut(v: &mut [f32]) -> &mut [u8] {
    // SAFETY: as `bytes_of`, and every bit pattern is a valid f32.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast(), std::mem::size_of_val(v)) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_matrix_maps_tile_edges_to_ndc_edges() {
        // A 100-texel face, tile [40, 60): face NDC of X=40 is −0.2, of 60 is 0.2.
        let m = tile_matrix(100.0, 100.0, 40.0, 0.0, 20.0, 100.0);
        let left = m * DVec4::new(-0.2, 0.0, 0.0, 1.0);
        let right = m * DVec4::new(0.2, 0.0, 0.0, 1.0);
        assert!((left.x + 1.0).abs() < 1e-12 && (right.x - 1.0).abs() < 1e-12);
    }
}
