//! Accuracy against run time (`shadowcull sweep`): the same world baked on a
//! ladder of settings — texel density ×¼ … ×4, k×k supersampling, and
//! refinement — each compared, per (caster, light) pair, with a much denser
//! reference bake. A bake is a sampled answer; this shows how wrong each
//! setting can be and what more accuracy costs.
//!
//! Every caster a bake keeps was proven useful by a ray, so a *false keep*
//! (kept here, culled by the reference) is a caster the reference missed;
//! the error that costs shadows in game is the *false cull*.
//!
//! The game's shadow map is not aligned with the bake's grid (cascades
//! snap to their own texels), so a second reference ORs the first with
//! several dense grids moved by random sub-texel offsets (seeded, so the
//! sweep is repeatable): a row's *false culls at any offset* count casters
//! some placement of the grid makes useful and the row culls.

use crate::bake::{self, BakeConfig, BakeError, BakeResult, GridMode, Silent};
use crate::formats::bake_settings::{LightKind, LightSettings};
use crate::rng::Rng;
use crate::scene::Scene;
use serde::Serialize;
use std::fmt::Write as _;
use std::time::Instant;

/// What to compare against, and how refinement samples.
#[derive(Debug, Clone)]
pub struct SweepConfig {
    /// The reference is the configured grid this many times denser (per
    /// side), plus refinement with `reference_refine_samples`.
    pub reference_density: f64,
    pub reference_refine_samples: u32,
    /// Samples per caster of the ladder's refinement rows.
    pub refine_samples: u32,
    /// Footprint lattice (rays per texel side) of the refinement rows.
    pub refine_density: u32,
    /// How many randomly offset grids at `reference_density` the offset
    /// reference ORs with the reference.
    pub offset_references: u32,
    /// Seed of the offsets.
    pub offset_seed: u64,
}

impl Default for SweepConfig {
    fn default() -> Self {
        SweepConfig {
            reference_density: 8.0,
            reference_refine_samples: 64,
            refine_samples: 64,
            refine_density: 8,
            offset_references: 3,
            offset_seed: 17,
        }
    }
}

/// One setting of the ladder.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Setting {
    /// Texel density relative to the settings file, per side.
    pub density: f64,
    /// k: k×k rays per texel.
    pub supersample: u32,
    /// Refinement samples per caster (0: none).
    pub refine_samples: u32,
    /// Refinement's footprint lattice, rays per texel side (0: none).
    pub refine_density: u32,
    /// Texel beams (`--conservative`) instead of centre rays.
    pub conservative: bool,
    /// The filter margin in texels (`--filter-radius`).
    pub filter_radius: u32,
}

impl Setting {
    pub fn label(&self) -> String {
        let mut label = format!("density x{}", fraction(self.density));
        if self.supersample > 1 {
            let _ = write!(label, ", {0}x{0} samples", self.supersample);
        }
        if self.refine_samples > 0 {
            let _ = write!(label, ", refine {}", self.refine_samples);
        }
        if self.refine_density > 0 {
            let _ = write!(label, " + footprint x{}", self.refine_density);
        }
        if self.conservative {
            label.push_str(", conservative");
        }
        if self.filter_radius > 0 {
            let _ = write!(label, ", filter radius {}", self.filter_radius);
        }
        label
    }
}

fn fraction(value: f64) -> String {
    match value {
        v if (v - 0.25).abs() < 1e-12 => "1/4".into(),
        v if (v - 0.5).abs() < 1e-12 => "1/2".into(),
        v => format!("{v}"),
    }
}

/// The ladder: density ×¼ … ×4, 2×2 and 4×4 supersampling at ×1,
/// refinement at ×¼, ×½ and ×1, and at ×1 the conservative mode and the
/// filter margin of one texel.
pub fn ladder(config: &SweepConfig) -> Vec<Setting> {
    let plain = |density| Setting {
        density,
        supersample: 1,
        refine_samples: 0,
        refine_density: 0,
        conservative: false,
        filter_radius: 0,
    };
    let mut settings: Vec<Setting> = [0.25, 0.5, 1.0, 2.0, 4.0].map(plain).to_vec();
    for k in [2, 4] {
        settings.push(Setting {
            supersample: k,
            ..plain(1.0)
        });
    }
    for density in [0.25, 0.5, 1.0] {
        settings.push(Setting {
            refine_samples: config.refine_samples,
            refine_density: config.refine_density,
            ..plain(density)
        });
    }
    settings.push(Setting {
        conservative: true,
        ..plain(1.0)
    });
    settings.push(Setting {
        filter_radius: 1,
        ..plain(1.0)
    });
    settings
}

#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub label: String,
    #[serde(flatten)]
    pub setting: Setting,
    pub rays: u64,
    pub seconds: f64,
    /// Useful in the reference, culled here: a missing shadow in game.
    pub false_culls: u64,
    /// Culled in the reference, kept here: wasted shadow-pass work (or a
    /// caster the reference missed).
    pub false_keeps: u64,
    /// Useful in the offset reference (the reference or a dense grid at
    /// some sub-texel offset), culled here: a shadow missing at some
    /// placement of the game's shadow map.
    pub false_culls_any_offset: u64,
    /// Culled in the offset reference, kept here.
    pub false_keeps_any_offset: u64,
    /// (caster, light) pairs compared.
    pub pairs: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SweepReport {
    pub reference: Row,
    /// The sub-texel offsets (texels of the reference grid) of the offset
    /// reference's extra grids.
    pub offsets: Vec<(f64, f64)>,
    pub rows: Vec<Row>,
}

/// A light with its grid `density` times denser per side.
pub fn scale_light(light: &LightSettings, density: f64) -> LightSettings {
    let mut light = light.clone();
    match &mut light.kind {
        LightKind::Directional { texel_size, .. } => *texel_size /= density,
        LightKind::Spot { resolution, .. } | LightKind::Point { resolution, .. } => {
            *resolution = ((*resolution as f64 * density).round() as u32).max(1)
        }
    }
    light
}

fn bake_setting(
    scene: &Scene,
    base: &BakeConfig,
    setting: Setting,
) -> Result<(BakeResult, f64), BakeError> {
    bake_at(scene, base, setting, (0.0, 0.0))
}

fn bake_at(
    scene: &Scene,
    base: &BakeConfig,
    setting: Setting,
    grid_offset: (f64, f64),
) -> Result<(BakeResult, f64), BakeError> {
    let config = BakeConfig {
        lights: base
            .lights
            .iter()
            .map(|l| scale_light(l, setting.density))
            .collect(),
        supersample: setting.supersample,
        refine_samples: setting.refine_samples,
        refine_density: setting.refine_density,
        grid_mode: if setting.conservative {
            GridMode::Conservative
        } else {
            GridMode::Centres
        },
        filter_radius: setting.filter_radius,
        grid_offset,
        // Rows compare light i at bit i: positions, not the file's <bit>s.
        bits: Vec::new(),
        ..base.clone()
    };
    let started = Instant::now();
    let result = bake::bake(scene, &config, &Silent)?;
    Ok((result, started.elapsed().as_secs_f64()))
}

/// The two references: the dense bake, and its masks OR-ed with dense
/// bakes at other grid offsets.
struct References<'r> {
    reference: &'r BakeResult,
    any_offset: &'r [u32],
}

fn row(setting: Setting, result: &BakeResult, seconds: f64, refs: &References<'_>) -> Row {
    let lights = refs.reference.lights.len().max(result.lights.len());
    let (mut false_culls, mut false_keeps, mut pairs) = (0, 0, 0);
    let (mut culls_any, mut keeps_any) = (0, 0);
    for (id, caster) in result.casters.casters.iter().enumerate() {
        if caster.receiver_only {
            continue;
        }
        let here = result.masks[id];
        let (truth, any) = (refs.reference.masks[id], refs.any_offset[id]);
        for light in 0..lights {
            let bit = 1u32 << light;
            pairs += 1;
            false_culls += u64::from(truth & bit != 0 && here & bit == 0);
            false_keeps += u64::from(truth & bit == 0 && here & bit != 0);
            culls_any += u64::from(any & bit != 0 && here & bit == 0);
            keeps_any += u64::from(any & bit == 0 && here & bit != 0);
        }
    }
    Row {
        label: setting.label(),
        setting,
        rays: result.lights.iter().map(|l| l.rays).sum(),
        seconds,
        false_culls,
        false_keeps,
        false_culls_any_offset: culls_any,
        false_keeps_any_offset: keeps_any,
        pairs,
    }
}

/// `count` sub-texel offsets from `seed`, each coordinate in (0, 1).
pub fn offsets(count: u32, seed: u64) -> Vec<(f64, f64)> {
    let mut rng = Rng::new(seed);
    (0..count)
        .map(|_| {
            let mut draw = || rng.unit().clamp(1.0 / 64.0, 63.0 / 64.0);
            (draw(), draw())
        })
        .collect()
}

/// Bakes the reference and every setting of the ladder. `on_row` hears of
/// each finished row (for progress).
pub fn sweep(
    scene: &Scene,
    base: &BakeConfig,
    config: &SweepConfig,
    mut on_row: impl FnMut(&Row),
) -> Result<SweepReport, BakeError> {
    let reference_setting = Setting {
        density: config.reference_density,
        supersample: 1,
        refine_samples: config.reference_refine_samples,
        refine_density: 0,
        conservative: false,
        filter_radius: 0,
    };
    let (reference, reference_seconds) = bake_setting(scene, base, reference_setting)?;
    let offsets = offsets(config.offset_references, config.offset_seed);
    let mut any_offset = reference.masks.clone();
    for &offset in &offsets {
        let plain = Setting {
            refine_samples: 0,
            ..reference_setting
        };
        let (moved, _) = bake_at(scene, base, plain, offset)?;
        for (any, mask) in any_offset.iter_mut().zip(&moved.masks) {
            *any |= mask;
        }
    }
    let refs = References {
        reference: &reference,
        any_offset: &any_offset,
    };
    let reference_row = row(reference_setting, &reference, reference_seconds, &refs);
    on_row(&reference_row);
    let mut rows = Vec::new();
    for setting in ladder(config) {
        let (result, seconds) = bake_setting(scene, base, setting)?;
        let row = row(setting, &result, seconds, &refs);
        on_row(&row);
        rows.push(row);
    }
    Ok(SweepReport {
        reference: reference_row,
        offsets,
        rows,
    })
}

impl SweepReport {
    pub fn to_csv(&self) -> String {
        let mut out = String::from(
            "label,density,supersample,refine_samples,refine_density,conservative,filter_radius,rays,seconds,false_culls,false_keeps,false_culls_any_offset,false_keeps_any_offset,pairs\n",
        );
        for row in std::iter::once(&self.reference).chain(&self.rows) {
            let setting = &row.setting;
            let _ = writeln!(
                out,
                "\"{}{}\",{},{},{},{},{},{},{},{:.6},{},{},{},{},{}",
                if std::ptr::eq(row, &self.reference) {
                    "reference: "
                } else {
                    ""
                },
                row.label,
                setting.density,
                setting.supersample,
                setting.refine_samples,
                setting.refine_density,
                setting.conservative,
                setting.filter_radius,
                row.rays,
                row.seconds,
                row.false_culls,
                row.false_keeps,
                row.false_culls_any_offset,
                row.false_keeps_any_offset,
                row.pairs
            );
        }
        out
    }

    pub fn to_table(&self) -> String {
        let mut out = format!(
            "reference: {} ({} rays, {:.2} s); offset reference: it OR {} grids at random sub-texel offsets (the reference itself misses {} there)\n{:<44} {:>12} {:>9} {:>11} {:>11} {:>10} {:>10} {:>8}\n",
            self.reference.label,
            self.reference.rays,
            self.reference.seconds,
            self.offsets.len(),
            self.reference.false_culls_any_offset,
            "setting",
            "rays",
            "seconds",
            "false culls",
            "false keeps",
            "culls@any",
            "keeps@any",
            "pairs"
        );
        for row in &self.rows {
            let _ = writeln!(
                out,
                "{:<44} {:>12} {:>9.3} {:>11} {:>11} {:>10} {:>10} {:>8}",
                row.label,
                row.rays,
                row.seconds,
                row.false_culls,
                row.false_keeps,
                row.false_culls_any_offset,
                row.false_keeps_any_offset,
                row.pairs
            );
        }
        out
    }

    /// Both errors against seconds (log scale), one labelled point per
    /// setting, as a self-contained SVG.
    pub fn to_svg(&self) -> String {
        let title = format!(
            "classification error against bake time (reference: {})",
            self.reference.label
        );
        let frame = PlotFrame::of(&self.rows, &title);
        let markers = Series::ALL.map(|series| frame.markers(&self.rows, series));
        let boxes: Vec<LabelBox> = markers
            .iter()
            .flatten()
            .map(|&(px, py)| LabelBox::around(px, py, 6.0))
            .collect();
        let names: Vec<&str> = self.rows.iter().map(|r| r.label.as_str()).collect();
        let (labels, keyed) = place_labels(&markers[0], &names, &boxes, frame.label_area());
        let key_height = keyed.len() as f64 * LINE_HEIGHT;
        let mut svg = frame.header(&title, key_height);
        frame.write_axes(&mut svg);
        for series in Series::ALL {
            write_markers(&mut svg, &self.rows, series, &markers[series.index()]);
        }
        write_labels(&mut svg, &labels);
        frame.write_legend(&mut svg);
        // Labels that found no free place are drawn as their row's number,
        // or not at all, and named here below the plot.
        for (line, &(row, how)) in keyed.iter().enumerate() {
            let values = match how {
                Keyed::Numbered => String::new(),
                Keyed::NotDrawn => {
                    let r = &self.rows[row];
                    format!(
                        " (unlabelled: {:.3} s, {} false culls, {} false keeps)",
                        r.seconds, r.false_culls, r.false_keeps
                    )
                }
            };
            let _ = writeln!(
                svg,
                "<text x=\"{}\" y=\"{}\" fill=\"#555\">{}: {}{values}</text>",
                frame.margin,
                frame.height - 4.0 + line as f64 * LINE_HEIGHT,
                row + 1,
                names[row]
            );
        }
        svg.push_str("</svg>\n");
        svg
    }
}

/// Font size of the plot's text, and of its title.
const FONT_SIZE: f64 = 11.0;
const TITLE_FONT_SIZE: f64 = 14.0;

/// The width of `text` at `font_size`, estimated generously: sans-serif
/// letters average about 0.55 em, so 0.625 em leaves room for wide ones.
fn text_width(text: &str, font_size: f64) -> f64 {
    text.chars().count() as f64 * 0.625 * font_size
}

/// Height of a label's line: font size 11 with room between lines.
const LINE_HEIGHT: f64 = 13.0;

/// How far above the time axis the zero row lies. Settings without errors
/// sit on it, often many close together: on the axis itself every label
/// beside them would leave the plot, and they would all crowd the lines
/// above; lifted, two lines of labels fit below them.
const ZERO_LIFT: f64 = 3.0 * LINE_HEIGHT;

/// The legend's entries, left to right in the band above the plot: a
/// marker and what it means.
const LEGEND: [(LegendMarker, &str); 3] = [
    (
        LegendMarker::Series(Series::FalseCulls),
        "false culls (dots)",
    ),
    (
        LegendMarker::Series(Series::FalseKeeps),
        "false keeps (rings)",
    ),
    (LegendMarker::Square, "squares: with refinement"),
];

#[derive(Debug, Clone, Copy)]
enum LegendMarker {
    Series(Series),
    /// A grey outlined square: the shape of rows with refinement.
    Square,
}

/// Space before a legend entry's text, after its marker, and between
/// entries.
const LEGEND_MARKER_GAP: f64 = 16.0;
const LEGEND_ENTRY_GAP: f64 = 24.0;

/// The legend's width in SVG pixels.
fn legend_width() -> f64 {
    LEGEND
        .iter()
        .map(|(_, text)| LEGEND_MARKER_GAP + text_width(text, FONT_SIZE))
        .sum::<f64>()
        + LEGEND_ENTRY_GAP * (LEGEND.len() - 1) as f64
}

/// The plot's size in SVG pixels and its axes: seconds in whole decades
/// from `lo` to `hi` (log10), errors as log10(1 + e) up to `top`.
struct PlotFrame {
    width: f64,
    height: f64,
    margin: f64,
    lo: f64,
    hi: f64,
    top: f64,
}

impl PlotFrame {
    /// Axes that hold every row's seconds and errors, wide enough for the
    /// title and the legend.
    fn of(rows: &[Row], title: &str) -> PlotFrame {
        let seconds: Vec<f64> = rows.iter().map(|r| r.seconds.max(1e-4)).collect();
        let (lo, hi) = seconds.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), s| {
            (lo.min(*s), hi.max(*s))
        });
        let (lo, hi) = (
            lo.log10().floor(),
            hi.log10().ceil().max(lo.log10().floor() + 1.0),
        );
        let max_error = rows
            .iter()
            .map(|r| r.false_culls.max(r.false_keeps))
            .max()
            .unwrap_or(0)
            .max(1) as f64;
        // log(1 + e): zero stays on the axis, small counts stay apart.
        let top = (1.0 + max_error).log10().ceil().max(1.0);
        let margin = 70.0;
        let width = [
            760.0,
            text_width(title, TITLE_FONT_SIZE) + 2.0 * LINE_HEIGHT,
            legend_width() + 2.0 * margin,
        ]
        .into_iter()
        .fold(0.0, f64::max)
        .ceil();
        PlotFrame {
            width,
            height: 460.0,
            margin,
            lo,
            hi,
            top,
        }
    }

    /// The pixel column of a run time.
    fn x(&self, s: f64) -> f64 {
        self.margin
            + (s.max(1e-4).log10() - self.lo) / (self.hi - self.lo)
                * (self.width - 2.0 * self.margin)
    }

    /// The pixel row of an error count: zero [`ZERO_LIFT`] above the axis.
    fn y(&self, e: f64) -> f64 {
        let zero = self.height - self.margin - ZERO_LIFT;
        zero - (1.0 + e).log10() / self.top * (zero - self.margin)
    }

    /// Where labels may go: the plot and a strip right of it.
    fn label_area(&self) -> LabelBox {
        LabelBox {
            x0: self.margin,
            y0: self.margin,
            x1: self.width - self.margin + 60.0,
            y1: self.height - self.margin,
        }
    }

    /// The opening tag, a white background and the title; `below` more
    /// pixels under the plot (for the key of numbered labels).
    fn header(&self, title: &str, below: f64) -> String {
        let (width, height) = (self.width, self.height + below);
        let mut svg = format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" height=\"{height}\" viewBox=\"0 0 {width} {height}\" font-family=\"sans-serif\" font-size=\"{FONT_SIZE}\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
        );
        let _ = writeln!(
            svg,
            "<text x=\"{}\" y=\"24\" font-size=\"{TITLE_FONT_SIZE}\" text-anchor=\"middle\">{title}</text>",
            width / 2.0,
        );
        svg
    }

    /// Axes, decade ticks, error ticks and the axis titles.
    fn write_axes(&self, svg: &mut String) {
        let (width, height, margin) = (self.width, self.height, self.margin);
        let _ = writeln!(
            svg,
            "<line x1=\"{margin}\" y1=\"{0}\" x2=\"{1}\" y2=\"{0}\" stroke=\"black\"/><line x1=\"{margin}\" y1=\"{margin}\" x2=\"{margin}\" y2=\"{0}\" stroke=\"black\"/>",
            height - margin,
            width - margin
        );
        let mut decade = self.lo;
        while decade <= self.hi {
            let px = self.x(10f64.powf(decade));
            let _ = writeln!(
                svg,
                "<line x1=\"{px}\" y1=\"{0}\" x2=\"{px}\" y2=\"{1}\" stroke=\"black\"/><text x=\"{px}\" y=\"{2}\" text-anchor=\"middle\">{3} s</text>",
                height - margin,
                height - margin + 5.0,
                height - margin + 18.0,
                10f64.powf(decade)
            );
            decade += 1.0;
        }
        for e in std::iter::once(0.0).chain((0..=self.top as i32).map(|p| 10f64.powi(p))) {
            let _ = writeln!(
                svg,
                "<text x=\"{}\" y=\"{}\" text-anchor=\"end\">{}</text>",
                margin - 6.0,
                self.y(e) + 4.0,
                e
            );
        }
        let _ = writeln!(
            svg,
            "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">seconds (log scale)</text><text x=\"16\" y=\"{}\" transform=\"rotate(-90 16 {})\" text-anchor=\"middle\">(caster, light) pairs, log scale</text>",
            width / 2.0,
            height - 24.0,
            height / 2.0,
            height / 2.0
        );
    }

    /// Each row's marker position in `series`: settings at the same place
    /// are nudged apart sideways, so each stays visible.
    fn markers(&self, rows: &[Row], series: Series) -> Vec<(f64, f64)> {
        let mut placed: Vec<(f64, f64)> = Vec::new();
        for row in rows {
            let (mut px, py) = (self.x(row.seconds), self.y(series.errors(row) as f64));
            while placed
                .iter()
                .any(|&(qx, qy)| (qx - px).abs() < 9.0 && (qy - py).abs() < 9.0)
            {
                px += 9.0;
            }
            placed.push((px, py));
        }
        placed
    }

    /// The legend, in one row centred in the band between the title and
    /// the plot.
    fn write_legend(&self, svg: &mut String) {
        let y = self.margin - 22.0;
        let mut x = (self.width - legend_width()) / 2.0;
        for (marker, text) in LEGEND {
            let centre = x + 6.0;
            let _ = match marker {
                LegendMarker::Series(series) => {
                    let (fill, r) = series.fill_and_radius();
                    write!(
                        svg,
                        "<circle cx=\"{centre}\" cy=\"{y}\" r=\"{r}\" fill=\"{fill}\" stroke=\"{}\" stroke-width=\"1.5\"/>",
                        series.colour()
                    )
                }
                LegendMarker::Square => write!(
                    svg,
                    "<rect x=\"{}\" y=\"{}\" width=\"10\" height=\"10\" fill=\"none\" stroke=\"#555\" stroke-width=\"1.5\"/>",
                    centre - 5.0,
                    y - 5.0
                ),
            };
            let _ = writeln!(
                svg,
                "<text x=\"{}\" y=\"{}\">{text}</text>",
                x + LEGEND_MARKER_GAP,
                y + 4.0
            );
            x += LEGEND_MARKER_GAP + text_width(text, FONT_SIZE) + LEGEND_ENTRY_GAP;
        }
    }
}

/// The two errors the plot draws. False keeps are rings around where false
/// culls are dots, so a setting with both at one value shows both.
#[derive(Debug, Clone, Copy)]
enum Series {
    FalseCulls,
    FalseKeeps,
}

impl Series {
    const ALL: [Series; 2] = [Series::FalseCulls, Series::FalseKeeps];

    fn index(self) -> usize {
        self as usize
    }

    fn colour(self) -> &'static str {
        match self {
            Series::FalseCulls => "#c0392b",
            Series::FalseKeeps => "#2471a3",
        }
    }

    fn errors(self, row: &Row) -> u64 {
        match self {
            Series::FalseCulls => row.false_culls,
            Series::FalseKeeps => row.false_keeps,
        }
    }

    /// Dots are filled and small, rings hollow and large.
    fn fill_and_radius(self) -> (&'static str, f64) {
        match self {
            Series::FalseCulls => (self.colour(), 3.5),
            Series::FalseKeeps => ("none", 6.0),
        }
    }
}

/// One marker per row: a square for a setting with refinement, else a
/// circle.
fn write_markers(svg: &mut String, rows: &[Row], series: Series, markers: &[(f64, f64)]) {
    let colour = series.colour();
    let (fill, r) = series.fill_and_radius();
    for (row, &(px, py)) in rows.iter().zip(markers) {
        let marker = if row.setting.refine_samples > 0 {
            format!(
                "<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"{fill}\" stroke=\"{colour}\" stroke-width=\"1.5\"/>",
                px - r,
                py - r,
                2.0 * r,
                2.0 * r
            )
        } else {
            format!("<circle cx=\"{px}\" cy=\"{py}\" r=\"{r}\" fill=\"{fill}\" stroke=\"{colour}\" stroke-width=\"1.5\"/>")
        };
        let _ = writeln!(svg, "{marker}");
    }
}

/// Each label where `place_labels` put it, with a leader line from its
/// point to the nearest point of its box.
fn write_labels(svg: &mut String, labels: &[PlacedLabel]) {
    for label in labels {
        let (px, py) = label.point;
        let (lx, ly) = label.at.leader_end(label.point);
        // The baseline leaves the descenders inside the box.
        let _ = writeln!(
            svg,
            "<line x1=\"{px}\" y1=\"{py}\" x2=\"{lx}\" y2=\"{ly}\" stroke=\"#bbb\"/><text x=\"{}\" y=\"{}\" fill=\"#555\">{}</text>",
            label.at.x0,
            label.at.y1 - 3.0,
            label.text
        );
    }
}

/// A label's or marker's box in SVG pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LabelBox {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

impl LabelBox {
    fn around(x: f64, y: f64, r: f64) -> LabelBox {
        LabelBox {
            x0: x - r,
            y0: y - r,
            x1: x + r,
            y1: y + r,
        }
    }

    pub fn overlaps(&self, other: &LabelBox) -> bool {
        self.x0 < other.x1 && other.x0 < self.x1 && self.y0 < other.y1 && other.y0 < self.y1
    }

    fn inside(&self, outer: &LabelBox) -> bool {
        self.x0 >= outer.x0 && self.x1 <= outer.x1 && self.y0 >= outer.y0 && self.y1 <= outer.y1
    }

    fn holds(&self, (x, y): (f64, f64)) -> bool {
        (self.x0..=self.x1).contains(&x) && (self.y0..=self.y1).contains(&y)
    }

    /// Where a leader line from `point` meets the label: the box's point
    /// nearest it, so the line never runs through the text.
    fn leader_end(&self, (px, py): (f64, f64)) -> (f64, f64) {
        (px.clamp(self.x0, self.x1), py.clamp(self.y0, self.y1))
    }

    /// Whether the segment `a`–`b` passes through the box's inside
    /// (Liang–Barsky clipping; touching an edge does not count).
    fn crossed_by(&self, (ax, ay): (f64, f64), (bx, by): (f64, f64)) -> bool {
        let (dx, dy) = (bx - ax, by - ay);
        let (mut enter, mut leave) = (0.0f64, 1.0f64);
        for (p, q) in [
            (-dx, ax - self.x0),
            (dx, self.x1 - ax),
            (-dy, ay - self.y0),
            (dy, self.y1 - ay),
        ] {
            if p == 0.0 {
                if q <= 0.0 {
                    return false;
                }
            } else if p < 0.0 {
                enter = enter.max(q / p);
            } else {
                leave = leave.min(q / p);
            }
        }
        enter < leave
    }
}

/// Gaps (SVG pixels, beyond 8) tried between a point and its label.
const LABEL_SHIFTS: [f64; 6] = [0.0, 40.0, 80.0, 120.0, 160.0, 200.0];

/// Lines above and below its point a label may go.
const LABEL_LINES: i32 = 20;

/// The grid (SVG pixels) on which a numbered label with no free place
/// near its point searches the whole area.
const FREE_STEP: f64 = 4.0;

/// Rounds of moving each label that still clashes to its best place
/// among all the others.
const REPAIR_ROUNDS: usize = 8;

/// A point's label as drawn: the row's label, or its number when no free
/// place was found for the label (the key below the plot names it).
#[derive(Debug, Clone, PartialEq)]
struct PlacedLabel {
    point: (f64, f64),
    text: String,
    at: LabelBox,
}

/// A box for each point's label inside `area` that lies on no other label
/// and no marker, whose leader line crosses no other label and is crossed
/// by no other leader. Each label takes the nearest free place (beside its
/// point, above or below it, or in line with other points' labels); the
/// labels that still clash are then moved, each to its best place among
/// all the others, and those that clash after that become their row's
/// number (1-based), short enough to fit. A number that still finds no
/// free place is not drawn: the key below the plot gives its row's values
/// instead. Returns the drawn labels in point order and the points the key
/// names, in point order.
fn place_labels(
    points: &[(f64, f64)],
    labels: &[&str],
    markers: &[LabelBox],
    area: LabelBox,
) -> (Vec<PlacedLabel>, Vec<(usize, Keyed)>) {
    let layout = LabelLayout {
        points,
        markers,
        area,
    };
    let mut texts: Vec<String> = labels.iter().map(|l| l.to_string()).collect();
    let mut boxes: Vec<Option<LabelBox>> = vec![None; points.len()];
    for i in 0..points.len() {
        boxes[i] = Some(layout.best(i, &texts[i], &boxes).1);
    }
    let clashes_now = |boxes: &[Option<LabelBox>], i: usize| {
        boxes[i].map_or(0, |at| layout.clashes(i, &at, boxes))
    };
    for _ in 0..REPAIR_ROUNDS {
        let mut moved = false;
        for i in 0..points.len() {
            let now = clashes_now(&boxes, i);
            if now == 0 {
                continue;
            }
            let (fewer, at) = layout.best(i, &texts[i], &boxes);
            if fewer < now {
                boxes[i] = Some(at);
                moved = true;
            }
        }
        if !moved {
            break;
        }
    }
    let mut keyed = Vec::new();
    for i in 0..points.len() {
        if clashes_now(&boxes, i) == 0 {
            continue;
        }
        texts[i] = (i + 1).to_string();
        boxes[i] = layout.free(i, &texts[i], &boxes);
        keyed.push((
            i,
            if boxes[i].is_some() {
                Keyed::Numbered
            } else {
                Keyed::NotDrawn
            },
        ));
    }
    let placed = points
        .iter()
        .zip(texts)
        .zip(boxes)
        .filter_map(|((&point, text), at)| {
            Some(PlacedLabel {
                point,
                text,
                at: at?,
            })
        })
        .collect();
    (placed, keyed)
}

/// How a point the key below the plot names is marked on the plot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Keyed {
    /// By its row's number.
    Numbered,
    /// Not at all: even its number found no free place, so the key gives
    /// the row's values.
    NotDrawn,
}

/// What a label must keep clear of: the points (each label's leader starts
/// at its point), every marker, and the area labels may use.
struct LabelLayout<'a> {
    points: &'a [(f64, f64)],
    markers: &'a [LabelBox],
    area: LabelBox,
}

impl LabelLayout<'_> {
    /// The place for point `i`'s `text` with the fewest clashes against
    /// the other `boxes`, the nearest among equals.
    fn best(&self, i: usize, text: &str, boxes: &[Option<LabelBox>]) -> (usize, LabelBox) {
        let mut best: Option<((usize, f64), LabelBox)> = None;
        for (distance, candidate) in self.candidates(i, text_width(text, FONT_SIZE)) {
            let key = (self.clashes(i, &candidate, boxes), distance);
            if best.is_none_or(|(b, _)| key.0 < b.0 || (key.0 == b.0 && key.1 < b.1)) {
                best = Some((key, candidate));
            }
        }
        best.map(|((clashes, _), at)| (clashes, at))
            .expect("every point has candidates")
    }

    /// A place for point `i`'s `text` that clashes with nothing: the best
    /// of its candidates, else the nearest free place anywhere in the area
    /// (a short label's last resort, on a grid of [`FREE_STEP`] pixels).
    fn free(&self, i: usize, text: &str, boxes: &[Option<LabelBox>]) -> Option<LabelBox> {
        let (clashes, at) = self.best(i, text, boxes);
        if clashes == 0 {
            return Some(at);
        }
        let (w, (px, py)) = (text_width(text, FONT_SIZE), self.points[i]);
        let columns = ((self.area.x1 - self.area.x0 - w) / FREE_STEP).max(0.0) as usize;
        let rows = ((self.area.y1 - self.area.y0 - LINE_HEIGHT) / FREE_STEP).max(0.0) as usize;
        let mut nearest: Option<(f64, LabelBox)> = None;
        for row in 0..=rows {
            for column in 0..=columns {
                let (x0, y0) = (
                    self.area.x0 + column as f64 * FREE_STEP,
                    self.area.y0 + row as f64 * FREE_STEP,
                );
                let candidate = LabelBox {
                    x0,
                    y0,
                    x1: x0 + w,
                    y1: y0 + LINE_HEIGHT,
                };
                let (lx, ly) = candidate.leader_end((px, py));
                let distance = (lx - px).hypot(ly - py);
                if nearest.is_none_or(|(d, _)| distance < d)
                    && self.clashes(i, &candidate, boxes) == 0
                {
                    nearest = Some((distance, candidate));
                }
            }
        }
        nearest.map(|(_, at)| at)
    }

    /// Boxes of width `w` for point `i`'s label, each with its distance:
    /// on the point's line and up to [`LABEL_LINES`] lines above and below
    /// it, right or left of the point (by [`LABEL_SHIFTS`], or level with
    /// another point on that side, so that labels of a crowd line up in a
    /// column their leaders do not cross), and centred on it off its line.
    fn candidates(&self, i: usize, w: f64) -> Vec<(f64, LabelBox)> {
        let (px, py) = self.points[i];
        let beyond = |right: bool| -> Vec<f64> {
            let level = self.points.iter().filter_map(|&(qx, _)| {
                let gap = if right { qx - px } else { px - qx };
                (gap > 0.0).then_some(gap)
            });
            LABEL_SHIFTS.iter().copied().chain(level).collect()
        };
        let (right, left) = (beyond(true), beyond(false));
        let mut found = Vec::new();
        for lines in 0..=2 * LABEL_LINES {
            // 0, −1, +1, −2, +2, … lines from the point.
            let line = f64::from((lines + 1) / 2) * if lines % 2 == 1 { -1.0 } else { 1.0 };
            let dy = line * LINE_HEIGHT;
            let at = |x0: f64| LabelBox {
                x0,
                y0: py + dy - LINE_HEIGHT / 2.0,
                x1: x0 + w,
                y1: py + dy + LINE_HEIGHT / 2.0,
            };
            found.extend(right.iter().map(|&s| (dy.abs() + s, at(px + 8.0 + s))));
            found.extend(left.iter().map(|&s| (dy.abs() + s, at(px - 8.0 - w - s))));
            if line != 0.0 {
                found.push((dy.abs(), at(px - w / 2.0)));
            }
        }
        found
    }

    /// How many markers point `i`'s label at `candidate` would lie on or
    /// its leader cross, and how many other labels it would lie on or cross
    /// leaders with, plus one when it leaves the area.
    fn clashes(&self, i: usize, candidate: &LabelBox, boxes: &[Option<LabelBox>]) -> usize {
        let point = self.points[i];
        let leader = candidate.leader_end(point);
        // A marker the leader starts in is its own (or one on it).
        let on_markers = self
            .markers
            .iter()
            .filter(|m| m.overlaps(candidate) || (!m.holds(point) && m.crossed_by(point, leader)))
            .count();
        let with_labels = boxes
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .filter_map(|(j, b)| b.map(|b| (self.points[j], b)))
            .filter(|(other, b)| {
                b.overlaps(candidate)
                    || b.crossed_by(point, leader)
                    || candidate.crossed_by(*other, b.leader_end(*other))
            })
            .count();
        on_markers + with_labels + usize::from(!candidate.inside(&self.area))
    }
}

#[cfg(test)]
mod label_tests {
    use super::*;

    #[test]
    fn crowded_labels_never_overlap_each_other_or_markers() {
        // Eleven settings within a few pixels of each other (the sweep's
        // low-density rows often are).
        let points: Vec<(f64, f64)> = (0..11)
            .map(|i| (300.0 + i as f64 * 3.0, 200.0 + (i % 3) as f64))
            .collect();
        let names: Vec<String> = (0..11)
            .map(|i| format!("density x{i}, refine 16"))
            .collect();
        let labels: Vec<&str> = names.iter().map(String::as_str).collect();
        let markers: Vec<LabelBox> = points
            .iter()
            .map(|&(x, y)| LabelBox::around(x, y, 6.0))
            .collect();
        let plot = LabelBox {
            x0: 70.0,
            y0: 70.0,
            x1: 750.0,
            y1: 390.0,
        };
        let (placed, keyed) = place_labels(&points, &labels, &markers, plot);
        assert_eq!(placed.len(), 11);
        for (i, a) in placed.iter().enumerate() {
            assert!(a.at.inside(&plot), "{a:?}");
            assert!(
                markers.iter().all(|m| !m.overlaps(&a.at)),
                "label {i} on a marker"
            );
            for (j, b) in placed.iter().enumerate().filter(|&(j, _)| j != i) {
                assert!(!a.at.overlaps(&b.at), "{a:?} and {b:?}");
                assert!(
                    !b.at.crossed_by(a.point, a.at.leader_end(a.point)),
                    "the leader of {i} crosses label {j}"
                );
            }
        }
        // A label is its row's number only where it found no place.
        assert!(keyed.len() < 11, "{keyed:?}");
        for (i, label) in placed.iter().enumerate() {
            let expected = if keyed.contains(&(i, Keyed::Numbered)) {
                (i + 1).to_string()
            } else {
                names[i].clone()
            };
            assert_eq!(label.text, expected);
        }
    }

    #[test]
    fn seeded_crowds_draw_only_labels_that_clash_with_nothing() {
        // Twelve points scattered in a small patch of the plot, as measured
        // run times crowd them; a fixed linear congruential sequence, so a
        // failure can be replayed.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = |range: f64| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * range
        };
        let area = LabelBox {
            x0: 70.0,
            y0: 70.0,
            x1: 750.0,
            y1: 390.0,
        };
        let names: Vec<String> = (0..12)
            .map(|i| format!("density x{i}, refine 16"))
            .collect();
        let labels: Vec<&str> = names.iter().map(String::as_str).collect();
        let mut not_drawn = 0;
        for crowd in 0..200 {
            let (cx, cy) = (100.0 + next(500.0), 100.0 + next(250.0));
            let points: Vec<(f64, f64)> = (0..12)
                .map(|_| (cx + next(120.0), cy + next(60.0)))
                .collect();
            // Each row has two markers: the second series lies on the
            // first or on the axis.
            let markers: Vec<LabelBox> = points
                .iter()
                .flat_map(|&(x, y)| [LabelBox::around(x, y, 6.0), LabelBox::around(x, 360.0, 6.0)])
                .collect();
            let (placed, keyed) = place_labels(&points, &labels, &markers, area);
            let layout = LabelLayout {
                points: &points,
                markers: &markers,
                area,
            };
            let mut boxes: Vec<Option<LabelBox>> = vec![None; points.len()];
            let drawn: Vec<usize> = (0..points.len())
                .filter(|i| !keyed.contains(&(*i, Keyed::NotDrawn)))
                .collect();
            assert_eq!(placed.len(), drawn.len(), "crowd {crowd}");
            for (&i, label) in drawn.iter().zip(&placed) {
                assert_eq!(label.point, points[i], "crowd {crowd}");
                boxes[i] = Some(label.at);
            }
            for &i in &drawn {
                assert_eq!(
                    layout.clashes(i, &boxes[i].unwrap(), &boxes),
                    0,
                    "crowd {crowd}, label {i}"
                );
            }
            not_drawn += keyed.iter().filter(|k| k.1 == Keyed::NotDrawn).count();
        }
        // Leaving a label off is the last resort: in crowds this dense
        // (twelve points in 120 × 60 pixels, each with two markers) about
        // one label in a hundred finds no place its leader reaches.
        assert!(
            not_drawn * 20 < 200 * 12,
            "{not_drawn} labels not drawn in 200 crowds"
        );
    }

    #[test]
    fn a_leader_line_ends_on_the_near_side_of_its_label() {
        let label = LabelBox {
            x0: 10.0,
            y0: 0.0,
            x1: 50.0,
            y1: 13.0,
        };
        assert_eq!(label.leader_end((0.0, 6.5)), (10.0, 6.5));
        assert_eq!(label.leader_end((60.0, 20.0)), (50.0, 13.0));
        assert_eq!(label.leader_end((30.0, -9.0)), (30.0, 0.0));
        assert!(label.crossed_by((0.0, 6.5), (60.0, 6.5)));
        assert!(!label.crossed_by((0.0, 6.5), (10.0, 6.5)));
        assert!(!label.crossed_by((0.0, -1.0), (60.0, -1.0)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn scaling_a_light_densifies_its_grid() {
        let sun = LightSettings {
            name: "sun".into(),
            kind: LightKind::Directional {
                direction: DVec3::NEG_Y,
                texel_size: 1.0,
            },
        };
        match scale_light(&sun, 4.0).kind {
            LightKind::Directional { texel_size, .. } => assert_eq!(texel_size, 0.25),
            _ => unreachable!(),
        }
        let point = LightSettings {
            name: "p".into(),
            kind: LightKind::Point {
                position: DVec3::ZERO,
                near: 0.1,
                far: 10.0,
                resolution: 6,
            },
        };
        for (density, expected) in [(0.25, 2), (0.1, 1), (2.0, 12)] {
            match scale_light(&point, density).kind {
                LightKind::Point { resolution, .. } => assert_eq!(resolution, expected),
                _ => unreachable!(),
            }
        }
    }

    #[test]
    fn ladder_has_the_densities_supersampling_and_refinement() {
        let ladder = ladder(&SweepConfig::default());
        let densities: Vec<f64> = ladder
            .iter()
            .filter(|s| {
                s.supersample == 1
                    && s.refine_samples == 0
                    && !s.conservative
                    && s.filter_radius == 0
            })
            .map(|s| s.density)
            .collect();
        assert_eq!(densities, [0.25, 0.5, 1.0, 2.0, 4.0]);
        assert!(ladder.iter().any(|s| s.supersample == 2));
        assert_eq!(ladder.iter().filter(|s| s.refine_samples > 0).count(), 3);
        assert_eq!(ladder.iter().filter(|s| s.conservative).count(), 1);
        assert_eq!(ladder.iter().filter(|s| s.filter_radius == 1).count(), 1);
        assert_eq!(ladder[0].label(), "density x1/4");
    }
}
