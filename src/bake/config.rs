//! What a bake is asked to do: the settings file's values after the
//! command line's overrides. Its own file because every part of the bake
//! reads it while the bake's root (`bake/mod.rs`) uses those parts, so
//! it sits below them all.

use crate::formats::bake_settings::{FaceCulling, LightKind, LightSettings};
use crate::formats::partial;

/// What to bake (the settings file's values after command-line overrides).
#[derive(Debug, Clone)]
pub struct BakeConfig {
    pub face_culling: FaceCulling,
    /// Metres: a non-terrain hit more than this below the terrain surface is
    /// ignored.
    pub height_bias: f64,
    /// Metres along a ray: the tie tolerance of docs/contract.md §4.
    pub tie_epsilon: f64,
    pub lights: Vec<LightSettings>,
    /// Trace every ray against every triangle instead of the BVH (the
    /// oracle; slow).
    pub brute_force: bool,
    /// Rays per texel side: 1 traces texel centres, k a k×k pattern of
    /// sub-texel centres (the same rays as a k× denser grid).
    pub supersample: u32,
    /// Refinement: rays aimed at this many points of every caster's own
    /// surface that the grid did not prove useful (0: off).
    pub refine_samples: u32,
    /// Refinement's footprint lattice: rays per texel side at which the
    /// light-space footprint of every caster the grid did not prove useful
    /// is sampled (0: off). See [`super::refine`].
    pub refine_density: u32,
    /// What a texel of the grid pass stands for: its centre ray, or every
    /// ray of its beam.
    pub grid_mode: GridMode,
    /// The filter margin in texels (`--filter-radius`): 0 is docs/contract.md §4's
    /// rule; K keeps a caster front-most at a texel when a surface lies
    /// behind its depth at a texel up to K away (PCF). See
    /// [`super::filter_margin`].
    pub filter_radius: u32,
    /// Every light's grid moved by this sub-texel amount (texel units, see
    /// `TexelGrid::with_offset`): the sweep's offset references and the
    /// tests bake at other placements of the game's shadow map.
    pub grid_offset: (f64, f64),
    /// Per light, its bit in the masks (`<bit>`); empty or short: a light's
    /// bit is its position. See [`BakeConfig::bit`].
    pub bits: Vec<u32>,
}

/// What a texel of the grid pass stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GridMode {
    /// One ray through the texel's centre (k×k with supersampling): docs/contract.md §4.
    #[default]
    Centres,
    /// The texel's whole beam (`--conservative`): a caster is kept whenever
    /// some placement of the shadow-map grid at this texel size could make
    /// it useful. See [`super::grid_pass`] and [`super::texel_beam`].
    Conservative,
}

impl BakeConfig {
    /// Refinement follows the grid (`--refine`).
    pub fn refines(&self) -> bool {
        self.refine_samples > 0 || self.refine_density > 0
    }

    /// The settings file's values; no supersampling, no refinement.
    pub fn from_settings(settings: &crate::formats::bake_settings::BakeSettings) -> BakeConfig {
        BakeConfig {
            face_culling: settings.face_culling,
            height_bias: settings.height_bias,
            tie_epsilon: settings.tie_epsilon,
            lights: settings.lights.clone(),
            brute_force: false,
            supersample: 1,
            refine_samples: 0,
            refine_density: 0,
            grid_mode: GridMode::Centres,
            filter_radius: 0,
            grid_offset: (0.0, 0.0),
            bits: settings.bits.clone(),
        }
    }

    /// Light `index`'s bit in every mask.
    pub fn bit(&self, index: usize) -> u32 {
        self.bits.get(index).copied().unwrap_or(index as u32)
    }

    /// The bits of every light this config bakes: the bits a bake replaces
    /// (every other bit of an existing mask is kept).
    pub fn baked_bits(&self) -> u32 {
        (0..self.lights.len()).fold(0, |bits, i| bits | 1u32.wrapping_shl(self.bit(i)))
    }

    /// Only the named lights (each keeps its bit). Errors name the unknown
    /// ones and list the lights there are.
    pub fn select_lights(&self, names: &[String]) -> Result<BakeConfig, String> {
        let unknown: Vec<&str> = names
            .iter()
            .filter(|n| !self.lights.iter().any(|l| &l.name == *n))
            .map(String::as_str)
            .collect();
        if !unknown.is_empty() {
            return Err(format!(
                "no light named {} in the settings file; its lights are {}",
                unknown
                    .iter()
                    .map(|n| format!("`{n}`"))
                    .collect::<Vec<_>>()
                    .join(", "),
                self.lights
                    .iter()
                    .map(|l| format!("`{}`", l.name))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        let keep: Vec<usize> = (0..self.lights.len())
            .filter(|&i| names.contains(&self.lights[i].name))
            .collect();
        Ok(BakeConfig {
            lights: keep.iter().map(|&i| self.lights[i].clone()).collect(),
            bits: keep.iter().map(|&i| self.bit(i)).collect(),
            ..self.clone()
        })
    }
}

impl Default for BakeConfig {
    /// docs/contract.md §3 defaults and no lights.
    fn default() -> Self {
        BakeConfig {
            face_culling: FaceCulling::Back,
            height_bias: 0.05,
            tie_epsilon: 1e-4,
            lights: Vec::new(),
            brute_force: false,
            supersample: 1,
            refine_samples: 0,
            refine_density: 0,
            grid_mode: GridMode::Centres,
            filter_radius: 0,
            grid_offset: (0.0, 0.0),
            bits: Vec::new(),
        }
    }
}

/// The settings a grid answer depends on (a shard's, a cached cell's), one (key, value) each: keys
/// are the settings file's element paths (`lights/light[0]/texelSize`) or
/// the flags (`--supersample`), values as written, so a difference reads as
/// the element and its two values.
pub fn settings_lines(config: &BakeConfig) -> Vec<(String, String)> {
    let v3 = |v: glam::DVec3| format!("{} {} {}", v.x, v.y, v.z);
    let mut lines = vec![
        (
            "shadowcull".to_string(),
            format!(
                "{} (partial format {})",
                env!("CARGO_PKG_VERSION"),
                partial::VERSION
            ),
        ),
        ("faceCulling".into(), config.face_culling.name().into()),
        ("heightBias".into(), config.height_bias.to_string()),
        ("tieEpsilon".into(), config.tie_epsilon.to_string()),
        (
            "--supersample".into(),
            config.supersample.max(1).to_string(),
        ),
        ("--brute-force".into(), config.brute_force.to_string()),
        (
            "--conservative".into(),
            (config.grid_mode == GridMode::Conservative).to_string(),
        ),
        ("--filter-radius".into(), config.filter_radius.to_string()),
        (
            "grid offset".into(),
            format!("{} {}", config.grid_offset.0, config.grid_offset.1),
        ),
        ("lights".into(), config.lights.len().to_string()),
    ];
    for (index, light) in config.lights.iter().enumerate() {
        let key = |name: &str| format!("lights/light[{index}]/{name}");
        lines.push((key("name"), light.name.clone()));
        lines.push((key("type"), light.kind.type_name().into()));
        let values: Vec<(&str, String)> = match &light.kind {
            LightKind::Directional {
                direction,
                texel_size,
            } => vec![
                ("direction", v3(*direction)),
                ("texelSize", texel_size.to_string()),
            ],
            LightKind::Spot {
                position,
                direction,
                fov_degrees,
                near,
                far,
                resolution,
            } => vec![
                ("position", v3(*position)),
                ("direction", v3(*direction)),
                ("fov", fov_degrees.to_string()),
                ("near", near.to_string()),
                ("far", far.to_string()),
                ("resolution", resolution.to_string()),
            ],
            LightKind::Point {
                position,
                near,
                far,
                resolution,
            } => vec![
                ("position", v3(*position)),
                ("near", near.to_string()),
                ("far", far.to_string()),
                ("resolution", resolution.to_string()),
            ],
        };
        lines.extend(values.into_iter().map(|(name, value)| (key(name), value)));
    }
    lines
}
