//! `sweep`: errors against a denser reference, on a world whose answers are
//! known, and the files the command writes.

use crate::generated::fixture_dir;
use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::gen::Preset;
use shadowcull::sweep::{ladder, sweep, Row, SweepConfig, SweepReport};
use std::process::Command;

#[test]
fn sweep_counts_the_misses_of_a_caster_smaller_than_a_texel() {
    // 1 m texels straight down over a 16 m block; a 15 cm box at 0.80..0.95
    // on terrain. Texel centres per density d lie at (k + 0.5)/d: only
    // ×4 (… 0.875), 4×4 samples and the reference ×8 (0.8125, 0.9375) land
    // on the box; refinement aims at it directly. So the box is a false
    // cull at ×¼, ×½, ×1, ×2 and 2×2, and nowhere else; the terrain block is
    // never useful (nothing behind it) in any bake: no error.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let m = world.model(Mesh {
        groups: vec![(
            cube(Vec3::new(0.8, 1.0, 0.8), Vec3::new(0.95, 1.2, 0.95)),
            OPAQUE,
        )],
    });
    world.place((0, 0), &[m], DMat4::IDENTITY, true);
    let base = config(vec![directional(DVec3::NEG_Y, 1.0)]);
    let report = sweep(&world.scene, &base, &SweepConfig::default(), |_| {}).unwrap();
    assert_eq!(
        (report.reference.false_culls, report.reference.false_keeps),
        (0, 0)
    );
    let got: Vec<(String, u64, u64, u64)> = report
        .rows
        .iter()
        .map(|r| (r.label.clone(), r.false_culls, r.false_keeps, r.pairs))
        .collect();
    let expected = [
        ("density x1/4", 1),
        ("density x1/2", 1),
        ("density x1", 1),
        ("density x2", 1),
        ("density x4", 0),
        ("density x1, 2x2 samples", 1),
        ("density x1, 4x4 samples", 0),
        ("density x1/4, refine 64 + footprint x8", 0),
        ("density x1/2, refine 64 + footprint x8", 0),
        ("density x1, refine 64 + footprint x8", 0),
        // The box's beam meets it with terrain behind: kept.
        ("density x1, conservative", 0),
        // The box is never front-most at a ×1 centre, so no margin helps.
        ("density x1, filter radius 1", 1),
    ]
    .map(|(label, culls)| (label.to_string(), culls, 0, 2));
    assert_eq!(got, expected);
    // The offset reference adds nothing here: every ×8 grid at any offset
    // lands two sample rows on the box, as the reference does.
    assert_eq!(report.offsets.len(), 3);
    for row in &report.rows {
        assert_eq!(
            (row.false_culls_any_offset, row.false_keeps_any_offset),
            (row.false_culls, row.false_keeps),
            "{}",
            row.label
        );
    }
    // Rays grow with the density squared: 16² texels at ×1.
    assert_eq!(report.rows[2].rays, 256);
    assert_eq!(report.rows[4].rays, 64 * 64);
    let csv = report.to_csv();
    assert_eq!(csv.lines().count(), 14, "header, reference, 12 rows");
    assert!(report.to_svg().starts_with("<svg") && report.to_svg().trim_end().ends_with("</svg>"));
}

#[test]
fn sweep_command_writes_csv_json_and_svg() {
    let out = tempfile::tempdir().unwrap();
    // The small fixture under one coarse light, so the ladder's ×4 rows stay
    // quick in the test profile.
    let settings = out.path().join("coarse.xml");
    std::fs::write(
        &settings,
        format!(
            "<shadowcull>\n\t<resPaths>\n\t\t<path>\t{}\t</path>\n\t</resPaths>\n\t<space>\tspaces/small\t</space>\n\t<lights>\n\t\t<light>\n\t\t\t<type>\tdirectional\t</type>\n\t\t\t<direction>\t-0.3 -1 0.2\t</direction>\n\t\t\t<texelSize>\t1.5\t</texelSize>\n\t\t</light>\n\t</lights>\n</shadowcull>\n",
            fixture_dir(Preset::Small).display()
        ),
    )
    .unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args([
            "sweep",
            settings.to_str().unwrap(),
            "--out",
            out.path().to_str().unwrap(),
            "--reference-density",
            "3",
            "--reference-refine-samples",
            "4",
            "--offset-references",
            "1",
        ])
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let table = String::from_utf8(output.stdout).unwrap();
    assert!(
        table.contains("false culls") && table.contains("density x1/4"),
        "{table}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("sweep.json")).unwrap()).unwrap();
    assert_eq!(json["rows"].as_array().unwrap().len(), 12);
    assert_eq!(json["reference"]["false_culls"], 0);
    let pairs = json["reference"]["pairs"].as_u64().unwrap();
    for row in json["rows"].as_array().unwrap() {
        assert_eq!(row["pairs"].as_u64(), Some(pairs));
        assert!(
            row["false_culls"].as_u64().unwrap() + row["false_keeps"].as_u64().unwrap() <= pairs
        );
    }
    let csv = std::fs::read_to_string(out.path().join("sweep.csv")).unwrap();
    assert!(csv.starts_with("label,density,supersample"));
    let svg = std::fs::read_to_string(out.path().join("sweep.svg")).unwrap();
    assert!(svg.contains("false culls") && svg.contains("</svg>"));
    assert_eq!(layout_problems(&svg), Vec::<String>::new(), "{svg}");
}

/// A report of the ladder with `seconds` and false culls per row (no
/// false keeps), against a reference of density x8.
fn report_of(rows: &[(f64, u64)]) -> SweepReport {
    let row = |setting: shadowcull::sweep::Setting, (seconds, false_culls): (f64, u64)| Row {
        label: setting.label(),
        setting,
        rays: 1000,
        seconds,
        false_culls,
        false_keeps: 0,
        false_culls_any_offset: false_culls,
        false_keeps_any_offset: 0,
        pairs: 549,
    };
    let ladder = ladder(&SweepConfig::default());
    assert_eq!(ladder.len(), rows.len());
    let reference = shadowcull::sweep::Setting {
        density: 8.0,
        refine_samples: 64,
        ..ladder[0]
    };
    SweepReport {
        reference: row(reference, (2.4, 0)),
        offsets: Vec::new(),
        rows: ladder
            .into_iter()
            .zip(rows.iter().copied())
            .map(|(s, r)| row(s, r))
            .collect(),
    }
}

#[test]
fn sweep_plot_keeps_its_legend_inside_and_its_labels_apart_near_zero() {
    // Most rows at zero errors and a few hundredths of a second apart, as
    // on the village: their labels crowd along the axis.
    let village = [
        (0.017, 102),
        (0.048, 41),
        (0.158, 9),
        (0.214, 3),
        (0.644, 0),
        (0.241, 3),
        (0.693, 0),
        (0.055, 0),
        (0.095, 0),
        (0.166, 0),
        (0.584, 0),
        (0.474, 2),
    ];
    // Every row at zero, within a factor of two in time.
    let all_zero: Vec<(f64, u64)> = (0..12).map(|i| (0.1 + 0.01 * i as f64, 0)).collect();
    // Every row at one time and one count: the densest crowd there is.
    let one_place = [(0.2, 3); 12];
    for rows in [&village[..], &all_zero, &one_place] {
        let report = report_of(rows);
        let svg = report.to_svg();
        assert_eq!(layout_problems(&svg), Vec::<String>::new(), "{svg}");
        // Every row is named: by its label at its point, or in the key.
        let texts: Vec<String> = texts(&svg).into_iter().map(|(t, _)| t).collect();
        for (i, row) in report.rows.iter().enumerate() {
            let keyed = format!("{}: {}", i + 1, row.label);
            assert!(
                texts
                    .iter()
                    .any(|t| *t == row.label || t.starts_with(&keyed)),
                "row {} ({}) is not named\n{svg}",
                i + 1,
                row.label
            );
        }
    }
}

/// A box in SVG pixels.
#[derive(Debug, Clone, Copy)]
struct Extent {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
}

impl Extent {
    fn overlaps(&self, o: &Extent) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.y0 < o.y1 && o.y0 < self.y1
    }

    fn shrunk(&self, by: f64) -> Extent {
        Extent {
            x0: self.x0 + by,
            y0: self.y0 + by,
            x1: self.x1 - by,
            y1: self.y1 - by,
        }
    }

    /// Whether the segment a–b passes through the box (Liang–Barsky).
    fn crossed_by(&self, (ax, ay): (f64, f64), (bx, by): (f64, f64)) -> bool {
        let (dx, dy) = (bx - ax, by - ay);
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for (p, q) in [
            (-dx, ax - self.x0),
            (dx, self.x1 - ax),
            (-dy, ay - self.y0),
            (dy, self.y1 - ay),
        ] {
            if p == 0.0 {
                if q < 0.0 {
                    return false;
                }
            } else if p < 0.0 {
                t0 = t0.max(q / p);
            } else {
                t1 = t1.min(q / p);
            }
        }
        t0 < t1
    }
}

/// The value of attribute `name` in the tag `tag`.
fn attribute<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
    let start = tag.find(&format!(" {name}=\""))? + name.len() + 3;
    tag[start..].split('"').next()
}

fn number(tag: &str, name: &str) -> f64 {
    attribute(tag, name).map_or(0.0, |v| v.parse().unwrap())
}

/// Where each `<text>` of `svg` lies, estimated generously (0.6 em a
/// character, ascent 0.8 em, descent 0.25 em), with its content.
fn texts(svg: &str) -> Vec<(String, Extent)> {
    let root_size = number(svg.split('>').next().unwrap(), "font-size");
    let mut found = Vec::new();
    for piece in svg.split("<text").skip(1) {
        let (tag, rest) = piece.split_once('>').unwrap();
        let content = rest.split("</text>").next().unwrap().to_string();
        let size = attribute(tag, "font-size").map_or(root_size, |v| v.parse().unwrap());
        let width = content.chars().count() as f64 * 0.6 * size;
        let (x, y) = (number(tag, "x"), number(tag, "y"));
        let start = match attribute(tag, "text-anchor") {
            Some("middle") => -width / 2.0,
            Some("end") => -width,
            _ => 0.0,
        };
        let extent = if attribute(tag, "transform").is_some_and(|t| t.starts_with("rotate(-90")) {
            // Turned to run upwards about its anchor.
            Extent {
                x0: x - 0.8 * size,
                y0: y - start - width,
                x1: x + 0.25 * size,
                y1: y - start,
            }
        } else {
            Extent {
                x0: x + start,
                y0: y - 0.8 * size,
                x1: x + start + width,
                y1: y + 0.25 * size,
            }
        };
        found.push((content, extent));
    }
    found
}

/// Markers (circles and squares) of the plot and its legend.
fn markers(svg: &str) -> Vec<Extent> {
    let mut found = Vec::new();
    for piece in svg.split("<circle").skip(1) {
        let tag = piece.split('>').next().unwrap();
        let (x, y, r) = (number(tag, "cx"), number(tag, "cy"), number(tag, "r"));
        found.push(Extent {
            x0: x - r,
            y0: y - r,
            x1: x + r,
            y1: y + r,
        });
    }
    for piece in svg.split("<rect").skip(1) {
        let tag = piece.split('>').next().unwrap();
        if attribute(tag, "width") == Some("100%") {
            continue;
        }
        let (x, y) = (number(tag, "x"), number(tag, "y"));
        found.push(Extent {
            x0: x,
            y0: y,
            x1: x + number(tag, "width"),
            y1: y + number(tag, "height"),
        });
    }
    found
}

/// What is wrong with the plot's layout: a text outside the viewBox, two
/// texts on each other, a text on a marker, a leader line through a text.
fn layout_problems(svg: &str) -> Vec<String> {
    let root = svg.split('>').next().unwrap();
    let Some(view) = attribute(root, "viewBox") else {
        return vec!["no viewBox".into()];
    };
    let view: Vec<f64> = view.split(' ').map(|v| v.parse().unwrap()).collect();
    let frame = Extent {
        x0: view[0],
        y0: view[1],
        x1: view[0] + view[2],
        y1: view[1] + view[3],
    };
    let texts = texts(svg);
    let markers = markers(svg);
    let mut problems = Vec::new();
    for (i, (content, at)) in texts.iter().enumerate() {
        if at.x0 < frame.x0 || at.y0 < frame.y0 || at.x1 > frame.x1 || at.y1 > frame.y1 {
            problems.push(format!("`{content}` {at:?} leaves the viewBox {frame:?}"));
        }
        for (other, at_other) in &texts[i + 1..] {
            if at.overlaps(at_other) {
                problems.push(format!("`{content}` lies on `{other}`"));
            }
        }
        if markers.iter().any(|m| m.overlaps(at)) {
            problems.push(format!("`{content}` lies on a marker"));
        }
    }
    for piece in svg.split("<line").skip(1) {
        let tag = piece.split('>').next().unwrap();
        if attribute(tag, "stroke") != Some("#bbb") {
            continue;
        }
        let (a, b) = (
            (number(tag, "x1"), number(tag, "y1")),
            (number(tag, "x2"), number(tag, "y2")),
        );
        for (content, at) in &texts {
            if at.shrunk(1.0).crossed_by(a, b) {
                problems.push(format!("a leader line {a:?}–{b:?} crosses `{content}`"));
            }
        }
    }
    problems
}
