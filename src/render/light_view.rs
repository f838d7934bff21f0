//! The light view: the shadow map as the light sees it. Each pixel is one
//! texel's front surface after the bake's own hit filter (face culling,
//! double-sided groups, mirrored instances, the below-ground test; the All
//! pass, so alpha-tested and receiver-only surfaces show where they are
//! first), coloured by its caster's verdict and shaded by distance.
//!
//! Layout: texel `(x, y)` is column `x`, row `height − 1 − y`, so the grid's
//! `v` axis points up the picture. A point light's six faces stand side by
//! side in the order +X, −X, +Y, −Y, +Z, −Z (`light::CUBE_FACE_NAMES`), each
//! `resolution` pixels wide. A map larger than the requested size is shown
//! smaller by picking, for each pixel, the texel under the pixel's centre
//! (no blending, so every pixel is one class and the counts stay counts of
//! texels); only those texels are traced.
//!
//! The marked view (`light_view_marked`, for `explain -o`) is the same map
//! in grey with a caller's texels in colours no grey pixel has, so a reader
//! (or a test decoding the PNG) counts them by colour.

use super::{check_size, shaded, verdicts, Class, Picture, RenderError, Source};
use crate::bake::setup::BakeWorld;
use crate::bake::trace_light::LightRays;
use crate::bake::BakeConfig;
use crate::light::{TexelGrid, CUBE_FACE_NAMES};
use crate::scene::Scene;
use rayon::prelude::*;

/// Faces narrower than this (pixels) get no label: it would hide them.
const FACE_LABEL_MIN_WIDTH: u32 = 12;

/// 3×5 glyphs, rows top to bottom, bit 2 = left column.
fn glyph(c: char) -> [u8; 5] {
    match c {
        '+' => [0b000, 0b010, 0b111, 0b010, 0b000],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        'X' => [0b101, 0b101, 0b010, 0b101, 0b101],
        'Y' => [0b101, 0b101, 0b010, 0b010, 0b010],
        _ => [0b111, 0b001, 0b010, 0b100, 0b111], // Z
    }
}

/// Writes each cube face's name (`+X` … `-Z`) into its top-left corner:
/// white glyphs on a black box, scaled with the face.
fn label_faces(rgb: &mut [u8], width: u32, height: u32) {
    let face_width = width / 6;
    if face_width < FACE_LABEL_MIN_WIDTH || height < 9 {
        return;
    }
    let scale = (face_width / 48).clamp(1, 8);
    let mut put = |x: u32, y: u32, colour: [u8; 3]| {
        if x < width && y < height {
            let i = ((y * width + x) * 3) as usize;
            rgb[i..i + 3].copy_from_slice(&colour);
        }
    };
    for (face, name) in CUBE_FACE_NAMES.iter().enumerate() {
        let x0 = (face as u64 * width as u64).div_ceil(6) as u32;
        // Box: 1 px margin, two glyphs of 3 with a 1 px gap.
        for y in 0..(7 * scale) {
            for x in 0..(9 * scale) {
                put(x0 + x, y, [0, 0, 0]);
            }
        }
        for (n, c) in name.chars().enumerate() {
            for (row, bits) in glyph(c).iter().enumerate() {
                for column in 0..3u32 {
                    if bits & (0b100 >> column) == 0 {
                        continue;
                    }
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let x = x0 + (1 + n as u32 * 4 + column) * scale + dx;
                            let y = (1 + row as u32) * scale + dy;
                            put(x, y, [255, 255, 255]);
                        }
                    }
                }
            }
        }
    }
}

/// Largest light view drawn when the caller gives no size.
pub const DEFAULT_MAX_LIGHT_SIZE: (u32, u32) = (2048, 2048);

/// Darkest shade, for the farthest surface in the picture; the nearest is
/// at full brightness.
const FAR_SHADE: f64 = 0.3;

/// Draws light `light` of `config`. `max_size` (width, height) bounds the
/// picture; the map is shown 1:1 when it fits, else reduced (aspect kept) to
/// fit. `None`: [`DEFAULT_MAX_LIGHT_SIZE`].
pub fn light_view(
    scene: &Scene,
    config: &BakeConfig,
    light: usize,
    max_size: Option<(u32, u32)>,
) -> Result<Picture, RenderError> {
    light_view_from(scene, config, light, max_size, Source::Bake)
}

/// [`light_view`] with the verdicts from `source`.
pub fn light_view_from(
    scene: &Scene,
    config: &BakeConfig,
    light: usize,
    max_size: Option<(u32, u32)>,
    source: Source,
) -> Result<Picture, RenderError> {
    light_view_in(&BakeWorld::new(scene), config, light, max_size, source)
}

/// [`light_view_from`] on a world already built, so that several lights'
/// views share its bottom levels.
pub fn light_view_in(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    max_size: Option<(u32, u32)>,
    source: Source,
) -> Result<Picture, RenderError> {
    draw(world, config, light, max_size, source, None)
}

/// What a texel says about the caster(s) a marked view is about; `explain`
/// decides it by the rules of docs/contract.md §4.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TexelMark {
    /// The front hit, with something behind it: useful here.
    Useful,
    /// The front hit, with nothing behind it that counts.
    NothingBehind,
    /// Met, but a nearer caster is the front hit.
    Hidden,
}

impl TexelMark {
    pub const ALL: [TexelMark; 3] = [
        TexelMark::Useful,
        TexelMark::NothingBehind,
        TexelMark::Hidden,
    ];

    /// Okabe-Ito colours none of which is grey, so every marked pixel
    /// stands out from the grey map (and a reader counts them by colour).
    pub fn colour(self) -> [u8; 3] {
        match self {
            TexelMark::Useful => [213, 94, 0],
            TexelMark::NothingBehind => [86, 180, 233],
            TexelMark::Hidden => [240, 228, 66],
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            TexelMark::Useful => "front hit, something behind: useful (vermilion)",
            TexelMark::NothingBehind => "front hit, nothing behind that counts (sky blue)",
            TexelMark::Hidden => "met but hidden by a nearer caster (yellow)",
        }
    }
}

/// The mark of texel `(face, x, y)`, or `None` to show the map there.
pub type Marker<'m> = dyn Fn(usize, u32, u32) -> Option<TexelMark> + Sync + 'm;

/// [`light_view_in`] in grey (each class's luminance, shaded by distance),
/// with each pixel whose texel `marker` marks in its [`TexelMark`] colour.
/// At 1:1 every texel is one pixel, so the pixels of a colour count the
/// texels of that mark.
pub fn light_view_marked(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    max_size: Option<(u32, u32)>,
    source: Source,
    marker: &Marker,
) -> Result<Picture, RenderError> {
    draw(world, config, light, max_size, source, Some(marker))
}

fn draw(
    world: &BakeWorld,
    config: &BakeConfig,
    light: usize,
    max_size: Option<(u32, u32)>,
    source: Source,
    marker: Option<&Marker>,
) -> Result<Picture, RenderError> {
    let max_size = max_size.unwrap_or(DEFAULT_MAX_LIGHT_SIZE);
    check_size(max_size.0, max_size.1)?;
    let (verdicts, setup) = verdicts(world, config, light, source)?;
    let Some(setup) = setup else {
        // The light reaches nothing: say why, as the grid does.
        let bounds = world.bounds.ok_or(RenderError::EmptyWorld)?;
        TexelGrid::new(&config.lights[light], bounds)?;
        return Err(RenderError::EmptyWorld);
    };
    let grid = &setup.grid;
    // front_hit does not classify: the passes play no part.
    let rays_of_light = setup.rays(world, config);
    let layout = MapLayout::of(grid, max_size);
    let pixels = front_surfaces(&rays_of_light, &verdicts.classes, &layout);
    let depths = DepthRange::of(&pixels);
    let mut rgb = depths.shade(&pixels);
    let mut notes = notes(grid, &layout, &depths);
    if grid.faces() == 6 {
        label_faces(&mut rgb, layout.width, layout.height);
    }
    // After the labels: a marked texel is never hidden under one.
    if let Some(marker) = marker {
        let counts = overlay(&mut rgb, &layout, marker);
        notes.extend(mark_notes(&counts));
    }
    Ok(Picture {
        width: layout.width,
        height: layout.height,
        rgb,
        classes: pixels.into_iter().map(|(class, _)| class).collect(),
        light: verdicts.light,
        notes,
    })
}

/// Turns `rgb` grey and paints each marked pixel in its mark's colour;
/// returns the pixels per mark, in [`TexelMark::ALL`] order.
fn overlay(rgb: &mut [u8], layout: &MapLayout, marker: &Marker) -> [u64; 3] {
    let marks: Vec<Option<TexelMark>> = (0..layout.height)
        .into_par_iter()
        .flat_map_iter(|row| {
            (0..layout.width).map(move |column| {
                let (face, x, y) = layout.texel_of(column, row);
                marker(face, x, y)
            })
        })
        .collect();
    let mut counts = [0u64; 3];
    for (pixel, mark) in rgb.chunks_exact_mut(3).zip(marks) {
        match mark {
            Some(mark) => {
                pixel.copy_from_slice(&mark.colour());
                counts[TexelMark::ALL.iter().position(|&m| m == mark).unwrap_or(0)] += 1;
            }
            None => {
                let [r, g, b] = [pixel[0], pixel[1], pixel[2]].map(f64::from);
                // Rec. 601 luma: the classes stay apart as shades of grey.
                let grey = (0.299 * r + 0.587 * g + 0.114 * b).round().min(255.0) as u8;
                pixel.copy_from_slice(&[grey; 3]);
            }
        }
    }
    counts
}

/// The legend's lines for a marked view.
fn mark_notes(counts: &[u64; 3]) -> Vec<String> {
    let mut notes = vec![
        "marked view: the map in grey (each class's luminance), the caster's texels in colour:"
            .to_string(),
    ];
    for (mark, count) in TexelMark::ALL.iter().zip(counts) {
        let [r, g, b] = mark.colour();
        notes.push(format!(
            "  {:<52} {r:>3} {g:>3} {b:>3}  {count:>10}",
            mark.label()
        ));
    }
    notes
}

/// The shadow map's size laid out flat (faces side by side) and the
/// picture's size.
struct MapLayout {
    /// At most 6 × 2^18 columns (`light::MAX_SIDE`): u64 arithmetic has
    /// room to spare.
    native_w: u64,
    native_h: u64,
    /// Texels across one face.
    face_width: u64,
    width: u32,
    height: u32,
}

impl MapLayout {
    fn of(grid: &TexelGrid, max_size: (u32, u32)) -> MapLayout {
        let native_w = grid.faces() as u64 * grid.width() as u64;
        let native_h = grid.height() as u64;
        let (width, height) = fit((native_w, native_h), max_size);
        MapLayout {
            native_w,
            native_h,
            face_width: grid.width() as u64,
            width,
            height,
        }
    }

    /// The texel `(face, x, y)` under the centre of pixel `(column, row)`
    /// (rows from the top).
    fn texel_of(&self, column: u32, row: u32) -> (usize, u32, u32) {
        let native_row = centre_sample(row, self.height, self.native_h);
        let native_column = centre_sample(column, self.width, self.native_w);
        (
            (native_column / self.face_width) as usize,
            (native_column % self.face_width) as u32,
            (self.native_h - 1 - native_row) as u32,
        )
    }

    fn is_one_to_one(&self) -> bool {
        (self.width as u64, self.height as u64) == (self.native_w, self.native_h)
    }
}

/// Each pixel's texel's front surface, row by row from the top: its
/// caster's class and its distance (`NaN` where nothing is hit).
fn front_surfaces(
    rays_of_light: &LightRays<'_>,
    classes: &[Class],
    layout: &MapLayout,
) -> Vec<(Class, f32)> {
    let rows: Vec<Vec<(Class, f32)>> = (0..layout.height)
        .into_par_iter()
        .map(|row| {
            (0..layout.width)
                .map(|column| {
                    let (face, x, y) = layout.texel_of(column, row);
                    match rays_of_light.front_hit(face, x, y) {
                        Some(hit) => (
                            classes
                                .get(hit.caster as usize)
                                .copied()
                                .unwrap_or(Class::Nothing),
                            hit.t,
                        ),
                        None => (Class::Nothing, f32::NAN),
                    }
                })
                .collect()
        })
        .collect();
    rows.into_iter().flatten().collect()
}

/// The nearest and farthest surface in the picture (infinite when none).
#[derive(Clone, Copy)]
struct DepthRange {
    near: f32,
    far: f32,
}

impl DepthRange {
    fn of(pixels: &[(Class, f32)]) -> DepthRange {
        let (near, far) = pixels
            .iter()
            .filter(|(class, _)| *class != Class::Nothing)
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), (_, t)| {
                (lo.min(*t), hi.max(*t))
            });
        DepthRange { near, far }
    }

    /// The pixels' colours, from full brightness at `near` down to
    /// [`FAR_SHADE`] at `far`.
    fn shade(&self, pixels: &[(Class, f32)]) -> Vec<u8> {
        let range = (self.far - self.near) as f64;
        let mut rgb = Vec::with_capacity(pixels.len() * 3);
        for (class, t) in pixels {
            let shade = if range > 0.0 {
                1.0 - (1.0 - FAR_SHADE) * ((t - self.near) as f64 / range)
            } else {
                1.0
            };
            rgb.extend(shaded(*class, shade));
        }
        rgb
    }
}

/// The legend's account of the picture: layout, sampling, face labels and
/// the distance range.
fn notes(grid: &TexelGrid, layout: &MapLayout, depths: &DepthRange) -> Vec<String> {
    let (width, height) = (layout.width, layout.height);
    let mut notes = vec![format!(
        "light view: shadow map {} × {} texels{}, shown at {} × {} ({})",
        grid.width(),
        grid.height(),
        if grid.faces() == 6 {
            format!(
                " per face, six faces side by side ({})",
                CUBE_FACE_NAMES.join(" ")
            )
        } else {
            String::new()
        },
        width,
        height,
        if layout.is_one_to_one() {
            "1:1, one pixel per texel".to_string()
        } else {
            "each pixel is the texel under its centre".to_string()
        }
    )];
    if grid.faces() == 6 && width / 6 >= FACE_LABEL_MIN_WIDTH {
        notes.push(
            "each face is labelled in its top-left corner, white on black (those pixels \
             still count as their texels' colours above)"
                .to_string(),
        );
    }
    notes.push(
        "each pixel: the texel's front surface after the bake's hit filter (face culling, \
         double-sided, mirrored, below ground; All pass), brighter = nearer the light"
            .to_string(),
    );
    let DepthRange { near, far } = *depths;
    if near.is_finite() {
        notes.push(format!(
            "distance range along the rays: {near:.3} m (full brightness) to {far:.3} m ({:.0} %)",
            FAR_SHADE * 100.0
        ));
    }
    notes
}

/// The picture size for a `native` map within `max`: native when it fits,
/// else the largest size with the same aspect (rounded down, at least 1).
fn fit((native_w, native_h): (u64, u64), (max_w, max_h): (u32, u32)) -> (u32, u32) {
    let (max_w, max_h) = (max_w as u64, max_h as u64);
    if native_w <= max_w && native_h <= max_h {
        return (native_w as u32, native_h as u32);
    }
    // Width-limited when native_w / native_h >= max_w / max_h.
    if native_w * max_h >= native_h * max_w {
        (max_w as u32, (native_h * max_w / native_w).max(1) as u32)
    } else {
        ((native_w * max_h / native_h).max(1) as u32, max_h as u32)
    }
}

/// The native index under the centre of picture index `i` of `n`, for a
/// native axis of `native` (≥ n) entries.
fn centre_sample(i: u32, n: u32, native: u64) -> u64 {
    ((2 * i as u64 + 1) * native / (2 * n as u64)).min(native - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_keeps_native_size_or_aspect() {
        assert_eq!(fit((100, 50), (800, 600)), (100, 50));
        assert_eq!(fit((1000, 500), (100, 100)), (100, 50));
        assert_eq!(fit((500, 1000), (100, 100)), (50, 100));
        assert_eq!(fit((6 * 256, 256), (640, 480)), (640, 106));
        assert_eq!(fit((100_000, 1), (10, 10)), (10, 1));
    }

    #[test]
    fn centre_sampling_is_identity_at_one_to_one_and_spreads_otherwise() {
        for i in 0..7 {
            assert_eq!(centre_sample(i, 7, 7), i as u64);
        }
        // 10 texels into 4 pixels: centres at 1.25, 3.75, 6.25, 8.75.
        let picked: Vec<u64> = (0..4).map(|i| centre_sample(i, 4, 10)).collect();
        assert_eq!(picked, vec![1, 3, 6, 8]);
    }
}
