//! Placement decisions and the world's text files: where every instance goes,
//! the chunk XML, terrain, `space.settings` and the bake settings. Decisions
//! are made once into a `WorldPlan`, from which both the files and the
//! `Expected` counts are derived, so the oracle cannot drift from the output.

use super::models::Kind;
use super::xml::{f6, v3, XmlOut};
use super::Preset;
use crate::formats::terrain::{write_terrain2_cdata, HeightMap, HoleMap};
use crate::rng::{mix, Rng};

pub(crate) type M43 = [[f64; 3]; 4];

/// How an instance declares its shadow casting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Shadow {
    /// No `castsShadow` element (default true).
    Default,
    /// `<castsShadow>\ttrue\t</castsShadow>`, written out explicitly.
    ExplicitTrue,
    /// `<castsShadow>\tfalse\t</castsShadow>` (14.x form).
    ReceiverOnly,
    /// `<editorOnly><castsShadow>\tfalse\t</castsShadow></editorOnly>`.
    ReceiverOnlyLegacy,
}

impl Shadow {
    pub(crate) fn receiver_only(self) -> bool {
        matches!(self, Shadow::ReceiverOnly | Shadow::ReceiverOnlyLegacy)
    }
}

#[derive(Debug, Clone)]
pub(crate) struct Placement {
    pub parts: Vec<Kind>,
    /// Chunk-local transform, row-vector convention.
    pub transform: M43,
    /// Decided before the matrix is built; tests check the two agree.
    #[cfg_attr(not(test), allow(dead_code))]
    pub mirrored: bool,
    pub shadow: Shadow,
}

#[derive(Debug, Clone, Default)]
pub(crate) struct ChunkPlan {
    pub gx: i32,
    pub gz: i32,
    pub placements: Vec<Placement>,
    pub entity: bool,
    pub navmesh: bool,
    /// Hole-map cells (x0, z0, size) cut out of this chunk's terrain.
    pub hole: Option<(usize, usize, usize)>,
}

impl ChunkPlan {
    pub(crate) fn name(&self) -> String {
        chunk_name(self.gx, self.gz)
    }
}

pub(crate) fn chunk_name(gx: i32, gz: i32) -> String {
    format!("{:04x}{:04x}o", gx as u16, gz as u16)
}

/// The per-preset knobs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Params {
    pub name: &'static str,
    /// Inclusive grid range, same for x and z.
    pub grid: (i32, i32),
    pub chunk_size: f64,
    pub height_map_size: usize,
    /// Randomly scattered instances per chunk, on top of the showcase.
    pub scatter: usize,
    /// Tessellation factor of the catalog meshes.
    pub detail: usize,
    pub hill_height: f64,
    /// Directional light texels along the world's width.
    pub sun_texels: f64,
    /// The forest's content besides the showcase: speedtrees, their
    /// proxies in the settings, every other chunk item kind, packed chunks.
    pub forest: bool,
}

impl Params {
    pub(crate) fn of(preset: Preset) -> Params {
        match preset {
            Preset::Small => Params {
                name: "small",
                grid: (-1, 0),
                chunk_size: 50.0,
                height_map_size: 16,
                scatter: 0,
                detail: 1,
                hill_height: 3.0,
                sun_texels: 512.0,
                forest: false,
            },
            Preset::Village => Params {
                name: "village",
                grid: (-1, 1),
                chunk_size: 100.0,
                height_map_size: 32,
                scatter: 14,
                detail: 1,
                hill_height: 6.0,
                sun_texels: 512.0,
                forest: false,
            },
            Preset::Bench => Params {
                name: "bench",
                grid: (-5, 4),
                chunk_size: 100.0,
                height_map_size: 64,
                scatter: 300,
                detail: 2,
                hill_height: 10.0,
                sun_texels: 1024.0,
                forest: false,
            },
            Preset::Forest => Params {
                name: "forest",
                grid: (-1, 1),
                chunk_size: 50.0,
                height_map_size: 16,
                scatter: 0,
                detail: 1,
                hill_height: 3.0,
                sun_texels: 512.0,
                forest: true,
            },
        }
    }

    /// A world of `n` × `n` chunks at the bench's density (100 m chunks,
    /// 300 scattered instances each), 128² terrain and a 1 m-texel sun.
    pub(crate) fn bench_of_size(n: u32) -> Params {
        let n = n.max(1) as i32;
        let lo = -(n / 2);
        let grid = (lo, lo + n - 1);
        let mut params = Params {
            grid,
            height_map_size: 128,
            ..Params::of(Preset::Bench)
        };
        params.sun_texels = params.world_width();
        params
    }

    pub(crate) fn space(&self) -> String {
        format!("spaces/{}", self.name)
    }

    fn chunks_per_side(&self) -> i32 {
        self.grid.1 - self.grid.0 + 1
    }

    pub(crate) fn world_width(&self) -> f64 {
        self.chunks_per_side() as f64 * self.chunk_size
    }

    /// World x (and z) of the middle of the grid.
    pub(crate) fn center(&self) -> f64 {
        self.grid.0 as f64 * self.chunk_size + 0.5 * self.world_width()
    }
}

/// Smooth deterministic hills: value noise over world coordinates (so
/// neighbouring blocks agree on shared samples), rounded to millimetres as
/// terrain2 v4 stores heights, so placements sit on the stored values.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hills {
    seed: u64,
    amplitude: f64,
}

impl Hills {
    pub(crate) fn height(&self, x: f64, z: f64) -> f64 {
        let h = self.amplitude
            * (0.6 * self.octave(x, z, 70.0, 1)
                + 0.3 * self.octave(x, z, 29.0, 2)
                + 0.1 * self.octave(x, z, 11.0, 3));
        (h * 1000.0).round() / 1000.0
    }

    fn lattice(&self, ix: i64, iz: i64, octave: u64) -> f64 {
        let h =
            mix(self.seed
                ^ mix((ix as u64).wrapping_mul(0x9E37_79B9) ^ ((iz as u64) << 32) ^ octave));
        (h >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    fn octave(&self, x: f64, z: f64, wavelength: f64, octave: u64) -> f64 {
        let (u, v) = (x / wavelength, z / wavelength);
        let (fx, fz) = (u.floor(), v.floor());
        let (ix, iz) = (fx as i64, fz as i64);
        let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
        let (tx, tz) = (fade(u - fx), fade(v - fz));
        let a = self.lattice(ix, iz, octave);
        let b = self.lattice(ix + 1, iz, octave);
        let c = self.lattice(ix, iz + 1, octave);
        let d = self.lattice(ix + 1, iz + 1, octave);
        let top = a + (b - a) * tx;
        let bottom = c + (d - c) * tx;
        top + (bottom - top) * tz
    }
}

#[derive(Debug, Clone)]
pub(crate) struct WorldPlan {
    pub params: Params,
    pub hills: Hills,
    pub chunks: Vec<ChunkPlan>,
    /// World positions of the spot light's target and the point light.
    pub spot_target: [f64; 3],
    pub point_position: [f64; 3],
    pub seed: u64,
    /// The random stream [`scatter`] draws from, chunk after chunk.
    pub scatter_rng: Rng,
}

/// Scale · Rx(tilt) · Ry(yaw) (row-vector order: scale first), translation t.
pub(crate) fn make_transform(scale: [f64; 3], tilt: f64, yaw: f64, t: [f64; 3]) -> M43 {
    let rx = [
        [1.0, 0.0, 0.0],
        [0.0, tilt.cos(), tilt.sin()],
        [0.0, -tilt.sin(), tilt.cos()],
    ];
    let ry = [
        [yaw.cos(), 0.0, -yaw.sin()],
        [0.0, 1.0, 0.0],
        [yaw.sin(), 0.0, yaw.cos()],
    ];
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = (0..3).map(|k| rx[i][k] * ry[k][j]).sum();
        }
    }
    [
        r[0].map(|v| v * scale[0]),
        r[1].map(|v| v * scale[1]),
        r[2].map(|v| v * scale[2]),
        t,
    ]
}

pub(crate) fn det3(m: &M43) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// One hand-placed showcase item, offsets from the world centre.
struct Show {
    parts: &'static [Kind],
    offset: [f64; 2],
    yaw_deg: f64,
    scale: [f64; 3],
    tilt_deg: f64,
    shadow: Shadow,
}

const fn show(parts: &'static [Kind], offset: [f64; 2], yaw_deg: f64, scale: [f64; 3]) -> Show {
    Show {
        parts,
        offset,
        yaw_deg,
        scale,
        tilt_deg: 0.0,
        shadow: Shadow::Default,
    }
}

/// Every feature in a dozen instances around the world centre: small's whole
/// content and village's centre-piece. The spot light looks at the house and
/// the point light hangs in the tree cluster.
fn showcase() -> Vec<Show> {
    use Kind::*;
    vec![
        Show {
            shadow: Shadow::ExplicitTrue,
            ..show(&[House], [0.0, 0.0], 0.0, [1.0, 1.0, 1.0])
        },
        show(&[House], [16.0, 4.0], 20.0, [-1.0, 1.0, 1.2]),
        show(&[Tree], [-12.0, -8.0], 10.0, [1.0, 1.1, 1.0]),
        show(&[Tree], [-15.0, -4.0], 75.0, [0.9, 1.0, 0.9]),
        show(&[Tree], [-9.5, -3.0], 140.0, [-1.0, 0.9, 1.0]),
        show(&[Signpost], [5.0, -8.0], 35.0, [1.0, 1.0, 1.0]),
        show(&[Crate, Pillar], [8.0, 10.0], 15.0, [1.2, 1.0, 1.2]),
        Show {
            shadow: Shadow::ReceiverOnly,
            ..show(&[Crate], [3.0, 6.5], 5.0, [2.5, 0.3, 2.0])
        },
        Show {
            shadow: Shadow::ReceiverOnlyLegacy,
            ..show(&[Boulder], [-6.0, 5.0], 0.0, [1.0, 1.0, 1.0])
        },
        show(&[Ring], [10.0, -6.0], 45.0, [1.0, 1.3, 0.8]),
        show(&[Banner], [-3.0, -12.0], 0.0, [1.0, 1.0, 1.0]),
        Show {
            tilt_deg: 8.0,
            ..show(&[Boulder], [-18.0, 12.0], 60.0, [-1.2, 0.8, 1.5])
        },
        show(&[Pillar], [18.0, -14.0], 0.0, [1.0, 1.5, 1.0]),
    ]
}

/// Scatter weights: (kind, weight).
const SCATTER: [(Kind, u32); 8] = [
    (Kind::Boulder, 25),
    (Kind::Tree, 30),
    (Kind::Crate, 15),
    (Kind::Pillar, 10),
    (Kind::Ring, 8),
    (Kind::House, 6),
    (Kind::Banner, 3),
    (Kind::Signpost, 3),
];

fn pick_kind(rng: &mut Rng) -> Kind {
    let total: u32 = SCATTER.iter().map(|s| s.1).sum();
    let mut r = rng.below(total as usize) as u32;
    for (k, w) in SCATTER {
        if r < w {
            return k;
        }
        r -= w;
    }
    Kind::Crate
}

#[cfg(test)]
pub(crate) fn plan(preset: Preset, seed: u64) -> WorldPlan {
    let mut plan = plan_frame(Params::of(preset), seed);
    let mut rng = plan.scatter_rng.clone();
    for i in 0..plan.chunks.len() {
        let mut ch = std::mem::take(&mut plan.chunks[i]);
        scatter(&plan, &mut rng, &mut ch);
        plan.chunks[i] = ch;
    }
    plan
}

/// Everything of a world but the scattered instances, which
/// [`scatter`] adds chunk by chunk (in chunk order, from
/// [`WorldPlan::scatter_rng`]) so a large world can be written without
/// holding all its placements.
pub(crate) fn plan_frame(params: Params, seed: u64) -> WorldPlan {
    let rng = Rng::new(seed ^ 0x005E_ED0F_5A4D_0C11);
    let hills = Hills {
        seed: mix(seed.wrapping_add(1)),
        amplitude: params.hill_height,
    };
    let size = params.chunk_size;
    let (g0, g1) = params.grid;
    let mut chunks: Vec<ChunkPlan> = Vec::new();
    for gz in g0..=g1 {
        for gx in g0..=g1 {
            chunks.push(ChunkPlan {
                gx,
                gz,
                placements: Vec::new(),
                entity: false,
                navmesh: (gx + gz).rem_euclid(2) == 0,
                hole: None,
            });
        }
    }
    let index_of = |wx: f64, wz: f64| -> usize {
        let cx = ((wx / size).floor() as i32).clamp(g0, g1);
        let cz = ((wz / size).floor() as i32).clamp(g0, g1);
        ((cz - g0) * (g1 - g0 + 1) + (cx - g0)) as usize
    };
    let c = params.center();
    let ground = |wx: f64, wz: f64| hills.height(wx, wz) - 0.05;

    for s in showcase() {
        let (wx, wz) = (c + s.offset[0], c + s.offset[1]);
        let i = index_of(wx, wz);
        let Some(ch) = chunks.get_mut(i) else {
            continue;
        };
        let local = [
            wx - ch.gx as f64 * size,
            ground(wx, wz),
            wz - ch.gz as f64 * size,
        ];
        let m = make_transform(
            s.scale,
            s.tilt_deg.to_radians(),
            s.yaw_deg.to_radians(),
            local,
        );
        ch.placements.push(Placement {
            parts: s.parts.to_vec(),
            transform: m,
            mirrored: det3(&m) < 0.0,
            shadow: s.shadow,
        });
    }
    let centre_chunk = index_of(c, c);
    if let Some(ch) = chunks.get_mut(centre_chunk) {
        ch.entity = true;
    }

    // Entities on a few chunks besides the centre one; a hole in the first
    // chunk, away from the showcase.
    let n = chunks.len();
    for (i, ch) in chunks.iter_mut().enumerate() {
        if i % 4 == 3 && n > 4 {
            ch.entity = true;
        }
    }
    let hms = params.height_map_size;
    if let Some(ch) = chunks.first_mut() {
        ch.hole = Some((hms / 8, hms / 8, (hms / 8).max(2)));
    }

    let house = [c, hills.height(c, c), c];
    let (px, pz) = (c - 12.0, c - 5.0);
    WorldPlan {
        params,
        hills,
        chunks,
        spot_target: house,
        point_position: [px, hills.height(px, pz) + 9.0, pz],
        seed,
        scatter_rng: rng,
    }
}

/// Adds chunk `ch`'s randomly scattered instances.
pub(crate) fn scatter(plan: &WorldPlan, rng: &mut Rng, ch: &mut ChunkPlan) {
    let params = &plan.params;
    let size = params.chunk_size;
    let hills = &plan.hills;
    let ground = |wx: f64, wz: f64| hills.height(wx, wz) - 0.05;
    {
        for _ in 0..params.scatter {
            let kind = pick_kind(rng);
            let lx = rng.range(2.0, size - 2.0);
            let lz = rng.range(2.0, size - 2.0);
            let (wx, wz) = (lx + ch.gx as f64 * size, lz + ch.gz as f64 * size);
            let base = rng.range(0.7, 1.4);
            let mut scale = [0, 1, 2].map(|_| base * rng.range(0.8, 1.25));
            let mirrored = rng.chance(0.15);
            if mirrored {
                scale[0] = -scale[0];
            }
            let tilt = if matches!(kind, Kind::Boulder | Kind::Crate) {
                rng.range(-10.0, 10.0).to_radians()
            } else {
                0.0
            };
            let yaw = rng.range(0.0, std::f64::consts::TAU);
            let shadow = match rng.below(100) {
                0..=3 => Shadow::ReceiverOnly,
                4 => Shadow::ReceiverOnlyLegacy,
                5..=9 => Shadow::ExplicitTrue,
                _ => Shadow::Default,
            };
            let parts = if rng.chance(0.03) {
                vec![Kind::Crate, Kind::Pillar]
            } else {
                vec![kind]
            };
            let m = make_transform(scale, tilt, yaw, [lx, ground(wx, wz), lz]);
            ch.placements.push(Placement {
                parts,
                transform: m,
                mirrored,
                shadow,
            });
        }
    }
}

pub(crate) fn chunk_xml(ch: &ChunkPlan, rng_seed: u64) -> Vec<u8> {
    let name = ch.name();
    let mut x = XmlOut::new("root");
    x.open("waypointGenerationTime");
    x.leaf("hi", "0");
    x.leaf("lo", "0");
    x.close();
    for p in &ch.placements {
        x.open("model");
        if p.shadow == Shadow::ReceiverOnlyLegacy {
            // Real chunks put editorOnly before resource at times.
            x.open("editorOnly");
            x.leaf("castsShadow", "false");
            x.leaf("hidden", "false");
            x.leaf("frozen", "false");
            x.close();
        }
        for k in &p.parts {
            x.leaf("resource", &k.resource());
        }
        x.transform(&p.transform);
        match p.shadow {
            Shadow::ExplicitTrue => x.leaf("castsShadow", "true"),
            Shadow::ReceiverOnly => x.leaf("castsShadow", "false"),
            Shadow::Default | Shadow::ReceiverOnlyLegacy => {}
        }
        x.leaf("reflectionVisible", "false");
        x.close();
    }
    x.open("terrain");
    x.open("editorOnly");
    x.leaf("hidden", "false");
    x.leaf("frozen", "false");
    x.close();
    x.empty("metaData");
    x.leaf("resource", &format!("{name}.cdata/terrain2"));
    x.close();
    if ch.entity {
        let mut r = Rng::new(mix(rng_seed ^ ((ch.gx as u64) << 20) ^ ch.gz as u64));
        let g = r.next_u64();
        let g2 = r.next_u64();
        x.open("entity");
        x.open("editorOnly");
        x.leaf("hidden", "false");
        x.leaf("frozen", "false");
        x.close();
        x.empty("metaData");
        x.leaf(
            "guid",
            &format!(
                "{:08X}.{:08X}.{:08X}.{:08X}",
                g >> 32,
                g & 0xFFFF_FFFF,
                g2 >> 32,
                g2 & 0xFFFF_FFFF
            ),
        );
        x.leaf("type", "TeleportPoint");
        x.transform(&[
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [r.range(5.0, 45.0), 1.0, r.range(5.0, 45.0)],
        ]);
        x.leaf("clientOnly", "false");
        x.open("properties");
        x.leaf("label", &format!("gen_{name}"));
        x.empty("patrolPathNode");
        x.close();
        x.empty("backLinks");
        x.close();
    }
    if ch.navmesh {
        x.open("worldNavmesh");
        x.leaf("resource", &format!("{name}.cdata/worldNavmesh"));
        x.close();
    }
    x.finish()
}

/// The terrain2 block of a chunk: heightMapSize + 1 samples over 0..size
/// plus 2 border samples each side.
pub(crate) fn height_map(plan: &WorldPlan, ch: &ChunkPlan) -> HeightMap {
    let hms = plan.params.height_map_size;
    let w = hms + 5;
    let spacing = plan.params.chunk_size / hms as f64;
    let (ox, oz) = (
        ch.gx as f64 * plan.params.chunk_size,
        ch.gz as f64 * plan.params.chunk_size,
    );
    let mut heights = Vec::with_capacity(w * w);
    for z in 0..w {
        for xi in 0..w {
            let wx = ox + (xi as f64 - 2.0) * spacing;
            let wz = oz + (z as f64 - 2.0) * spacing;
            heights.push(plan.hills.height(wx, wz) as f32);
        }
    }
    HeightMap {
        width: w,
        height: w,
        heights,
    }
}

/// Hole map at one cell per height-map cell (`holeMapSize` = heightMapSize).
pub(crate) fn hole_map(plan: &WorldPlan, ch: &ChunkPlan) -> Option<HoleMap> {
    let (x0, z0, n) = ch.hole?;
    let hms = plan.params.height_map_size;
    let mut holes = vec![false; hms * hms];
    for z in z0..(z0 + n).min(hms) {
        for x in x0..(x0 + n).min(hms) {
            holes[z * hms + x] = true;
        }
    }
    Some(HoleMap {
        width: hms,
        height: hms,
        holes,
    })
}

pub(crate) fn terrain_cdata(plan: &WorldPlan, ch: &ChunkPlan) -> Vec<u8> {
    let grid = height_map(plan, ch);
    let holes = hole_map(plan, ch);
    write_terrain2_cdata(&grid, holes.as_ref())
}

pub(crate) fn space_settings(p: &Params) -> Vec<u8> {
    // Bounds are inclusive grid indices; Y here is the grid z.
    let mut x = XmlOut::new("space.settings");
    x.open("bounds");
    x.leaf("minX", &p.grid.0.to_string());
    x.leaf("maxX", &p.grid.1.to_string());
    x.leaf("minY", &p.grid.0.to_string());
    x.leaf("maxY", &p.grid.1.to_string());
    x.close();
    x.leaf("chunkSize", &f6(p.chunk_size));
    x.leaf("farPlane", &f6(1000.0));
    x.open("terrain");
    x.leaf("version", "200");
    x.leaf("heightMapSize", &p.height_map_size.to_string());
    x.leaf("normalMapSize", &p.height_map_size.to_string());
    x.leaf("holeMapSize", &p.height_map_size.to_string());
    x.close();
    x.finish()
}

pub(crate) fn bake_settings(plan: &WorldPlan) -> Vec<u8> {
    let p = &plan.params;
    let mut x = XmlOut::new("shadowcull");
    x.open("resPaths");
    x.leaf("path", ".");
    x.close();
    x.leaf("space", &p.space());
    x.leaf("faceCulling", "back");
    x.leaf("heightBias", &f6(0.05));
    x.leaf("tieEpsilon", &f6(0.0001));
    x.open("lights");

    x.open("light");
    x.leaf("name", "sun");
    x.leaf("type", "directional");
    x.leaf("direction", &v3([-0.3, -1.0, 0.2]));
    x.leaf("texelSize", &f6(p.world_width() / p.sun_texels));
    x.close();

    let t = plan.spot_target;
    x.open("light");
    x.leaf("name", "spot");
    x.leaf("type", "spot");
    x.leaf("position", &v3([t[0] - 2.5, t[1] + 25.0, t[2] - 1.5]));
    x.leaf("direction", &v3([0.1, -1.0, 0.06]));
    x.leaf("fov", &f6(60.0));
    x.leaf("near", &f6(0.1));
    x.leaf("far", &f6(80.0));
    x.leaf("resolution", "512");
    x.close();

    x.open("light");
    x.leaf("name", "point");
    x.leaf("type", "point");
    x.leaf("position", &v3(plan.point_position));
    x.leaf("near", &f6(0.1));
    x.leaf("far", &f6(30.0));
    x.leaf("resolution", "256");
    x.close();

    x.close();
    x.finish()
}
