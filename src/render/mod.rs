//! Pictures of what the bake decided, for artists who check a bake by
//! looking rather than by reading masks (the GPU tool this replaces showed
//! its verdicts in a window; shadowcull is headless, so it draws them).
//!
//! Two views of one light's verdicts:
//! - [`light_view`]: the light's own shadow map, one pixel per texel, each
//!   coloured by the texel's front caster ([`crate::bake::trace_light::LightRays::front_hit`],
//!   the bake's own hit filter) and shaded by its distance;
//! - [`camera_view`]: a perspective picture of the whole world, each surface
//!   coloured by its caster's verdict and lit by the light (Lambert).
//!
//! The verdicts come from [`crate::bake::bake`] run for that light alone, so
//! the picture shows exactly the masks a bake writes (bit 0 here = the
//! light's bit there: lights are baked independently). Pictures are plain
//! RGB buffers (rows top to bottom); `formats::png_write` writes them. Every
//! pixel is a pure function of its position, so the bytes are the same for
//! any thread count.

mod camera;
mod light_view;

pub use camera::{camera_view, camera_view_from, CameraSpec};
pub use light_view::{
    light_view, light_view_from, light_view_in, light_view_marked, Marker, TexelMark,
    DEFAULT_MAX_LIGHT_SIZE,
};

use crate::bake::casters::Caster;
use crate::bake::setup::{BakeWorld, LightSetup, NoSetup};
use crate::bake::trace_light::CasterSet;
use crate::bake::{self, BakeConfig, BakeError, Silent};
use crate::formats::bake_settings::LightSettings;
use crate::light::GridError;

/// The colours' origin, named in every legend.
pub const PALETTE: &str =
    "Okabe-Ito (Okabe & Ito 2008): blue / orange and bluish green / reddish purple stay \
distinct with red-green colour blindness (protanopia, deuteranopia); yellow, the \
palette's lightest, marks casters without a mask";

/// Largest picture side either view draws: a 16384² RGB buffer is 800 MB.
pub const MAX_SIDE: u32 = 16384;

/// What a pixel shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Class {
    /// A model group whose bit is set for the light.
    Useful,
    /// A model group whose bit is clear (including groups outside the
    /// light's reach, which the bake never sees and so never keeps).
    Culled,
    TerrainUseful,
    TerrainCulled,
    /// A model group or terrain block whose chunk holds no `<shadow>` for
    /// it (never baked): neither useful nor culled, since the game casts
    /// its shadow for every light.
    NoMask,
    /// A group of a `castsShadow` false instance: hit, never a caster.
    ReceiverOnly,
    /// No surface (light view: no hit that counts; camera view: sky).
    Nothing,
}

impl Class {
    pub const ALL: [Class; 7] = [
        Class::Useful,
        Class::Culled,
        Class::TerrainUseful,
        Class::TerrainCulled,
        Class::NoMask,
        Class::ReceiverOnly,
        Class::Nothing,
    ];

    /// Full-brightness colour; pixels are this times a shade in (0, 1], so
    /// the hue identifies the class. Terrain gets warm tints of its own so a
    /// green or red model stands out against the ground. No mask is the
    /// palette's yellow: the lightest colour, apart from every verdict's.
    pub fn colour(self) -> [u8; 3] {
        match self {
            Class::Useful => [0, 114, 178],
            Class::Culled => [230, 159, 0],
            Class::TerrainUseful => [0, 158, 115],
            Class::TerrainCulled => [204, 121, 167],
            Class::NoMask => [240, 228, 66],
            Class::ReceiverOnly => [165, 165, 165],
            Class::Nothing => [0, 0, 0],
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            Class::Useful => "useful caster (blue)",
            Class::Culled => "culled caster (orange)",
            Class::TerrainUseful => "useful terrain (bluish green)",
            Class::TerrainCulled => "culled terrain (reddish purple)",
            Class::NoMask => "no mask, not baked (yellow)",
            Class::ReceiverOnly => "receiver-only (grey)",
            Class::Nothing => "nothing (black; camera: dark blue sky)",
        }
    }

    fn of(caster: &Caster, verdict: Verdict) -> Class {
        match (caster.receiver_only, caster.is_terrain(), verdict) {
            (true, _, _) => Class::ReceiverOnly,
            (false, _, Verdict::NoMask) => Class::NoMask,
            (false, true, Verdict::Useful) => Class::TerrainUseful,
            (false, true, Verdict::Culled) => Class::TerrainCulled,
            (false, false, Verdict::Useful) => Class::Useful,
            (false, false, Verdict::Culled) => Class::Culled,
        }
    }
}

/// What a caster's mask says for the light.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    Useful,
    Culled,
    /// The chunk file holds no mask for the caster.
    NoMask,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("no light named `{name}` in the settings; known lights: {}", known.join(", "))]
    UnknownLight { name: String, known: Vec<String> },
    #[error("the world has no geometry (no loaded model or terrain block): nothing to draw")]
    EmptyWorld,
    #[error("{0}")]
    BadCamera(String),
    #[error("picture size {width}×{height}: each side must be 1 to {MAX_SIDE} pixels")]
    BadSize { width: u32, height: u32 },
    #[error(transparent)]
    Bake(#[from] BakeError),
    #[error(transparent)]
    Grid(#[from] GridError),
}

/// The light a picture is about, and the bake's totals for it.
#[derive(Debug, Clone, PartialEq)]
pub struct LightSummary {
    pub name: String,
    pub kind: &'static str,
    pub useful_casters: usize,
    pub culled_casters: usize,
    /// Casters whose chunk holds no mask for them (only when the verdicts
    /// come from the chunk files).
    pub no_mask_casters: usize,
    pub receiver_only_groups: usize,
    /// Of the useful casters, the speedtrees without a proxy: kept for
    /// every light and drawn nowhere (they have no geometry).
    pub unmodelled_casters: usize,
    /// Every culled caster: `chunk model INDEX RESOURCE group G` or
    /// `chunk terrain`, in caster id order.
    pub culled: Vec<String>,
    /// Where the verdicts came from, for the legend.
    pub source: String,
}

/// Where a picture's verdicts come from.
#[derive(Debug, Clone, Copy)]
pub enum Source<'a> {
    /// A bake of the light alone (nothing written).
    Bake,
    /// Masks already in the chunk files (`output::masks_from_chunks`),
    /// per caster id (`None`: the chunk holds none for it), read at the
    /// light's bit.
    ChunkMasks { masks: &'a [Option<u32>], bit: u32 },
    /// The masks of a bake just made (`BakeResult::masks`, per caster id
    /// of the same scene), read at the light's bit: no light traced again
    /// for the verdicts.
    Baked { masks: &'a [u32], bit: u32 },
}

/// A rendered picture: `rgb` is `width × height × 3` bytes, rows top to
/// bottom; `classes` says what each pixel shows.
#[derive(Debug, Clone)]
pub struct Picture {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
    pub classes: Vec<Class>,
    pub light: LightSummary,
    /// How the picture was made (layout, sampling, camera), for the legend.
    pub notes: Vec<String>,
}

impl Picture {
    /// Pixels per class, in [`Class::ALL`] order.
    pub fn counts(&self) -> [u64; Class::ALL.len()] {
        let mut counts = [0u64; Class::ALL.len()];
        for class in &self.classes {
            if let Some(i) = Class::ALL.iter().position(|c| c == class) {
                counts[i] += 1;
            }
        }
        counts
    }

    /// The legend written beside the picture: light, bake totals, pixels per
    /// colour, how it was drawn, and `command` (how to make it again).
    pub fn legend(&self, command: &str) -> String {
        let mut out = format!(
            "light `{}` ({})\nbake verdicts: {} useful casters, {} culled casters, {} casters without a mask, \
             {} receiver-only groups\n\
             picture: {} × {} pixels\n\npixels per colour (RGB at full brightness):\n",
            self.light.name,
            self.light.kind,
            self.light.useful_casters,
            self.light.culled_casters,
            self.light.no_mask_casters,
            self.light.receiver_only_groups,
            self.width,
            self.height
        );
        out = out.replacen("\n", &format!(" from {}\n", self.light.source), 1);
        if self.light.unmodelled_casters > 0 {
            out = out.replacen(
                "receiver-only groups\n",
                &format!(
                    "receiver-only groups\n{} of the useful casters are speedtrees without a proxy: kept for every light, not drawn (no geometry)\n",
                    self.light.unmodelled_casters
                ),
                1,
            );
        }
        for (class, count) in Class::ALL.iter().zip(self.counts()) {
            let [r, g, b] = class.colour();
            out += &format!(
                "  {:<40} {:>3} {:>3} {:>3}  {count:>10}\n",
                class.label(),
                r,
                g,
                b
            );
        }
        out += &format!("palette: {PALETTE}\n\n");
        if self.light.no_mask_casters > 0 {
            out += "no mask: the chunk file holds no <shadow> for the caster (never baked, or \
                    placed since the last bake); the game casts its shadow for every light\n";
        }
        for note in &self.notes {
            out += note;
            out += "\n";
        }
        out += &format!(
            "\nculled casters (chunk, index, resource): {}\n",
            self.light.culled.len()
        );
        for culled in &self.light.culled {
            out += &format!("  {culled}\n");
        }
        out += &format!("\ncommand: {command}\n");
        out
    }
}

/// The index of the light called `name`, or an error listing the known ones.
pub fn find_light(lights: &[LightSettings], name: &str) -> Result<usize, RenderError> {
    lights
        .iter()
        .position(|l| l.name == name)
        .ok_or_else(|| RenderError::UnknownLight {
            name: name.to_string(),
            known: lights.iter().map(|l| l.name.clone()).collect(),
        })
}

/// The bake's verdict for light `light` of `config`: per caster, its class.
struct Verdicts {
    classes: Vec<Class>,
    light: LightSummary,
}

/// The bake's verdicts for light `light` (the bake's own per-light path on
/// the caller's world), and its setup for pictures that trace the light
/// again (`None`: the light reaches nothing, so every caster is culled).
fn verdicts(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    source: Source,
) -> Result<(Verdicts, Option<LightSetup>), RenderError> {
    let settings = config
        .lights
        .get(light)
        .ok_or_else(|| RenderError::UnknownLight {
            name: format!("#{light}"),
            known: config.lights.iter().map(|l| l.name.clone()).collect(),
        })?;
    let casters = &world.casters;
    let (useful, setup) = match LightSetup::new(world, config, light) {
        Ok(setup) => match source {
            Source::Bake => {
                let (useful, _) = bake::bake_light(world, &setup, config, &Silent, &mut Vec::new());
                (useful, Some(setup))
            }
            Source::ChunkMasks { .. } | Source::Baked { .. } => {
                (CasterSet::new(casters.len()), Some(setup))
            }
        },
        Err(nothing) if nothing.is_nothing_to_trace() => (CasterSet::new(casters.len()), None),
        Err(NoSetup::Grid(err)) => return Err(err.into()),
        Err(NoSetup::NoGeometry) => unreachable!("no geometry is nothing to trace"),
    };
    let verdict_of = |id: usize| -> Verdict {
        let useful_here = match source {
            Source::Bake => Some(useful.contains(id as u32)),
            Source::ChunkMasks { masks, bit } => masks
                .get(id)
                .copied()
                .flatten()
                .map(|mask| mask & 1u32.wrapping_shl(bit) != 0),
            Source::Baked { masks, bit } => {
                masks.get(id).map(|mask| mask & 1u32.wrapping_shl(bit) != 0)
            }
        };
        match useful_here {
            Some(true) => Verdict::Useful,
            Some(false) => Verdict::Culled,
            None => Verdict::NoMask,
        }
    };
    let classes: Vec<Class> = casters
        .casters
        .iter()
        .enumerate()
        .map(|(id, caster)| Class::of(caster, verdict_of(id)))
        .collect();
    let culled = casters
        .casters
        .iter()
        .zip(&classes)
        .filter(|(_, class)| matches!(class, Class::Culled | Class::TerrainCulled))
        .map(|(caster, _)| describe(world, caster))
        .collect();
    let count = |wanted: &[Class]| classes.iter().filter(|c| wanted.contains(c)).count();
    let verdicts = Verdicts {
        light: LightSummary {
            name: settings.name.clone(),
            kind: settings.kind.type_name(),
            useful_casters: count(&[Class::Useful, Class::TerrainUseful]),
            culled_casters: count(&[Class::Culled, Class::TerrainCulled]),
            no_mask_casters: count(&[Class::NoMask]),
            receiver_only_groups: count(&[Class::ReceiverOnly]),
            unmodelled_casters: casters.unmodelled().count(),
            culled,
            source: match source {
                Source::Bake => "a bake of this light alone (nothing written)".into(),
                Source::ChunkMasks { bit, .. } => {
                    format!("the masks in the chunk files (bit {bit}; not baked)")
                }
                Source::Baked { bit, .. } => format!("the bake's masks (bit {bit})"),
            },
        },
        classes,
    };
    Ok((verdicts, setup))
}

/// A caster for people: chunk, instance index and resource, group.
fn describe(world: &BakeWorld, caster: &Caster) -> String {
    let scene = world.scene;
    match caster.owner {
        crate::bake::casters::Owner::Group {
            instance,
            part,
            group,
        } => {
            let placed = &scene.instances[instance as usize];
            format!(
                "{} {} {} {} group {group}",
                scene.chunks[placed.chunk].name,
                placed.kind.tag(),
                placed.index,
                placed
                    .resources
                    .get(part as usize)
                    .map(|r| r.trim())
                    .unwrap_or("?")
            )
        }
        crate::bake::casters::Owner::Terrain { block } => {
            let chunk = scene
                .chunks
                .iter()
                .find(|c| c.terrain == Some(block as usize))
                .map_or("?", |c| c.name.as_str());
            format!("{chunk} terrain")
        }
        crate::bake::casters::Owner::Unmodelled { instance } => {
            let tree = &scene.instances[instance as usize];
            format!(
                "{} speedtree {} {} (no proxy)",
                scene.chunks[tree.chunk].name,
                tree.index,
                crate::scene::items::spt_of(tree)
            )
        }
    }
}

/// `colour × shade`, rounded, for `shade` in [0, 1].
fn shaded(class: Class, shade: f64) -> [u8; 3] {
    let shade = if shade.is_finite() {
        shade.clamp(0.0, 1.0)
    } else {
        1.0
    };
    class
        .colour()
        .map(|c| (c as f64 * shade).round().clamp(0.0, 255.0) as u8)
}

fn check_size(width: u32, height: u32) -> Result<(), RenderError> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(RenderError::BadSize { width, height });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::casters::Owner;

    #[test]
    fn classes_have_distinct_hues_that_survive_shading() {
        // A test (and a reader) tells classes apart by hue: no two colours
        // may be multiples of each other.
        for a in Class::ALL {
            for b in Class::ALL {
                if a == b || a == Class::Nothing || b == Class::Nothing {
                    continue;
                }
                let (ca, cb) = (a.colour().map(f64::from), b.colour().map(f64::from));
                let ratio = ca[0] / cb[0];
                let parallel =
                    (ca[1] - cb[1] * ratio).abs() < 1.0 && (ca[2] - cb[2] * ratio).abs() < 1.0;
                assert!(!parallel, "{a:?} and {b:?} differ only in brightness");
            }
        }
        assert_eq!(shaded(Class::Useful, 0.5), [0, 57, 89]);
        assert_eq!(shaded(Class::Culled, f64::NAN), Class::Culled.colour());
    }

    #[test]
    fn verdict_classes_follow_owner_and_flags() {
        let group = Caster {
            owner: Owner::Group {
                instance: 0,
                part: 0,
                group: 0,
            },
            alpha_tested: false,
            double_sided: false,
            receiver_only: false,
        };
        let terrain = Caster {
            owner: Owner::Terrain { block: 0 },
            ..group
        };
        let receiver = Caster {
            receiver_only: true,
            ..group
        };
        assert_eq!(Class::of(&group, Verdict::Useful), Class::Useful);
        assert_eq!(Class::of(&group, Verdict::Culled), Class::Culled);
        assert_eq!(Class::of(&terrain, Verdict::Useful), Class::TerrainUseful);
        assert_eq!(Class::of(&terrain, Verdict::Culled), Class::TerrainCulled);
        assert_eq!(Class::of(&receiver, Verdict::Useful), Class::ReceiverOnly);
        // Without a mask a caster is neither useful nor culled; a
        // receiver-only instance stays what it is.
        assert_eq!(Class::of(&group, Verdict::NoMask), Class::NoMask);
        assert_eq!(Class::of(&terrain, Verdict::NoMask), Class::NoMask);
        assert_eq!(Class::of(&receiver, Verdict::NoMask), Class::ReceiverOnly);
    }

    #[test]
    fn unknown_light_lists_the_known_ones() {
        let light = |name: &str| LightSettings {
            name: name.into(),
            kind: crate::formats::bake_settings::LightKind::Directional {
                direction: glam::DVec3::NEG_Y,
                texel_size: 1.0,
            },
        };
        let lights = [light("sun"), light("moon")];
        assert_eq!(find_light(&lights, "moon").unwrap(), 1);
        let message = find_light(&lights, "star").unwrap_err().to_string();
        assert!(
            message.contains("`star`") && message.contains("sun, moon"),
            "{message}"
        );
    }

    #[test]
    fn sizes_outside_the_limits_are_refused() {
        assert!(check_size(0, 10).is_err());
        assert!(check_size(10, MAX_SIDE + 1).is_err());
        assert!(check_size(1, 1).is_ok());
    }
}
