//! The bake settings file (docs/contract.md §3): which world to read, how to filter hits
//! and which lights to bake. Every subcommand reads it, and the command line
//! may override its values afterwards, so this module only turns the XML tree
//! into checked values; it reads no file itself.
//!
//! Everything a light needs to be baked is validated here, so a bad file
//! fails before any work, with the element at fault named.

pub use super::speedtree_proxies::{
    CrownShape, ParametricTree, Proxy, ProxyRule, SpeedTreeProxies, SptPattern,
};
use super::Section;
use crate::error::FormatError;
use glam::DVec3;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// The shadow-caster mask of an instance is 32 bits, one per light.
pub const MAX_LIGHTS: usize = 32;
pub const DEFAULT_HEIGHT_BIAS: f64 = 0.05;
pub const DEFAULT_TIE_EPSILON: f64 = 1e-4;
/// Largest shadow map side accepted (a 65536² map is already 4 G rays).
pub const MAX_RESOLUTION: u32 = 65536;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FaceCulling {
    /// Hits on back faces are ignored unless the group is double-sided.
    #[default]
    Back,
    Front,
    None,
}

impl FaceCulling {
    /// The settings-file (and command-line) spelling, case-insensitive.
    pub fn from_name(name: &str) -> Option<FaceCulling> {
        match name.to_ascii_lowercase().as_str() {
            "back" => Some(FaceCulling::Back),
            "front" => Some(FaceCulling::Front),
            "none" => Some(FaceCulling::None),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            FaceCulling::Back => "back",
            FaceCulling::Front => "front",
            FaceCulling::None => "none",
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct BakeSettings {
    /// Resource roots in search order; relative ones are joined to the
    /// settings file's folder.
    pub res_paths: Vec<PathBuf>,
    /// The space folder as a resource name (e.g. `spaces/arctic`).
    pub space: String,
    pub face_culling: FaceCulling,
    /// Metres; see docs/contract.md §4 (below-ground test).
    pub height_bias: f64,
    /// Metres along a ray; see docs/contract.md §4 (front-set tie tolerance).
    pub tie_epsilon: f64,
    /// In file order.
    pub lights: Vec<LightSettings>,
    /// Per light (same order): its bit in every mask, `<bit>` or its
    /// position in the file. Distinct, each below [`MAX_LIGHTS`].
    pub bits: Vec<u32>,
    /// `<speedtrees>`: the proxy geometry of SpeedTree placements.
    pub speedtrees: SpeedTreeProxies,
    /// `<unmodelledCasters>`: what a strict bake does with casters it
    /// cannot model (speedtrees without a proxy).
    pub unmodelled_casters: UnmodelledCasters,
    /// Elements the file holds that no setting reads (a typo such as
    /// `<heightBais>`): the caller decides (a strict bake refuses them,
    /// docs/contract.md §3), so every value here is read as if they were
    /// absent.
    pub unknown: Vec<UnknownElement>,
}

/// An element of the settings file that nothing reads.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownElement {
    /// Slash-separated path from the root, e.g. `shadowcull/heightBais`.
    pub path: String,
    /// Byte offset of its start tag (text XML) or its data (packed XML).
    pub offset: usize,
    /// What the parent may hold instead.
    pub known: &'static [&'static str],
    /// The valid name closest to it (a misspelling), if one is close.
    pub suggestion: Option<&'static str>,
    /// Line and column in a text file (set by the reader that has the bytes).
    pub position: Option<crate::error::TextPosition>,
}

impl UnknownElement {
    fn new(path: &str, offset: usize, known: &'static [&'static str]) -> UnknownElement {
        let tag = path.rsplit('/').next().unwrap_or(path);
        UnknownElement {
            path: path.to_string(),
            offset,
            known,
            suggestion: closest_name(tag, known),
            position: None,
        }
    }

    /// `line:column` in a text file, else `byte N`.
    pub fn location(&self) -> String {
        match self.position {
            Some(p) => p.to_string(),
            None => format!("byte {}", self.offset),
        }
    }

    /// `unknown element <heightBais> (shadowcull/heightBais)`.
    pub fn describe(&self) -> String {
        let tag = self.path.rsplit('/').next().unwrap_or(&self.path);
        format!("unknown element <{tag}> ({})", self.path)
    }

    /// `did you mean <heightBias>?`, or every name valid there when none
    /// is close.
    pub fn hint(&self) -> String {
        match self.suggestion {
            Some(name) => format!("did you mean <{name}>?"),
            None => format!("expected one of {}", self.known.join(", ")),
        }
    }

    /// What is wrong and what may be meant: [`describe`](Self::describe)
    /// and [`hint`](Self::hint).
    pub fn reason(&self) -> String {
        format!("{}; {}", self.describe(), self.hint())
    }
}

impl std::fmt::Display for UnknownElement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.location(), self.reason())
    }
}

/// The name of `known` nearest `name` by edit distance (case ignored, a
/// swap of neighbours one edit), when it is close enough to be a
/// misspelling of it: at most one edit per three characters, at least
/// one. The first of equally near names wins.
fn closest_name(name: &str, known: &'static [&'static str]) -> Option<&'static str> {
    let lower = name.to_lowercase();
    let allowed = (lower.chars().count() / 3).max(1);
    known
        .iter()
        .map(|&candidate| (edit_distance(&lower, &candidate.to_lowercase()), candidate))
        .filter(|&(distance, _)| distance <= allowed)
        .min_by_key(|&(distance, _)| distance)
        .map(|(_, candidate)| candidate)
}

/// Edits (insert, delete, replace, swap two neighbours) that turn `a` into
/// `b`: the optimal string alignment distance, by characters.
fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    // Rows i - 2, i - 1 and i of the table: distance of a[..i] to b[..j].
    let mut before: Vec<usize> = vec![0; b.len() + 1];
    let mut previous: Vec<usize> = (0..=b.len()).collect();
    let mut current: Vec<usize> = vec![0; b.len() + 1];
    for i in 1..=a.len() {
        current[0] = i;
        for j in 1..=b.len() {
            let replace = usize::from(a[i - 1] != b[j - 1]);
            let mut best = (previous[j] + 1)
                .min(current[j - 1] + 1)
                .min(previous[j - 1] + replace);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                best = best.min(before[j - 2] + 1);
            }
            current[j] = best;
        }
        std::mem::swap(&mut before, &mut previous);
        std::mem::swap(&mut previous, &mut current);
    }
    previous[b.len()]
}

/// The elements each level of the settings file may hold.
const ROOT_TAGS: &[&str] = &[
    "resPaths",
    "space",
    "faceCulling",
    "heightBias",
    "tieEpsilon",
    "lights",
    "speedtrees",
    "unmodelledCasters",
];
const RES_PATHS_TAGS: &[&str] = &["path"];
const LIGHTS_TAGS: &[&str] = &["light"];
const LIGHT_TAGS: &[&str] = &[
    "name",
    "type",
    "bit",
    "direction",
    "texelSize",
    "position",
    "fov",
    "near",
    "far",
    "resolution",
];

#[derive(Debug, Clone, PartialEq)]
pub struct LightSettings {
    /// `<name>`, or `light{i}` with `i` the light's index.
    pub name: String,
    pub kind: LightKind,
}

/// Directions are normalised here (the file need not); every value is finite
/// and in range.
#[derive(Debug, Clone, PartialEq)]
pub enum LightKind {
    Directional {
        direction: DVec3,
        /// Metres between ray centres, perpendicular to the direction.
        texel_size: f64,
    },
    Spot {
        position: DVec3,
        direction: DVec3,
        /// Full opening angle, in (0, 180).
        fov_degrees: f64,
        near: f64,
        far: f64,
        resolution: u32,
    },
    Point {
        position: DVec3,
        near: f64,
        far: f64,
        /// Side of each of the six cube faces.
        resolution: u32,
    },
}

impl LightKind {
    /// The settings-file spelling of the type, as used in reports.
    pub fn type_name(&self) -> &'static str {
        match self {
            LightKind::Directional { .. } => "directional",
            LightKind::Spot { .. } => "spot",
            LightKind::Point { .. } => "point",
        }
    }
}

/// The settings file at `path`, from its bytes: `path` names it in errors
/// (with line and column), and relative paths in it are taken relative to
/// its folder.
pub fn from_bytes(bytes: &[u8], path: &Path) -> crate::Result<BakeSettings> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let mut settings = super::parse_data_section(bytes)
        .and_then(|root| parse(&root, dir))
        .map_err(|e| e.in_source(path, bytes))?;
    for unknown in &mut settings.unknown {
        unknown.position = super::text_position(bytes, unknown.offset as u64);
    }
    Ok(settings)
}

/// Reads the settings tree of a file in folder `settings_dir`.
pub fn parse(root: &Section, settings_dir: &Path) -> Result<BakeSettings, FormatError> {
    let res_section = root.required("resPaths")?;
    let res_paths = parse_res_paths(res_section, settings_dir)?;

    let space_section = root.required("space")?;
    if space_section.value.is_empty() {
        return Err(space_section.error("empty <space>; give the space folder, e.g. spaces/arctic"));
    }
    let space = space_section.value.clone();

    let face_culling = match root.child("faceCulling") {
        None => FaceCulling::default(),
        Some(s) => FaceCulling::from_name(&s.value).ok_or_else(|| {
            s.error(format!(
                "unknown face culling `{}`; expected back, front or none",
                s.value
            ))
        })?,
    };
    let height_bias = optional_non_negative(root, "heightBias", DEFAULT_HEIGHT_BIAS)?;
    let tie_epsilon = optional_non_negative(root, "tieEpsilon", DEFAULT_TIE_EPSILON)?;

    let mut unknown = Vec::new();
    unknown_children(root, ROOT_TAGS, &mut unknown);
    unknown_children(res_section, RES_PATHS_TAGS, &mut unknown);
    let (lights, bits) = match root.child("lights") {
        Some(lights_section) => parse_lights(lights_section, &mut unknown)?,
        None => (Vec::new(), Vec::new()),
    };
    let speedtrees = match root.child("speedtrees") {
        Some(section) => parse_speedtrees(section, &mut unknown)?,
        None => SpeedTreeProxies::default(),
    };
    let unmodelled_casters = match root.child("unmodelledCasters") {
        None => UnmodelledCasters::default(),
        Some(s) => UnmodelledCasters::from_name(&s.value).ok_or_else(|| {
            s.error(format!(
                "unknown <unmodelledCasters> `{}`; expected fail or keep",
                s.value
            ))
        })?,
    };

    Ok(BakeSettings {
        res_paths,
        space,
        face_culling,
        height_bias,
        tie_epsilon,
        lights,
        bits,
        speedtrees,
        unmodelled_casters,
        unknown,
    })
}

/// `<resPaths>`: at least one folder, relative ones joined to
/// `settings_dir`.
fn parse_res_paths(
    res_section: &Section,
    settings_dir: &Path,
) -> Result<Vec<PathBuf>, FormatError> {
    let mut res_paths = Vec::new();
    for path in res_section.children_named("path") {
        if path.value.is_empty() {
            return Err(path.error("empty resource path; give a folder or remove the element"));
        }
        let p = PathBuf::from(&path.value);
        let joined = if p.is_absolute() {
            p
        } else {
            settings_dir.join(p)
        };
        // `.` components only clutter messages (`world/./spaces/x`).
        let cleaned: PathBuf = joined
            .components()
            .filter(|c| !matches!(c, std::path::Component::CurDir))
            .collect();
        res_paths.push(if cleaned.as_os_str().is_empty() {
            PathBuf::from(".")
        } else {
            cleaned
        });
    }
    if res_paths.is_empty() {
        return Err(
            res_section.error("no <path> in <resPaths>; give at least one resource root folder")
        );
    }
    Ok(res_paths)
}

/// `<lights>`: each light and its bit, in file order (at most
/// [`MAX_LIGHTS`], names and bits distinct); elements nothing reads are
/// added to `unknown`.
fn parse_lights(
    lights_section: &Section,
    unknown: &mut Vec<UnknownElement>,
) -> Result<(Vec<LightSettings>, Vec<u32>), FormatError> {
    unknown_children(lights_section, LIGHTS_TAGS, unknown);
    let count = lights_section.children_named("light").count();
    if count > MAX_LIGHTS {
        return Err(lights_section.error(format!(
            "{count} lights; at most {MAX_LIGHTS} can be baked (the caster mask has 32 bits): \
             split them over several settings files"
        )));
    }
    let mut lights = Vec::new();
    let mut bits = Vec::new();
    let mut names = HashSet::new();
    let mut owners: Vec<Option<String>> = vec![None; MAX_LIGHTS];
    for (i, light) in lights_section.children_named("light").enumerate() {
        unknown_children(light, LIGHT_TAGS, unknown);
        let parsed = parse_light(light, i)?;
        if !names.insert(parsed.name.clone()) {
            return Err(light.error(format!(
                "duplicate light name `{}`; light names must be unique",
                parsed.name
            )));
        }
        let bit = light_bit(light, i)?;
        if let Some(owner) = &owners[bit as usize] {
            return Err(light.error(format!(
                "light `{}` and light `{owner}` both use bit {bit}; give each light its own <bit> (0..{})",
                parsed.name,
                MAX_LIGHTS - 1
            )));
        }
        owners[bit as usize] = Some(parsed.name.clone());
        bits.push(bit);
        lights.push(parsed);
    }
    Ok((lights, bits))
}

/// `<bit>`, or the light's position in the file.
fn light_bit(light: &Section, index: usize) -> Result<u32, FormatError> {
    let Some(s) = light.child("bit") else {
        return Ok(index as u32);
    };
    let v = s.as_i64()?;
    match u32::try_from(v) {
        Ok(bit) if (bit as usize) < MAX_LIGHTS => Ok(bit),
        _ => Err(s.error(format!(
            "<bit> must be between 0 and {} (the mask has {MAX_LIGHTS} bits), found {v}",
            MAX_LIGHTS - 1
        ))),
    }
}

/// What a strict bake does with casters it cannot model (speedtrees
/// without a proxy): `<unmodelledCasters>` (docs/contract.md §3). Either
/// way such a caster is kept for every light and never occludes; the
/// policy only says whether that is an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum UnmodelledCasters {
    /// A strict bake (and `plan`, `inspect`) fails, listing them.
    #[default]
    Fail,
    /// They are baked kept for every light; every output still lists them.
    Keep,
}

impl UnmodelledCasters {
    /// The settings-file spelling, case-insensitive.
    pub fn from_name(name: &str) -> Option<UnmodelledCasters> {
        match name.to_ascii_lowercase().as_str() {
            "fail" => Some(UnmodelledCasters::Fail),
            "keep" => Some(UnmodelledCasters::Keep),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            UnmodelledCasters::Fail => "fail",
            UnmodelledCasters::Keep => "keep",
        }
    }
}

/// Adds the children of `section` whose tags are not in `known` to `out`.
fn unknown_children(
    section: &Section,
    known: &'static [&'static str],
    out: &mut Vec<UnknownElement>,
) {
    for child in &section.children {
        if !known.contains(&child.name.as_str()) {
            out.push(UnknownElement::new(&child.path, child.span.start, known));
        }
    }
}

fn optional_non_negative(root: &Section, tag: &str, default: f64) -> Result<f64, FormatError> {
    match root.child(tag) {
        None => Ok(default),
        Some(s) => {
            let v = s.as_f64()?;
            if v.is_finite() && v >= 0.0 {
                Ok(v)
            } else {
                Err(s.error(format!("<{tag}> must be a finite number >= 0, found {v}")))
            }
        }
    }
}

fn parse_light(light: &Section, index: usize) -> Result<LightSettings, FormatError> {
    let name = match light.child("name") {
        Some(n) if !n.value.is_empty() => n.value.clone(),
        Some(n) => return Err(n.error("empty light <name>; remove it to get the default")),
        None => format!("light{index}"),
    };
    let type_section = light.required("type")?;
    let kind = match type_section.value.to_ascii_lowercase().as_str() {
        "directional" => LightKind::Directional {
            direction: direction(light)?,
            texel_size: positive(light, "texelSize")?,
        },
        "spot" => {
            let fov = light.required("fov")?;
            let fov_degrees = fov.as_f64()?;
            if !(fov_degrees > 0.0 && fov_degrees < 180.0) {
                return Err(fov.error(format!(
                    "spot light fov must be in (0, 180) degrees, found {fov_degrees}"
                )));
            }
            let (near, far) = near_far(light)?;
            LightKind::Spot {
                position: position(light)?,
                direction: direction(light)?,
                fov_degrees,
                near,
                far,
                resolution: resolution(light)?,
            }
        }
        "point" => {
            let (near, far) = near_far(light)?;
            LightKind::Point {
                position: position(light)?,
                near,
                far,
                resolution: resolution(light)?,
            }
        }
        other => {
            return Err(type_section.error(format!(
                "unknown light type `{other}`; expected directional, spot or point"
            )))
        }
    };
    Ok(LightSettings { name, kind })
}

fn direction(light: &Section) -> Result<DVec3, FormatError> {
    let s = light.required("direction")?;
    let d = s.as_vec3()?;
    let length = d.length();
    if !d.is_finite() || length == 0.0 || !length.is_finite() {
        return Err(s.error(format!(
            "light direction must be a finite, non-zero vector, found {} {} {}",
            d.x, d.y, d.z
        )));
    }
    Ok(d / length)
}

fn position(light: &Section) -> Result<DVec3, FormatError> {
    let s = light.required("position")?;
    let p = s.as_vec3()?;
    if !p.is_finite() {
        return Err(s.error("light position must be finite"));
    }
    Ok(p)
}

fn positive(light: &Section, tag: &str) -> Result<f64, FormatError> {
    let s = light.required(tag)?;
    let v = s.as_f64()?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(s.error(format!("<{tag}> must be a finite number > 0, found {v}")))
    }
}

fn near_far(light: &Section) -> Result<(f64, f64), FormatError> {
    let near = positive(light, "near")?;
    let far_section = light.required("far")?;
    let far = far_section.as_f64()?;
    if !(far.is_finite() && far > near) {
        return Err(far_section.error(format!(
            "<far> must be finite and greater than <near> ({near}), found {far}"
        )));
    }
    Ok((near, far))
}

fn resolution(light: &Section) -> Result<u32, FormatError> {
    let s = light.required("resolution")?;
    let v = s.as_i64()?;
    match u32::try_from(v) {
        Ok(r) if (1..=MAX_RESOLUTION).contains(&r) => Ok(r),
        _ => Err(s.error(format!(
            "<resolution> must be between 1 and {MAX_RESOLUTION} texels, found {v}"
        ))),
    }
}

const SPEEDTREES_TAGS: &[&str] = &["tree"];
const TREE_TAGS: &[&str] = &["spt", "model", "trunk", "crown"];
const TRUNK_TAGS: &[&str] = &["radius", "height"];
const CROWN_TAGS: &[&str] = &["radius", "height", "base", "shape"];

/// `<speedtrees>` (docs/contract.md §3): each `<tree>` rule checked (errors name the element, so
/// the reader adds the file's line and column); elements nothing reads
/// are added to `unknown`.
fn parse_speedtrees(
    section: &Section,
    unknown: &mut Vec<UnknownElement>,
) -> Result<SpeedTreeProxies, FormatError> {
    unknown_children(section, SPEEDTREES_TAGS, unknown);
    let mut rules: Vec<ProxyRule> = Vec::new();
    for tree in section.children_named("tree") {
        unknown_children(tree, TREE_TAGS, unknown);
        let patterns = patterns(tree, &rules)?;
        let proxy = proxy(tree, unknown)?;
        rules.push(ProxyRule { patterns, proxy });
    }
    Ok(SpeedTreeProxies { rules })
}

/// A rule's `<spt>` patterns; one written in an earlier rule is an error
/// (that rule takes every tree it matches: this one never would).
fn patterns(tree: &Section, earlier: &[ProxyRule]) -> Result<Vec<SptPattern>, FormatError> {
    let mut out: Vec<SptPattern> = Vec::new();
    for spt in tree.children_named("spt") {
        let pattern = SptPattern::new(&spt.value).map_err(|why| spt.error(why))?;
        let taken = earlier
            .iter()
            .flat_map(|rule| &rule.patterns)
            .chain(&out)
            .any(|p| p.same_as(&pattern));
        if taken {
            return Err(spt.error(format!(
                "<spt> `{}` is given before; the first rule that matches a tree wins, so this one never would: remove it",
                pattern.text
            )));
        }
        out.push(pattern);
    }
    if out.is_empty() {
        return Err(tree.error(
            "<tree> without <spt>; give the .spt names it covers (a name or a glob such as speedtree/**/Bush*.spt)",
        ));
    }
    Ok(out)
}

/// A rule's proxy: `<model>`, or `<trunk>` and `<crown>`.
fn proxy(tree: &Section, unknown: &mut Vec<UnknownElement>) -> Result<Proxy, FormatError> {
    let models: Vec<&Section> = tree.children_named("model").collect();
    let (trunk, crown) = (tree.child("trunk"), tree.child("crown"));
    for tag in ["model", "trunk", "crown"] {
        if let Some(second) = tree.children_named(tag).nth(1) {
            return Err(second.error(format!("a second <{tag}> in one <tree>; give one")));
        }
    }
    match (models.first(), trunk, crown) {
        (Some(model), None, None) => {
            if model.value.is_empty() {
                return Err(model.error("empty <model>; give the proxy's .model resource name"));
            }
            Ok(Proxy::Model(model.value.clone()))
        }
        (Some(model), _, _) => Err(model.error(
            "a <tree> with both <model> and <trunk>/<crown>; give one proxy: a .model or a parametric trunk and crown",
        )),
        (None, Some(trunk), Some(crown)) => {
            unknown_children(trunk, TRUNK_TAGS, unknown);
            unknown_children(crown, CROWN_TAGS, unknown);
            Ok(Proxy::Parametric(parametric(trunk, crown)?))
        }
        (None, None, None) => Err(tree.error(
            "<tree> without a proxy; give <model> (a .model resource) or <trunk> and <crown> (sizes in metres)",
        )),
        (None, _, None) => Err(tree.error("<trunk> without <crown>; a parametric proxy has both")),
        (None, None, _) => Err(tree.error("<crown> without <trunk>; a parametric proxy has both")),
    }
}

fn parametric(trunk: &Section, crown: &Section) -> Result<ParametricTree, FormatError> {
    let crown_shape = match crown.child("shape") {
        None => CrownShape::default(),
        Some(s) => CrownShape::from_name(&s.value).ok_or_else(|| {
            s.error(format!(
                "unknown crown <shape> `{}`; expected ellipsoid or cone",
                s.value
            ))
        })?,
    };
    let crown_base = match crown.child("base") {
        None => 0.0,
        Some(s) => {
            let v = s.as_f64()?;
            if !(v.is_finite() && v >= 0.0) {
                return Err(s.error(format!(
                    "<base> must be a finite number of metres >= 0, found {v}"
                )));
            }
            v
        }
    };
    Ok(ParametricTree {
        trunk_radius: size(trunk, "radius")?,
        trunk_height: size(trunk, "height")?,
        crown_radius: size(crown, "radius")?,
        crown_height: size(crown, "height")?,
        crown_base,
        crown_shape,
    })
}

/// A required size in metres: finite and above zero.
fn size(section: &Section, tag: &str) -> Result<f64, FormatError> {
    let s = section.required(tag)?;
    let v = s.as_f64()?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(s.error(format!(
            "<{tag}> must be a finite number of metres > 0, found {v}"
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::section::build::{el, with_paths};

    fn leaf(name: &str, value: &str) -> Section {
        el(name, value, vec![])
    }

    fn sun() -> Section {
        el(
            "light",
            "",
            vec![
                leaf("name", "sun"),
                leaf("type", "directional"),
                leaf("direction", "0 -2 0"),
                leaf("texelSize", "0.1"),
            ],
        )
    }

    fn spot() -> Section {
        el(
            "light",
            "",
            vec![
                leaf("type", "spot"),
                leaf("position", "10 20 5"),
                leaf("direction", "0 -1 0"),
                leaf("fov", "60"),
                leaf("near", "0.1"),
                leaf("far", "80"),
                leaf("resolution", "1024"),
            ],
        )
    }

    fn point() -> Section {
        el(
            "light",
            "",
            vec![
                leaf("type", "Point"),
                leaf("position", "0 5 0"),
                leaf("near", "0.1"),
                leaf("far", "30"),
                leaf("resolution", "512"),
            ],
        )
    }

    fn settings(lights: Vec<Section>, extra: Vec<Section>) -> Section {
        let mut children = vec![
            el(
                "resPaths",
                "",
                vec![leaf("path", "res"), leaf("path", "/abs/res")],
            ),
            leaf("space", "spaces/arctic"),
            el("lights", "", lights),
        ];
        children.extend(extra);
        with_paths(el("shadowcull", "", children), "")
    }

    fn parse_it(root: &Section) -> Result<BakeSettings, FormatError> {
        parse(root, Path::new("/work/cfg"))
    }

    #[test]
    fn the_spec_sketch_parses_with_defaults() {
        let s = parse_it(&settings(vec![sun(), spot(), point()], vec![])).unwrap();
        assert_eq!(
            s.res_paths,
            [PathBuf::from("/work/cfg/res"), PathBuf::from("/abs/res")]
        );
        assert_eq!(s.space, "spaces/arctic");
        assert_eq!(s.face_culling, FaceCulling::Back);
        assert_eq!(s.height_bias, 0.05);
        assert_eq!(s.tie_epsilon, 1e-4);
        assert_eq!(s.lights.len(), 3);
        assert_eq!(s.lights[0].name, "sun");
        assert_eq!(
            s.lights[0].kind,
            LightKind::Directional {
                direction: DVec3::new(0.0, -1.0, 0.0),
                texel_size: 0.1
            }
        );
        assert_eq!(s.lights[1].name, "light1");
        assert_eq!(s.lights[1].kind.type_name(), "spot");
        assert!(matches!(
            s.lights[1].kind,
            LightKind::Spot { fov_degrees, resolution: 1024, far, .. } if fov_degrees == 60.0 && far == 80.0
        ));
        assert_eq!(s.lights[2].name, "light2");
        assert!(matches!(
            s.lights[2].kind,
            LightKind::Point { resolution: 512, position, .. } if position == DVec3::new(0.0, 5.0, 0.0)
        ));
    }

    #[test]
    fn overrides_are_read() {
        let s = parse_it(&settings(
            vec![],
            vec![
                leaf("faceCulling", "NONE"),
                leaf("heightBias", "0"),
                leaf("tieEpsilon", "0.01"),
            ],
        ))
        .unwrap();
        assert_eq!(s.face_culling, FaceCulling::None);
        assert_eq!(s.height_bias, 0.0);
        assert_eq!(s.tie_epsilon, 0.01);
        assert!(s.lights.is_empty());
        assert_eq!(FaceCulling::from_name("front"), Some(FaceCulling::Front));
        assert_eq!(FaceCulling::Front.name(), "front");
    }

    fn error_of(root: Section) -> String {
        parse_it(&root).unwrap_err().to_string()
    }

    /// `light` with `tag` set to `value`, or removed when `value` is None.
    fn tweak(mut light: Section, tag: &str, value: Option<&str>) -> Section {
        light.children.retain(|c| c.name != tag);
        if let Some(v) = value {
            light.children.push(leaf(tag, v));
        }
        light
    }

    fn light_error(light: Section) -> String {
        error_of(settings(vec![light], vec![]))
    }

    #[test]
    fn too_many_lights() {
        let lights: Vec<Section> = (0..33).map(|_| tweak(sun(), "name", None)).collect();
        let e = error_of(settings(lights, vec![]));
        assert!(
            e.contains("33 lights") && e.contains("<shadowcull/lights>"),
            "{e}"
        );
        let lights: Vec<Section> = (0..32).map(|_| tweak(sun(), "name", None)).collect();
        assert_eq!(
            parse_it(&settings(lights, vec![])).unwrap().lights.len(),
            32
        );
    }

    #[test]
    fn bad_directions() {
        for d in ["0 0 0", "NaN 1 0", "inf 0 0", "1 2"] {
            let e = light_error(tweak(sun(), "direction", Some(d)));
            assert!(
                e.contains("<shadowcull/lights/light/direction>"),
                "{d}: {e}"
            );
        }
        let e = light_error(tweak(spot(), "direction", Some("0 0 0")));
        assert!(e.contains("non-zero"), "{e}");
    }

    #[test]
    fn bad_light_values() {
        let cases = [
            (tweak(sun(), "texelSize", Some("0")), "texelSize"),
            (tweak(sun(), "texelSize", Some("-1")), "texelSize"),
            (tweak(spot(), "fov", Some("0")), "(0, 180)"),
            (tweak(spot(), "fov", Some("180")), "(0, 180)"),
            (tweak(spot(), "fov", Some("NaN")), "(0, 180)"),
            (tweak(spot(), "near", Some("0")), "<near> must be"),
            (tweak(point(), "far", Some("0.1")), "greater than <near>"),
            (tweak(point(), "far", Some("inf")), "greater than <near>"),
            (
                tweak(point(), "resolution", Some("0")),
                "between 1 and 65536",
            ),
            (
                tweak(spot(), "resolution", Some("65537")),
                "between 1 and 65536",
            ),
            (
                tweak(spot(), "resolution", Some("-3")),
                "between 1 and 65536",
            ),
            (tweak(spot(), "position", Some("1 inf 0")), "finite"),
            (
                tweak(sun(), "type", Some("area")),
                "unknown light type `area`",
            ),
            (tweak(sun(), "name", Some("")), "empty light <name>"),
        ];
        for (light, expected) in cases {
            let e = light_error(light);
            assert!(e.contains(expected), "expected `{expected}`: {e}");
            assert!(e.contains("<shadowcull/lights/light"), "{e}");
        }
    }

    #[test]
    fn missing_values() {
        for (light, tag) in [
            (tweak(sun(), "type", None), "type"),
            (tweak(sun(), "direction", None), "direction"),
            (tweak(sun(), "texelSize", None), "texelSize"),
            (tweak(spot(), "fov", None), "fov"),
            (tweak(spot(), "position", None), "position"),
            (tweak(point(), "near", None), "near"),
            (tweak(point(), "far", None), "far"),
            (tweak(point(), "resolution", None), "resolution"),
        ] {
            let e = light_error(light);
            assert!(
                e.contains(&format!("missing required element <{tag}>")),
                "{e}"
            );
        }
        let mut root = settings(vec![], vec![]);
        root.children.retain(|c| c.name != "space");
        assert!(error_of(root).contains("<space>"));
        let mut root = settings(vec![], vec![]);
        root.children.retain(|c| c.name != "resPaths");
        assert!(error_of(root).contains("<resPaths>"));
        let mut root = settings(vec![], vec![]);
        root.children[0].children.clear();
        assert!(error_of(root).contains("no <path>"));
    }

    #[test]
    fn bad_global_values() {
        let e = error_of(settings(vec![], vec![leaf("faceCulling", "both")]));
        assert!(e.contains("unknown face culling `both`"), "{e}");
        let e = error_of(settings(vec![], vec![leaf("heightBias", "-1")]));
        assert!(e.contains("<heightBias>"), "{e}");
        let e = error_of(settings(vec![], vec![leaf("tieEpsilon", "NaN")]));
        assert!(e.contains("<tieEpsilon>"), "{e}");
        let e = error_of(settings(vec![], vec![leaf("tieEpsilon", "tiny")]));
        assert!(e.contains("tiny"), "{e}");
    }

    #[test]
    fn duplicate_names_including_defaults() {
        let e = error_of(settings(vec![sun(), sun()], vec![]));
        assert!(e.contains("duplicate light name `sun`"), "{e}");
        // The second light's default name is light1, which the first took.
        let e = error_of(settings(
            vec![tweak(sun(), "name", Some("light1")), spot()],
            vec![],
        ));
        assert!(e.contains("duplicate light name `light1`"), "{e}");
    }

    #[test]
    fn bits_default_to_the_position_and_may_be_given() {
        let s = parse_it(&settings(vec![sun(), spot(), point()], vec![])).unwrap();
        assert_eq!(s.bits, [0, 1, 2]);
        let s = parse_it(&settings(
            vec![
                tweak(sun(), "bit", Some("5")),
                tweak(spot(), "bit", Some("31")),
            ],
            vec![],
        ))
        .unwrap();
        assert_eq!(s.bits, [5, 31]);
        for bad in ["32", "-1", "two"] {
            let e = light_error(tweak(sun(), "bit", Some(bad)));
            assert!(e.contains("bit"), "{bad}: {e}");
        }
        // The spot (light1) takes bit 0 explicitly; the sun has it by position.
        let e = error_of(settings(
            vec![sun(), tweak(spot(), "bit", Some("0"))],
            vec![],
        ));
        assert!(
            e.contains("light `light1` and light `sun` both use bit 0"),
            "{e}"
        );
    }

    #[test]
    fn edit_distance_counts_inserts_deletes_replacements_and_swaps() {
        assert_eq!(edit_distance("", ""), 0);
        assert_eq!(edit_distance("abc", ""), 3);
        assert_eq!(edit_distance("", "ab"), 2);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("heightbais", "heightbias"), 1);
        assert_eq!(edit_distance("ab", "ba"), 1);
        assert_eq!(edit_distance("texelsiz", "texelsize"), 1);
        assert_eq!(edit_distance("fov", "fov"), 0);
        assert_eq!(edit_distance("höhe", "hohe"), 1);
    }

    #[test]
    fn the_closest_valid_name_is_suggested_only_when_close() {
        assert_eq!(closest_name("heightBais", ROOT_TAGS), Some("heightBias"));
        assert_eq!(closest_name("HeightBias", ROOT_TAGS), Some("heightBias"));
        assert_eq!(closest_name("tieEpsilom", ROOT_TAGS), Some("tieEpsilon"));
        assert_eq!(closest_name("light", ROOT_TAGS), Some("lights"));
        assert_eq!(closest_name("texelSiz", LIGHT_TAGS), Some("texelSize"));
        assert_eq!(closest_name("resoltion", LIGHT_TAGS), Some("resolution"));
        assert_eq!(closest_name("paths", RES_PATHS_TAGS), Some("path"));
        // Only names valid at that level: <texelSize> belongs in a light.
        assert_eq!(closest_name("texelSize", ROOT_TAGS), None);
        assert_eq!(closest_name("colour", LIGHT_TAGS), None);
        assert_eq!(closest_name("x", LIGHT_TAGS), None);
    }

    #[test]
    fn an_unknown_element_says_where_it_is_and_what_was_meant() {
        let s = parse_it(&settings(
            vec![tweak(sun(), "colour", Some("red"))],
            vec![leaf("heightBais", "0.1")],
        ))
        .unwrap();
        let [misspelt, stranger] = &s.unknown[..] else {
            panic!("{:?}", s.unknown);
        };
        assert_eq!(
            misspelt.reason(),
            "unknown element <heightBais> (shadowcull/heightBais); did you mean <heightBias>?"
        );
        assert_eq!(misspelt.location(), format!("byte {}", misspelt.offset));
        assert_eq!(
            stranger.reason(),
            format!(
                "unknown element <colour> (shadowcull/lights/light/colour); expected one of {}",
                LIGHT_TAGS.join(", ")
            )
        );
        let text = b"<s>\n\t<heightBais>1</heightBais>\n</s>";
        let mut positioned = misspelt.clone();
        positioned.offset = 5;
        positioned.position = crate::formats::text_position(text, 5);
        assert_eq!(positioned.location(), "2:2");
        assert!(positioned
            .to_string()
            .starts_with("2:2: unknown element <heightBais>"));
    }

    #[test]
    fn unknown_elements_are_listed_not_refused() {
        let s = parse_it(&settings(
            vec![tweak(sun(), "texelSiz", Some("1"))],
            vec![leaf("heightBais", "0.1")],
        ))
        .unwrap();
        let paths: Vec<&str> = s.unknown.iter().map(|u| u.path.as_str()).collect();
        assert_eq!(
            paths,
            ["shadowcull/heightBais", "shadowcull/lights/light/texelSiz"]
        );
        assert!(parse_it(&settings(vec![sun()], vec![]))
            .unwrap()
            .unknown
            .is_empty());
    }
}

#[cfg(test)]
mod speedtree_tests {
    use super::*;
    use crate::formats::xml;

    const SETTINGS: &str = "<s>\n<speedtrees>\n\t<tree>\n\t\t<spt>speedtree/*/Bush*.spt</spt>\n\t\t<model>sets/proxies/bush.model</model>\n\t</tree>\n\t<tree>\n\t\t<spt>speedtree/**</spt>\n\t\t<trunk><radius>0.3</radius><height>6</height></trunk>\n\t\t<crown><radius>3</radius><height>5</height><base>2</base></crown>\n\t</tree>\n</speedtrees>\n</s>";

    fn read(text: &str) -> Result<(SpeedTreeProxies, Vec<UnknownElement>), FormatError> {
        let root = xml::parse(text.as_bytes()).unwrap();
        let mut unknown = Vec::new();
        let proxies = parse_speedtrees(root.child("speedtrees").unwrap(), &mut unknown)?;
        Ok((proxies, unknown))
    }

    #[test]
    fn the_first_matching_rule_wins() {
        let (proxies, unknown) = read(SETTINGS).unwrap();
        assert!(unknown.is_empty());
        assert_eq!(
            proxies.proxy_for("speedtree/m/Bush2.spt"),
            Some(&Proxy::Model("sets/proxies/bush.model".into()))
        );
        let Some(Proxy::Parametric(tree)) = proxies.proxy_for("speedtree/m/Oak.spt") else {
            panic!("the second rule covers every other tree");
        };
        assert_eq!(
            (
                tree.trunk_radius,
                tree.trunk_height,
                tree.crown_radius,
                tree.crown_height,
                tree.crown_base
            ),
            (0.3, 6.0, 3.0, 5.0, 2.0)
        );
        assert_eq!(tree.crown_shape, CrownShape::Ellipsoid);
        assert_eq!(proxies.proxy_for("trees/Oak.spt"), None);
    }

    #[test]
    fn mistakes_name_the_element() {
        let cases = [
            ("<tree><model>a.model</model></tree>", "without <spt>", "speedtrees/tree"),
            ("<tree><spt>a.spt</spt></tree>", "without a proxy", "speedtrees/tree"),
            ("<tree><spt>a.spt</spt><model>m</model><trunk/></tree>", "both <model>", "tree/model"),
            ("<tree><spt>a.spt</spt><trunk><radius>1</radius><height>1</height></trunk></tree>", "without <crown>", "speedtrees/tree"),
            ("<tree><spt>a.spt</spt><trunk><radius>0</radius><height>1</height></trunk><crown><radius>1</radius><height>1</height></crown></tree>", "> 0, found 0", "trunk/radius"),
            ("<tree><spt>a.spt</spt><trunk><radius>1</radius></trunk><crown><radius>1</radius><height>1</height></crown></tree>", "missing required element <height>", "tree/trunk"),
            ("<tree><spt>a.spt</spt><trunk><radius>1</radius><height>1</height></trunk><crown><radius>1</radius><height>nan</height></crown></tree>", "finite", "crown/height"),
            ("<tree><spt>a.spt</spt><trunk><radius>1</radius><height>1</height></trunk><crown><radius>1</radius><height>1</height><shape>cube</shape></crown></tree>", "unknown crown <shape> `cube`", "crown/shape"),
            ("<tree><spt>a.spt</spt><trunk><radius>1</radius><height>1</height></trunk><crown><radius>1</radius><height>1</height><base>-1</base></crown></tree>", ">= 0", "crown/base"),
            ("<tree><spt>a/**b</spt><model>m</model></tree>", "whole segment", "tree/spt"),
            ("<tree><spt>A.spt</spt><model>m</model></tree><tree><spt>a.SPT</spt><model>n</model></tree>", "never would", "tree/spt"),
            ("<tree><spt>a.spt</spt><model>m</model><model>n</model></tree>", "a second <model>", "tree/model"),
        ];
        for (trees, message, element) in cases {
            let text = format!("<s><speedtrees>{trees}</speedtrees></s>");
            let err = read(&text).unwrap_err().to_string();
            assert!(err.contains(message), "{trees}: {err}");
            assert!(err.contains(element), "{trees}: {err}");
        }
    }

    #[test]
    fn unknown_elements_are_listed_with_their_level() {
        let text = "<s><speedtrees><forest/><tree><spt>a.spt</spt><modle>x</modle><model>m</model></tree><tree><spt>b.spt</spt><trunk><radius>1</radius><height>1</height><girth>2</girth></trunk><crown><radius>1</radius><height>1</height></crown></tree></speedtrees></s>";
        let (_, unknown) = read(text).unwrap();
        let reasons: Vec<String> = unknown.iter().map(UnknownElement::reason).collect();
        assert_eq!(reasons.len(), 3, "{reasons:?}");
        assert!(reasons[0].contains("<forest>"), "{reasons:?}");
        assert!(reasons[1].contains("did you mean <model>?"), "{reasons:?}");
        assert!(
            reasons[2].contains("<girth>") && reasons[2].contains("radius, height"),
            "{reasons:?}"
        );
    }

    #[test]
    fn parametric_names_differ_exactly_when_parameters_do() {
        let (proxies, _) = read(SETTINGS).unwrap();
        let Proxy::Parametric(tree) = proxies.rules[1].proxy else {
            panic!()
        };
        let cone = ParametricTree {
            crown_shape: CrownShape::Cone,
            ..tree
        };
        let taller = ParametricTree {
            trunk_height: 6.000001,
            ..tree
        };
        assert_ne!(tree.name(), cone.name());
        assert_ne!(tree.name(), taller.name());
        assert_eq!(tree.name(), ParametricTree { ..tree }.name());
        assert!(tree.name().contains(':'));
    }

    #[test]
    fn the_unmodelled_casters_policy_defaults_to_fail() {
        let read = |extra: &str| {
            let text = format!(
                "<shadowcull><resPaths><path>r</path></resPaths><space>s</space>{extra}</shadowcull>"
            );
            from_bytes(text.as_bytes(), Path::new("bake.xml"))
        };
        assert_eq!(
            read("").unwrap().unmodelled_casters,
            UnmodelledCasters::Fail
        );
        assert!(read("").unwrap().speedtrees.is_empty());
        let keep = read("<unmodelledCasters> KEEP </unmodelledCasters>").unwrap();
        assert_eq!(keep.unmodelled_casters, UnmodelledCasters::Keep);
        assert_eq!(UnmodelledCasters::Keep.name(), "keep");
        let err = read("<unmodelledCasters>maybe</unmodelledCasters>").unwrap_err();
        assert!(err.to_string().contains("expected fail or keep"), "{err}");
    }

    #[test]
    fn speedtree_mistakes_give_the_file_line_and_column() {
        let text = "<shadowcull>\n\t<resPaths><path>r</path></resPaths>\n\t<space>s</space>\n\t<speedtrees>\n\t\t<tree>\n\t\t\t<spt>a/*.spt</spt>\n\t\t\t<trunk><radius>-1</radius><height>2</height></trunk>\n\t\t\t<crown><radius>1</radius><height>1</height></crown>\n\t\t</tree>\n\t</speedtrees>\n</shadowcull>";
        let err = from_bytes(text.as_bytes(), Path::new("bake.xml"))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("bake.xml:7:"), "{err}");
        assert!(
            err.contains("<radius> must be a finite number of metres > 0, found -1"),
            "{err}"
        );
        let typo = text.replace(
            "<trunk><radius>-1",
            "<trunk><radius>1</radius><raduis>1</raduis><radius>1",
        );
        let settings = from_bytes(typo.as_bytes(), Path::new("bake.xml")).unwrap();
        let [unknown] = &settings.unknown[..] else {
            panic!("{:?}", settings.unknown);
        };
        // Three tabs, `<trunk>` and `<radius>1</radius>` (28 characters) before it.
        assert_eq!(unknown.location(), "7:29");
        assert!(
            unknown.reason().contains("did you mean <radius>?"),
            "{}",
            unknown.reason()
        );
    }

    #[test]
    fn the_contract_sketch_reads_as_it_says() {
        let contract = include_str!("../../docs/contract.md");
        let section = &contract[contract.find("## 3. Bake settings").unwrap()..];
        let start = section.find("```xml\n").unwrap() + "```xml\n".len();
        let sketch = &section[start..start + section[start..].find("```").unwrap()];
        let settings = from_bytes(sketch.as_bytes(), Path::new("sketch.xml")).unwrap();
        assert!(settings.unknown.is_empty(), "{:?}", settings.unknown);
        assert_eq!(settings.lights.len(), 3);
        assert_eq!(settings.unmodelled_casters, UnmodelledCasters::Fail);
        let proxies = &settings.speedtrees;
        assert_eq!(
            proxies.proxy_for("speedtree/arctic/Bush2_1.spt"),
            Some(&Proxy::Model("sets/proxies/bush.model".into()))
        );
        assert_eq!(
            proxies.proxy_for("speedtree/arctic/Oak.spt"),
            Some(&Proxy::Parametric(ParametricTree {
                trunk_radius: 0.3,
                trunk_height: 6.0,
                crown_radius: 3.0,
                crown_height: 5.0,
                crown_base: 2.0,
                crown_shape: CrownShape::Ellipsoid,
            }))
        );
        assert_eq!(proxies.proxy_for("trees/Oak.spt"), None);
    }
}
