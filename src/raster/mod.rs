//! The rasterized reference: the occlusion-query method the ray-cast bake
//! replaces, run through OpenGL (Mesa's llvmpipe where there is no GPU) on
//! the same lights as the bake: every light is prepared by
//! [`LightSetup::new`], so the raster sees the bake's grid (pixel centres =
//! texel centres), reach and passes.
//!
//! Per light, face and tile of the shadow map, and per alpha variant (all
//! groups; alpha-tested groups left out), OR-ed:
//! - pass 1: every caster triangle with depth LESS and depth writes; the
//!   stencil is incremented by every fragment that survives face culling and
//!   the fragment tests, whether it passes depth or not; then receiver-only
//!   instances, which are not drawn into the shadow map: no depth writes, and
//!   they count only where they are not in front of the nearest caster
//!   (depth GEQUAL), as docs/contract.md §4's "receiver-only hits that are not in front
//!   of the front set"; they are never counted;
//! - pass 2: per caster (primitive group, terrain block), the samples that
//!   pass depth LEQUAL against pass 1 where stencil > 1, no writes; a caster
//!   is useful if any sample passes.
//!
//! Pass 2's samples are counted by a [`Counter`]: per-caster atomic counters
//! written by the fragments that passed early depth and stencil tests (the
//! default), or occlusion queries, or both compared caster by caster. Every
//! tile checks that its counts add up to the samples pass 2 drew (counted
//! by additive blending into the colour buffer): a driver that miscounts
//! fails the run instead of skewing the comparison.
//!
//! Why not queries alone: Mesa's llvmpipe (seen on 22.3) bins a query's
//! begin and end into every 64×64 bin of the framebuffer; when its scene
//! memory runs out part-way through those bins it flushes the scene with the
//! query already marked active, and the bins that missed the command count
//! the samples of earlier queries (or count twice) at the end of the bin.
//! More bins (2048² tiles: 1024) and more triangles per scene make that
//! likelier, and a tile that overcounts does so on every run. A flush
//! before every begin and end keeps both in an empty scene and makes the
//! queries exact (the `Queries` counter does that), at a cost that grows
//! with the queries; atomic counters need no flush at all.
//!
//! The fragment shader applies what a depth-clipped rasterizer would not:
//! spot and point lights keep fragments whose *distance* from the light is in
//! [near, far] (the ray caster's rule; the clip planes are set wider and
//! discard does the rest), and non-terrain fragments below the terrain −
//! heightBias are discarded, with every terrain block in an atlas
//! (`ground_atlas.rs`) and the engine's per-cell diagonal.
//!
//! Known differences from the ray cast (and why `xcheck` explains them
//! rather than hides them): rasterization rules at triangle edges vs the
//! ray test's tie rule, f32 depth quantization and interpolated positions
//! vs exact ray distances, and ε ties (LEQUAL ties only exactly equal
//! depths).

pub mod context;
pub mod ground_atlas;
pub mod savings;
pub mod xcheck;

use crate::bake::casters::CasterTable;
use crate::bake::setup::{BakeWorld, LightSetup};
use crate::bake::BakeConfig;
use crate::classify::Passes;
use crate::formats::bake_settings::FaceCulling;
use crate::light::TexelGrid;
use context::GlContext;
use glam::{DMat4, DVec3, DVec4};
use glow::HasContext;
use ground_atlas::GroundAtlas;
use std::sync::Arc;

/// Largest tile side (pixels); smaller values force tiling (tests).
pub const DEFAULT_MAX_TILE: u32 = 2048;

/// Occlusion queries issued before their results are read (each read waits
/// for the rasterizer). With the flush before every begin and end
/// ([`Counter::Queries`]) the batch size does not change the counts.
const QUERY_BATCH: usize = 64;

/// How pass 2's passing samples are counted per caster.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Counter {
    /// A storage buffer of per-caster counters, incremented atomically by
    /// every fragment that passed the early depth and stencil tests.
    #[default]
    Atomics,
    /// `GL_SAMPLES_PASSED` queries, with a flush before every begin and
    /// end (the llvmpipe workaround in this module's notes).
    Queries,
    /// Queries without those flushes: llvmpipe miscounts at large tiles.
    /// Kept to show the driver bug (tests); not for cross-checking.
    QueriesUnflushed,
    /// Atomics and flushed queries, one after the other on the same depth
    /// and stencil; every caster's two counts must be equal.
    Both,
}

/// A deliberate fault, so tests can show the per-tile self-check fails.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Fault {
    #[default]
    None,
    /// One sample added to the first caster counted in every tile.
    ExtraSample,
}

#[derive(Debug, Clone, Copy)]
pub struct RasterOptions {
    /// Largest tile side (pixels), capped by the driver's limit.
    pub max_tile: u32,
    pub counter: Counter,
    pub fault: Fault,
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions {
            max_tile: DEFAULT_MAX_TILE,
            counter: Counter::default(),
            fault: Fault::None,
        }
    }
}

impl RasterOptions {
    /// The defaults with tiles of at most `max_tile` pixels.
    pub fn with_tile(max_tile: u32) -> Self {
        RasterOptions {
            max_tile,
            ..Default::default()
        }
    }
}

#[derive(Debug, Clone)]
pub struct RasterResult {
    pub casters: Arc<CasterTable>,
    /// Per caster id: bit i set = useful for light i (receiver-only: 0).
    pub masks: Vec<u32>,
    /// Per light, per caster: samples (one per texel) that passed pass 2
    /// in the All variant.
    pub texels: Vec<Vec<u64>>,
    /// The same in the Opaque variant (alpha-tested groups left out); all
    /// zero for a light that reaches no alpha-tested group.
    pub texels_opaque: Vec<Vec<u64>>,
    /// Per light: wall time in seconds.
    pub seconds: Vec<f64>,
    /// Per light: tiles drawn (faces × tiles × variants).
    pub tiles: Vec<u64>,
    /// Why the below-ground test could not be applied, if so.
    pub ground_note: Option<String>,
    pub renderer: String,
    pub counter: Counter,
}

const VERTEX: &str = r#"
layout(location = 0) in vec3 pos;
uniform mat4 clip_from_rel;
out vec3 rel;
invariant gl_Position;
void main() {
    rel = pos;
    gl_Position = clip_from_rel * vec4(pos, 1.0);
}
"#;

/// GLSL 4.30: storage buffers, atomics and early fragment tests.
const GLSL_VERSION: &str = "#version 430 core\n";
const FRAGMENT: &str = r#"
in vec3 rel;
#ifdef COUNT
// Depth and stencil decide before the shader runs, so only fragments that
// pass them reach the counter; a discard below still keeps a fragment out
// of it, as it keeps it out of an occlusion query.
layout(early_fragment_tests) in;
layout(std430, binding = 0) buffer Counts { uint counts[]; };
uniform uint slot;
#endif
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
#ifdef COUNT
    atomicAdd(counts[slot], 1u);
#endif
    colour = vec4(1.0);
}
"#;

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

/// A contiguous run of one caster's triangles in the vertex buffer.
#[derive(Debug, Clone, Copy)]
struct Run {
    caster: u32,
    first: i32,
    count: i32,
}

/// The two programs: `draw` (pass 1, and pass 2 under queries) and `count`
/// (pass 2 under atomics: the same vertex shader, so `invariant
/// gl_Position` gives both passes the same depths).
struct Programs {
    draw: glow::Program,
    count: glow::Program,
}

impl Programs {
    unsafe fn new(gl: &glow::Context) -> Result<Programs, String> {
        Ok(Programs {
            draw: compile(gl, "")?,
            count: compile(gl, "#define COUNT 1\n")?,
        })
    }

    /// Sets a uniform in both programs, leaving `draw` in use.
    unsafe fn set(
        &self,
        gl: &glow::Context,
        name: &str,
        value: impl Fn(Option<&glow::UniformLocation>),
    ) {
        for program in [self.count, self.draw] {
            gl.use_program(Some(program));
            value(gl.get_uniform_location(program, name).as_ref());
        }
    }

    unsafe fn delete(self, gl: &glow::Context) {
        gl.delete_program(self.draw);
        gl.delete_program(self.count);
    }
}

unsafe fn compile(gl: &glow::Context, defines: &str) -> Result<glow::Program, String> {
    link(
        gl,
        &format!("{defines}{VERTEX}"),
        &format!("{defines}{FRAGMENT}"),
    )
}

/// A program of these two shaders, each after the GLSL version line.
unsafe fn link(gl: &glow::Context, vertex: &str, fragment: &str) -> Result<glow::Program, String> {
    let program = gl.create_program()?;
    for (kind, source) in [
        (glow::VERTEX_SHADER, vertex),
        (glow::FRAGMENT_SHADER, fragment),
    ] {
        let shader = gl.create_shader(kind)?;
        gl.shader_source(shader, &format!("{GLSL_VERSION}{source}"));
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
/// culling and height bias; supersampling and refinement do not apply) over
/// `world`, each light prepared by [`LightSetup::new`].
pub fn raster(
    world: &BakeWorld,
    config: &BakeConfig,
    options: &RasterOptions,
) -> Result<RasterResult, String> {
    let ctx = GlContext::new()?;
    // SAFETY: every GL call below runs on the thread where `ctx` is current,
    // with objects created in it and buffers sized from Rust slices.
    unsafe { raster_in(&ctx, world, config, options) }
}

/// The GL objects every light reuses.
struct Target {
    fbo: glow::Framebuffer,
    colour: glow::Renderbuffer,
    depth: glow::Renderbuffer,
    vao: glow::VertexArray,
    vbo: glow::Buffer,
    counts: glow::Buffer,
    ground: [glow::Texture; 4],
    tile: u32,
}

impl Target {
    unsafe fn new(gl: &glow::Context, max_tile: u32) -> Result<Target, String> {
        let limit = gl.get_parameter_i32(glow::MAX_RENDERBUFFER_SIZE).max(1) as u32;
        let tile = max_tile.max(1).min(limit);
        let fbo = gl.create_framebuffer()?;
        gl.bind_framebuffer(glow::FRAMEBUFFER, Some(fbo));
        // Pass 2 also adds 1 per passing sample to the colour (float
        // blending is exact to 2^24 per texel), so the counts can be checked
        // against what was drawn.
        let colour = attach(gl, glow::R32F, glow::COLOR_ATTACHMENT0, tile)?;
        let depth = attach(
            gl,
            glow::DEPTH32F_STENCIL8,
            glow::DEPTH_STENCIL_ATTACHMENT,
            tile,
        )?;
        if gl.check_framebuffer_status(glow::FRAMEBUFFER) != glow::FRAMEBUFFER_COMPLETE {
            return Err("the depth32f/stencil8 framebuffer is not complete".into());
        }
        let vao = gl.create_vertex_array()?;
        gl.bind_vertex_array(Some(vao));
        let vbo = gl.create_buffer()?;
        gl.bind_buffer(glow::ARRAY_BUFFER, Some(vbo));
        gl.enable_vertex_attrib_array(0);
        gl.vertex_attrib_pointer_f32(0, 3, glow::FLOAT, false, 12, 0);
        let counts = gl.create_buffer()?;
        gl.bind_buffer(glow::SHADER_STORAGE_BUFFER, Some(counts));
        gl.bind_buffer_base(glow::SHADER_STORAGE_BUFFER, 0, Some(counts));
        let ground = [
            gl.create_texture()?,
            gl.create_texture()?,
            gl.create_texture()?,
            gl.create_texture()?,
        ];
        Ok(Target {
            fbo,
            colour,
            depth,
            vao,
            vbo,
            counts,
            ground,
            tile,
        })
    }

    unsafe fn delete(self, gl: &glow::Context) {
        for texture in self.ground {
            gl.delete_texture(texture);
        }
        gl.delete_buffer(self.counts);
        gl.delete_buffer(self.vbo);
        gl.delete_vertex_array(self.vao);
        gl.delete_renderbuffer(self.colour);
        gl.delete_renderbuffer(self.depth);
        gl.delete_framebuffer(self.fbo);
    }
}

unsafe fn attach(
    gl: &glow::Context,
    format: u32,
    attachment: u32,
    tile: u32,
) -> Result<glow::Renderbuffer, String> {
    let rb = gl.create_renderbuffer()?;
    gl.bind_renderbuffer(glow::RENDERBUFFER, Some(rb));
    gl.renderbuffer_storage(glow::RENDERBUFFER, format, tile as i32, tile as i32);
    gl.framebuffer_renderbuffer(glow::FRAMEBUFFER, attachment, glow::RENDERBUFFER, Some(rb));
    Ok(rb)
}

/// One light's counts.
struct LightCounts {
    all: Vec<u64>,
    opaque: Vec<u64>,
    tiles: u64,
}

unsafe fn raster_in(
    ctx: &GlContext,
    world: &BakeWorld,
    config: &BakeConfig,
    options: &RasterOptions,
) -> Result<RasterResult, String> {
    let gl = &ctx.gl;
    let scene = world.scene;
    let casters = &world.casters;
    let programs = Programs::new(gl)?;
    let max_texture = gl.get_parameter_i32(glow::MAX_TEXTURE_SIZE).max(1) as usize;
    let (atlas, ground_note) = match GroundAtlas::new(scene, max_texture) {
        Ok(a) => (a, None),
        Err(why) => (
            None,
            Some(format!("below-ground test off in the raster: {why}")),
        ),
    };
    let target = Target::new(gl, options.max_tile)?;
    gl.enable(glow::DEPTH_TEST);
    gl.enable(glow::STENCIL_TEST);
    gl.disable(glow::MULTISAMPLE);
    gl.blend_func(glow::ONE, glow::ONE);
    gl.pixel_store_i32(glow::PACK_ALIGNMENT, 4);
    // CCW in the light's window (x along u, y along v, depth along u × v)
    // is a normal along the ray: a back face.
    gl.front_face(glow::CW);
    gl.cull_face(match config.face_culling {
        FaceCulling::Front => glow::FRONT,
        _ => glow::BACK,
    });
    // Zeroed counters for every tile, sized once.
    let zeros = vec![0u8; casters.len().max(1) * 4];
    gl.buffer_data_u8_slice(glow::SHADER_STORAGE_BUFFER, &zeros, glow::DYNAMIC_READ);
    let mut out = RasterResult {
        casters: Arc::clone(casters),
        masks: vec![0u32; casters.len()],
        texels: Vec::new(),
        texels_opaque: Vec::new(),
        seconds: Vec::new(),
        tiles: Vec::new(),
        ground_note,
        renderer: ctx.renderer.clone(),
        counter: options.counter,
    };
    for index in 0..config.lights.len() {
        let started = std::time::Instant::now();
        let setup = match LightSetup::new(world, config, index) {
            Ok(setup) => Some(setup),
            Err(e) if e.is_nothing_to_trace() => None,
            Err(e) => return Err(e.to_string()),
        };
        let counts = match &setup {
            Some(setup) => {
                let light = LightPass {
                    gl,
                    programs: &programs,
                    target: &target,
                    world,
                    config,
                    options,
                    setup,
                    atlas: atlas.as_ref(),
                    zeros: &zeros,
                };
                light.run()?
            }
            None => LightCounts {
                all: vec![0; casters.len()],
                opaque: vec![0; casters.len()],
                tiles: 0,
            },
        };
        for (id, (a, o)) in counts.all.iter().zip(&counts.opaque).enumerate() {
            if a + o > 0 && !casters.casters[id].receiver_only {
                out.masks[id] |= 1 << index;
            }
        }
        if gl.get_error() != glow::NO_ERROR {
            return Err(format!("OpenGL error while rasterizing light {index}"));
        }
        out.texels.push(counts.all);
        out.texels_opaque.push(counts.opaque);
        out.tiles.push(counts.tiles);
        out.seconds.push(started.elapsed().as_secs_f64());
    }
    target.delete(gl);
    programs.delete(gl);
    Ok(out)
}

/// One light ready to draw.
struct LightPass<'a> {
    gl: &'a glow::Context,
    programs: &'a Programs,
    target: &'a Target,
    world: &'a BakeWorld<'a>,
    config: &'a BakeConfig,
    options: &'a RasterOptions,
    setup: &'a LightSetup,
    atlas: Option<&'a GroundAtlas>,
    zeros: &'a [u8],
}

/// Where a tile lies in its face.
#[derive(Debug, Clone, Copy)]
struct TileAt {
    face: usize,
    x0: u32,
    y0: u32,
    w: u32,
    h: u32,
}

impl LightPass<'_> {
    unsafe fn run(&self) -> Result<LightCounts, String> {
        let gl = self.gl;
        let grid = &self.setup.grid;
        let reference = grid.reference_point();
        let geo = self.setup.reach_geometry(self.world);
        let (vertices, runs) = vertex_runs(&geo.triangles);
        gl.bind_buffer(glow::ARRAY_BUFFER, Some(self.target.vbo));
        gl.buffer_data_u8_slice(glow::ARRAY_BUFFER, bytes_of(&vertices), glow::STATIC_DRAW);
        let ground_on = match self.atlas {
            Some(atlas) => {
                upload_ground(gl, atlas, reference, self.programs, self.target.ground);
                let bias = self.config.height_bias as f32;
                self.programs
                    .set(gl, "height_bias", |u| gl.uniform_1_f32(u, bias));
                true
            }
            None => false,
        };
        let n = self.world.casters.len();
        let mut counts = LightCounts {
            all: vec![0; n],
            opaque: vec![0; n],
            tiles: 0,
        };
        let far = directional_far(grid, &geo.triangles, reference);
        let variants: &[bool] = match self.setup.passes {
            Passes::AllAndOpaque => &[false, true],
            Passes::AllOnly => &[false],
        };
        let mut queries = Vec::new();
        if self.options.counter != Counter::Atomics {
            for _ in 0..runs.len() {
                queries.push(gl.create_query()?);
            }
        }
        let draw = Draw {
            gl,
            programs: self.programs,
            casters: &self.world.casters,
            culling: self.config.face_culling != FaceCulling::None,
            ground_on,
            runs: &runs,
            queries: &queries,
        };
        let tile = self.target.tile;
        for face in 0..grid.faces() {
            let view = face_view(grid, face, (-1.0, far));
            self.set_face_uniforms(&view);
            let (w, h) = (grid.width(), grid.height());
            for y0 in (0..h).step_by(tile as usize) {
                for x0 in (0..w).step_by(tile as usize) {
                    let at = TileAt {
                        face,
                        x0,
                        y0,
                        w: tile.min(w - x0),
                        h: tile.min(h - y0),
                    };
                    let m = tile_matrix(
                        w as f64,
                        h as f64,
                        x0 as f64,
                        y0 as f64,
                        at.w as f64,
                        at.h as f64,
                    ) * view.clip_from_rel;
                    let m = m.as_mat4().to_cols_array();
                    self.programs.set(gl, "clip_from_rel", |u| {
                        gl.uniform_matrix_4_f32_slice(u, false, &m)
                    });
                    gl.viewport(0, 0, at.w as i32, at.h as i32);
                    for &opaque_only in variants {
                        let tile_counts = draw.tile(at, opaque_only, self)?;
                        let tally = if opaque_only {
                            &mut counts.opaque
                        } else {
                            &mut counts.all
                        };
                        for (t, c) in tally.iter_mut().zip(tile_counts) {
                            *t += c;
                        }
                        counts.tiles += 1;
                    }
                }
            }
        }
        for q in queries {
            gl.delete_query(q);
        }
        Ok(counts)
    }

    unsafe fn set_face_uniforms(&self, view: &FaceView) {
        let (gl, p) = (self.gl, self.programs);
        match view.perspective {
            Some((apex, near, far)) => {
                p.set(gl, "by_distance", |u| gl.uniform_1_i32(u, 1));
                let apex = apex.as_vec3();
                p.set(gl, "apex", |u| gl.uniform_3_f32(u, apex.x, apex.y, apex.z));
                p.set(gl, "near_d", |u| gl.uniform_1_f32(u, near as f32));
                let far = if far.is_finite() {
                    far as f32
                } else {
                    f32::MAX
                };
                p.set(gl, "far_d", |u| gl.uniform_1_f32(u, far));
            }
            None => p.set(gl, "by_distance", |u| gl.uniform_1_i32(u, 0)),
        }
    }
}

/// Depth range of a directional light: what the geometry spans along the
/// ray from the origin plane.
fn directional_far(
    grid: &TexelGrid,
    triangles: &[crate::trace::TraceTriangle],
    reference: DVec3,
) -> f64 {
    let o0 = grid.ray_through(0, 0.0, 0.0);
    let d = o0.direction;
    let origin_rel = o0.origin - reference;
    triangles
        .iter()
        .flat_map(|t| t.vertices.iter())
        .map(|v| (v.as_dvec3() - origin_rel).dot(d))
        .fold(1.0f64, f64::max)
        * 1.01
        + 1.0
}

/// The vertex buffer's contents and each caster's run in it (triangles
/// come in caster id order, so one run per caster).
fn vertex_runs(triangles: &[crate::trace::TraceTriangle]) -> (Vec<f32>, Vec<Run>) {
    let mut vertices: Vec<f32> = Vec::with_capacity(triangles.len() * 9);
    let mut runs: Vec<Run> = Vec::new();
    for (i, t) in triangles.iter().enumerate() {
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
    (vertices, runs)
}

/// What draws one light's runs.
struct Draw<'a> {
    gl: &'a glow::Context,
    programs: &'a Programs,
    casters: &'a CasterTable,
    culling: bool,
    ground_on: bool,
    runs: &'a [Run],
    /// One per run (empty under [`Counter::Atomics`]).
    queries: &'a [glow::Query],
}

impl Draw<'_> {
    /// Passes 1 and 2 of one tile and variant; per caster, the samples that
    /// passed, checked against the samples drawn.
    unsafe fn tile(
        &self,
        at: TileAt,
        opaque_only: bool,
        light: &LightPass,
    ) -> Result<Vec<u64>, String> {
        let counted = |r: &&Run| {
            let c = &self.casters.casters[r.caster as usize];
            !(c.receiver_only || opaque_only && c.alpha_tested)
        };
        self.pass_one(opaque_only);
        let counter = light.options.counter;
        let n = self.casters.len();
        let mut per_caster = match counter {
            Counter::Atomics | Counter::Both => self.pass_two_atomics(counted, light.zeros, n),
            Counter::Queries => self.pass_two_queries(counted, Flush::Around, n),
            Counter::QueriesUnflushed => self.pass_two_queries(counted, Flush::Never, n),
        };
        if light.options.fault == Fault::ExtraSample {
            if let Some(c) = per_caster.iter_mut().find(|c| **c > 0) {
                *c += 1;
            }
        }
        let name = match counter {
            Counter::Atomics | Counter::Both => "atomic counters",
            _ => "occlusion queries",
        };
        self.check_drawn(&per_caster, at, light, name)?;
        if counter == Counter::Both {
            self.clear(glow::COLOR_BUFFER_BIT);
            let queried = self.pass_two_queries(counted, Flush::Around, n);
            self.check_drawn(&queried, at, light, "occlusion queries")?;
            if let Some(c) = (0..n).find(|&c| queried[c] != per_caster[c]) {
                return Err(format!(
                    "caster {c}: the occlusion query counted {} samples, the atomic counter {} \
                     (light {}, {})",
                    queried[c],
                    per_caster[c],
                    light.setup.index,
                    describe_tile(at)
                ));
            }
        }
        Ok(per_caster)
    }

    unsafe fn clear(&self, bits: u32) {
        let gl = self.gl;
        gl.depth_mask(true);
        gl.stencil_mask(0xff);
        gl.color_mask(true, false, false, false);
        gl.clear_depth_f64(1.0);
        gl.clear_stencil(0);
        gl.clear_color(0.0, 0.0, 0.0, 0.0);
        gl.clear(bits);
    }

    /// Pass 1: casters write the nearest caster depth; every fragment counts
    /// in the stencil; then receiver-only instances.
    unsafe fn pass_one(&self, opaque_only: bool) {
        let gl = self.gl;
        self.clear(glow::DEPTH_BUFFER_BIT | glow::STENCIL_BUFFER_BIT | glow::COLOR_BUFFER_BIT);
        gl.use_program(Some(self.programs.draw));
        gl.color_mask(false, false, false, false);
        gl.depth_func(glow::LESS);
        gl.stencil_func(glow::ALWAYS, 0, 0xff);
        gl.stencil_op(glow::KEEP, glow::INCR, glow::INCR);
        let included =
            |r: &&Run| !(opaque_only && self.casters.casters[r.caster as usize].alpha_tested);
        let receiver = |r: &Run| self.casters.casters[r.caster as usize].receiver_only;
        for r in self.runs.iter().filter(included).filter(|r| !receiver(r)) {
            self.draw_run(self.programs.draw, r);
        }
        // Receiver-only instances are not drawn into the shadow map
        // (docs/contract.md §2): they write no depth, and count only where they are not in
        // front of the nearest caster (docs/contract.md §4), i.e. depth GEQUAL.
        gl.depth_mask(false);
        gl.depth_func(glow::GEQUAL);
        gl.stencil_op(glow::KEEP, glow::KEEP, glow::INCR);
        for r in self.runs.iter().filter(included).filter(|r| receiver(r)) {
            self.draw_run(self.programs.draw, r);
        }
    }

    /// The state of pass 2: LEQUAL against pass 1 where stencil > 1, no
    /// writes but the additive colour.
    unsafe fn pass_two_state(&self, program: glow::Program) {
        let gl = self.gl;
        gl.use_program(Some(program));
        gl.depth_mask(false);
        gl.stencil_mask(0);
        gl.depth_func(glow::LEQUAL);
        gl.stencil_func(glow::LESS, 1, 0xff);
        gl.stencil_op(glow::KEEP, glow::KEEP, glow::KEEP);
        gl.color_mask(true, false, false, false);
        gl.enable(glow::BLEND);
    }

    unsafe fn pass_two_atomics(
        &self,
        counted: impl Fn(&&Run) -> bool,
        zeros: &[u8],
        n: usize,
    ) -> Vec<u64> {
        let gl = self.gl;
        gl.buffer_sub_data_u8_slice(glow::SHADER_STORAGE_BUFFER, 0, zeros);
        self.pass_two_state(self.programs.count);
        let slot = gl.get_uniform_location(self.programs.count, "slot");
        for r in self.runs.iter().filter(counted) {
            gl.uniform_1_u32(slot.as_ref(), r.caster);
            self.draw_run(self.programs.count, r);
        }
        gl.disable(glow::BLEND);
        gl.memory_barrier(glow::BUFFER_UPDATE_BARRIER_BIT);
        let mut raw = vec![0u8; n * 4];
        gl.get_buffer_sub_data(glow::SHADER_STORAGE_BUFFER, 0, &mut raw);
        raw.chunks_exact(4)
            .map(|b| u64::from(u32::from_ne_bytes([b[0], b[1], b[2], b[3]])))
            .collect()
    }

    unsafe fn pass_two_queries(
        &self,
        counted: impl Fn(&&Run) -> bool,
        flush: Flush,
        n: usize,
    ) -> Vec<u64> {
        let gl = self.gl;
        self.pass_two_state(self.programs.draw);
        let mut per_caster = vec![0u64; n];
        let mut asked = Vec::new();
        for (r, q) in self.runs.iter().zip(self.queries) {
            if !counted(&r) {
                continue;
            }
            // Begin and end each in an empty llvmpipe scene: they are
            // binned into every bin, and a scene that fills up part-way
            // miscounts (module notes).
            if flush == Flush::Around {
                gl.flush();
            }
            gl.begin_query(glow::SAMPLES_PASSED, *q);
            self.draw_run(self.programs.draw, r);
            if flush == Flush::Around {
                gl.flush();
            }
            gl.end_query(glow::SAMPLES_PASSED);
            asked.push((r.caster, *q));
            if asked.len() >= QUERY_BATCH {
                read_queries(gl, &mut asked, &mut per_caster);
            }
        }
        read_queries(gl, &mut asked, &mut per_caster);
        gl.disable(glow::BLEND);
        per_caster
    }

    /// The per-tile self-check: the counts must add up to the samples pass
    /// 2 drew into the colour buffer.
    unsafe fn check_drawn(
        &self,
        per_caster: &[u64],
        at: TileAt,
        light: &LightPass,
        counter: &str,
    ) -> Result<(), String> {
        let gl = self.gl;
        let mut drawn = vec![0f32; at.w as usize * at.h as usize];
        gl.read_pixels(
            0,
            0,
            at.w as i32,
            at.h as i32,
            glow::RED,
            glow::FLOAT,
            glow::PixelPackData::Slice(Some(bytes_of_mut(&mut drawn))),
        );
        let samples: u64 = drawn.iter().map(|&n| n as u64).sum();
        check_tile(per_caster, samples).map_err(|counted| {
            format!(
                "the OpenGL driver's {counter} counted {counted} samples where it drew {samples} \
                 (light {} \"{}\", {}); its counts cannot be trusted (a driver bug: try another \
                 driver, e.g. a GPU's or Mesa's llvmpipe with LIBGL_ALWAYS_SOFTWARE=1)",
                light.setup.index,
                light.config.lights[light.setup.index].name,
                describe_tile(at)
            )
        })
    }

    unsafe fn draw_run(&self, program: glow::Program, r: &Run) {
        let gl = self.gl;
        let caster = &self.casters.casters[r.caster as usize];
        if self.culling && !caster.double_sided {
            gl.enable(glow::CULL_FACE);
        } else {
            gl.disable(glow::CULL_FACE);
        }
        let check = i32::from(self.ground_on && !caster.is_terrain());
        gl.uniform_1_i32(
            gl.get_uniform_location(program, "check_ground").as_ref(),
            check,
        );
        gl.draw_arrays(glow::TRIANGLES, r.first, r.count);
    }
}

/// Whether pass 2 under queries flushes before every begin and end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Flush {
    Around,
    Never,
}

fn describe_tile(at: TileAt) -> String {
    format!(
        "face {}, tile of {}×{} at texel {}, {}",
        at.face, at.w, at.h, at.x0, at.y0
    )
}

/// The per-tile self-check: `Err(total counted)` when the per-caster
/// counts do not add up to the samples drawn.
fn check_tile(per_caster: &[u64], drawn: u64) -> Result<(), u64> {
    let counted: u64 = per_caster.iter().sum();
    if counted == drawn {
        Ok(())
    } else {
        Err(counted)
    }
}

/// Reads (and forgets) the results of `asked`, adding each to its caster.
unsafe fn read_queries(
    gl: &glow::Context,
    asked: &mut Vec<(u32, glow::Query)>,
    per_caster: &mut [u64],
) {
    for (caster, q) in asked.drain(..) {
        per_caster[caster as usize] += u64::from(gl.get_query_parameter_u32(q, glow::QUERY_RESULT));
    }
}
/// Puts the ground atlas into texture units 0–3 (heights, cell flags, block
/// placement, block frame), relative to `reference`, and sets the
/// shader's ground uniforms but the bias.
unsafe fn upload_ground(
    gl: &glow::Context,
    atlas: &GroundAtlas,
    reference: DVec3,
    programs: &Programs,
    textures: [glow::Texture; 4],
) {
    let texels = GroundTexels::of(atlas, reference);
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
            bytes_of(&texels.heights),
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
            bytes_of(&texels.place),
        ),
        (
            glow::RGBA32F,
            grid_size,
            glow::RGBA,
            glow::FLOAT,
            bytes_of(&texels.frame),
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
    set_ground_uniforms(gl, atlas, reference, programs);
}

/// The f32 texels of the atlas's heights and per-chunk index, relative to
/// the upload's reference point.
struct GroundTexels {
    heights: Vec<f32>,
    /// Per chunk: the block's corner in the atlas and its cells across
    /// (−1 where the chunk has no block).
    place: Vec<f32>,
    /// Per chunk: the block's origin (x, z) and its cell spacing.
    frame: Vec<f32>,
}

impl GroundTexels {
    fn of(atlas: &GroundAtlas, reference: DVec3) -> GroundTexels {
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
        GroundTexels {
            heights,
            place,
            frame,
        }
    }
}

/// The shader's samplers for texture units 0–3 and the chunk grid's
/// uniforms (origin relative to `reference`, chunk size, chunks across).
unsafe fn set_ground_uniforms(
    gl: &glow::Context,
    atlas: &GroundAtlas,
    reference: DVec3,
    programs: &Programs,
) {
    for (unit, name) in ["heights", "cells", "block_place", "block_frame"]
        .iter()
        .enumerate()
    {
        programs.set(gl, name, |u| gl.uniform_1_i32(u, unit as i32));
    }
    let origin = (
        (f64::from(atlas.grid_min.0) * atlas.chunk_size - reference.x) as f32,
        (f64::from(atlas.grid_min.1) * atlas.chunk_size - reference.z) as f32,
    );
    programs.set(gl, "grid_origin", |u| {
        gl.uniform_2_f32(u, origin.0, origin.1)
    });
    let chunk = atlas.chunk_size as f32;
    programs.set(gl, "chunk_size", |u| gl.uniform_1_f32(u, chunk));
    let (gw, gh) = (atlas.grid_count.0 as i32, atlas.grid_count.1 as i32);
    programs.set(gl, "grid_count", |u| gl.uniform_2_i32(u, gw, gh));
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
    fn the_tile_check_fails_on_any_count_off_by_one() {
        assert_eq!(check_tile(&[3, 0, 4], 7), Ok(()));
        assert_eq!(check_tile(&[3, 1, 4], 7), Err(8));
        assert_eq!(check_tile(&[3, 0, 3], 7), Err(6));
        assert_eq!(check_tile(&[], 0), Ok(()));
    }

    #[test]
    fn tile_matrix_maps_tile_edges_to_ndc_edges() {
        // A 100-texel face, tile [40, 60): face NDC of X=40 is −0.2, of 60 is 0.2.
        let m = tile_matrix(100.0, 100.0, 40.0, 0.0, 20.0, 100.0);
        let left = m * DVec4::new(-0.2, 0.0, 0.0, 1.0);
        let right = m * DVec4::new(0.2, 0.0, 0.0, 1.0);
        assert!((left.x + 1.0).abs() < 1e-12 && (right.x - 1.0).abs() < 1e-12);
    }
}
