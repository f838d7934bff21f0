//! `sweep`: errors against a denser reference, on a world whose answers are
//! known, and the files the command writes.

use crate::generated::fixture_dir;
use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::gen::Preset;
use shadowcull::sweep::{sweep, SweepConfig};
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
}
