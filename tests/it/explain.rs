//! `explain`: its verdict equals the bake's for every caster of `village`
//! and every light; its reasons on micro worlds built to be hidden, to have
//! nothing behind, and to have only alpha-tested or receiver-only geometry
//! behind; the command line's output, JSON and errors.

use crate::generated::{fixture_dir, load_world};
use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::bake::setup::BakeWorld;
use shadowcull::bake::{self, BakeConfig, GridMode, Silent};
use shadowcull::explain::{self, CasterExplanation, Explanation, Reason, Verdict};
use shadowcull::formats::png_write;
use shadowcull::gen::Preset;
use shadowcull::render::{self, TexelMark};
use std::process::{Command, Output};

const DOWN: DVec3 = DVec3::new(0.0, -1.0, 0.0);

/// Every caster of `scene` explained for light `light`.
fn explain_all(scene: &shadowcull::scene::Scene, config: &BakeConfig, light: usize) -> Explanation {
    let world = BakeWorld::new(scene);
    let ids: Vec<u32> = (0..world.casters.len() as u32).collect();
    explain::explain(&world, config, light, &ids).expect("explain")
}

/// The counts hold together: useful texels are front texels, every front
/// texel that is not useful has one class behind it, every hidden texel
/// one hider.
fn check_counts(c: &CasterExplanation) {
    let t = &c.texels;
    let b = &t.behind;
    assert!(t.useful <= t.front, "{c:?}");
    if c.receiver_only {
        assert_eq!(t.front + t.hidden, 0, "a receiver is never a caster: {c:?}");
    } else {
        assert_eq!(t.front + t.hidden, t.hit, "{c:?}");
    }
    let behind = b.nothing + b.below_ground + b.facing_away + b.alpha_tested;
    assert_eq!(
        behind + b.receiver_only_alpha_tested,
        t.front - t.useful,
        "{c:?}"
    );
    let hiders: u64 = t.hidden_by.iter().map(|h| h.texels).sum();
    assert_eq!(hiders + t.hidden_by_others, t.hidden, "{c:?}");
    assert_eq!(
        c.grid_verdict == Verdict::Useful,
        t.useful > 0 || c.reason == Reason::Unmodelled
    );
}

/// Every caster of village for every light, with the bake's default
/// options and with each option that changes a verdict without
/// refinement's cost: the explanation's bake verdict is an independent
/// bake's mask; without modes the grid pass's own verdict is too, with the
/// filter margin every caster it adds is named as kept by it.
#[test]
fn every_village_caster_gets_the_bakes_verdict_for_every_light() {
    let settings = fixture_dir(Preset::Village).join("bake.xml");
    let scene = load_world(&settings);
    let file_settings = shadowcull::files::read_bake_settings(&settings).unwrap();
    let plain = BakeConfig::from_settings(&file_settings);
    let options = [
        plain.clone(),
        BakeConfig {
            supersample: 2,
            ..plain.clone()
        },
        BakeConfig {
            filter_radius: 1,
            ..plain.clone()
        },
    ];
    let mut seen = std::collections::BTreeSet::new();
    let mut kept_by_margin = 0;
    for config in &options {
        let baked = bake::bake(&scene, config, &Silent).expect("bake");
        for light in 0..config.lights.len() {
            let explanation = explain_all(&scene, config, light);
            assert!(!explanation.disagrees(), "light {light}");
            assert_eq!(explanation.supersample, config.supersample);
            assert_eq!(explanation.filter_radius, config.filter_radius);
            let bit = 1u32 << config.bit(light);
            for caster in &explanation.casters {
                check_counts(caster);
                let useful = baked.masks[caster.id as usize] & bit != 0;
                let at = format!("light {light} caster {} {config:?}", caster.caster);
                assert_eq!(caster.bake_verdict == Verdict::Useful, useful, "{at}");
                let grid_useful = caster.grid_verdict == Verdict::Useful;
                if config.filter_radius == 0 {
                    assert_eq!(grid_useful, useful, "{at}");
                    assert_eq!(caster.kept_by, None, "{at}");
                } else if useful && !grid_useful {
                    assert_eq!(caster.kept_by, Some("the filter margin"), "{at}");
                    kept_by_margin += 1;
                } else {
                    assert!(useful || !grid_useful, "the margin only adds: {at}");
                }
                seen.insert(format!("{:?}", caster.reason));
            }
        }
    }
    // Houses stand on the terrain; the terrain is the lowest surface, with
    // nothing behind it.
    for reason in [Reason::SomethingBehind, Reason::NothingBehind] {
        assert!(
            seen.contains(&format!("{reason:?}")),
            "{reason:?} in {seen:?}"
        );
    }
    assert!(kept_by_margin > 0, "the filter margin keeps some caster");
}

fn opaque(triangles: Vec<[Vec3; 3]>) -> Mesh {
    Mesh {
        groups: vec![(triangles, OPAQUE)],
    }
}

fn canopy(triangles: Vec<[Vec3; 3]>) -> Mesh {
    Mesh {
        groups: vec![(triangles, CANOPY)],
    }
}

/// `world`'s explanation for a sun straight down with half-metre texels,
/// each caster's verdict checked against a bake (with its oracle check).
fn explain_micro(world: &World) -> Explanation {
    let config = config(vec![directional(DOWN, 0.5)]);
    let explanation = explain_all(&world.scene, &config, 0);
    let baked = run(world, &config);
    for caster in &explanation.casters {
        check_counts(caster);
        assert!(!caster.disagrees, "{caster:?}");
        let useful = baked.masks[caster.id as usize] & 1 != 0;
        assert_eq!(caster.grid_verdict == Verdict::Useful, useful, "{caster:?}");
    }
    explanation
}

fn of(explanation: &Explanation, world: &World, instance: usize) -> CasterExplanation {
    let name = name(world, instance);
    let found = explanation.casters.iter().find(|c| c.caster == name);
    found.unwrap_or_else(|| panic!("{name} explained")).clone()
}

/// Group 0 of `instance` as `--caster` names it.
fn name(world: &World, instance: usize) -> String {
    let placed = &world.scene.instances[instance];
    format!(
        "{}:{}:0",
        world.scene.chunks[placed.chunk].name, placed.index
    )
}

/// Flat terrain at 0; box A (4..12 across, y 4..5) over box B (6..8
/// across, y 1..2): every ray down that meets B meets A first, so B is
/// hidden by A alone; A has the terrain or B behind it; the terrain has
/// nothing behind it where it is first. Returns the world, A and B.
fn box_over_box() -> (World, usize, usize) {
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let a = world.model(opaque(cube(
        Vec3::new(4.0, 4.0, 4.0),
        Vec3::new(12.0, 5.0, 12.0),
    )));
    let b = world.model(opaque(cube(
        Vec3::new(6.0, 1.0, 6.0),
        Vec3::new(8.0, 2.0, 8.0),
    )));
    let a = world.place((0, 0), &[a], DMat4::IDENTITY, true);
    let b = world.place((0, 0), &[b], DMat4::IDENTITY, true);
    (world, a, b)
}

#[test]
fn a_caster_under_a_nearer_one_is_hidden_and_the_nearer_one_named() {
    let (world, a, b) = box_over_box();
    let explanation = explain_micro(&world);

    let hidden = of(&explanation, &world, b);
    assert_eq!(hidden.grid_verdict, Verdict::Culled);
    assert_eq!(hidden.reason, Reason::Hidden);
    // 2 m × 2 m at 0.5 m texels: 16 texel centres, give or take an edge row.
    assert!((9..=25).contains(&hidden.texels.hit), "{hidden:?}");
    assert_eq!(hidden.texels.front, 0);
    assert_eq!(hidden.texels.hidden, hidden.texels.hit);
    assert_eq!(hidden.texels.hidden_by.len(), 1, "{hidden:?}");
    assert_eq!(hidden.texels.hidden_by[0].caster, name(&world, a));
    assert_eq!(hidden.texels.hidden_by[0].texels, hidden.texels.hit);

    let front = of(&explanation, &world, a);
    assert_eq!(front.reason, Reason::SomethingBehind);
    assert_eq!(front.texels.useful, front.texels.front);
    assert!(front.texels.front >= 225, "8 m square: about 256 texels");

    let terrain = explanation
        .casters
        .iter()
        .find(|c| c.caster.ends_with(":terrain"))
        .unwrap();
    assert_eq!(terrain.reason, Reason::NothingBehind);
    assert_eq!(terrain.texels.behind.nothing, terrain.texels.front);
}

/// No terrain. Quad Q (facing up, y 2) alone: nothing behind it at all.
/// Box C (y 1..2) elsewhere: its bottom faces away from the light, so its
/// rays meet only a turned-away face after its top.
#[test]
fn a_caster_with_nothing_behind_says_what_its_rays_meet_after_it() {
    let mut world = World::new(1, 1);
    let q = world.model(opaque(quad_up(2.0, 2.0, 6.0, 6.0, 2.0)));
    let c = world.model(opaque(cube(
        Vec3::new(10.0, 1.0, 10.0),
        Vec3::new(12.0, 2.0, 12.0),
    )));
    let q = world.place((0, 0), &[q], DMat4::IDENTITY, true);
    let c = world.place((0, 0), &[c], DMat4::IDENTITY, true);
    let explanation = explain_micro(&world);

    let quad = of(&explanation, &world, q);
    assert_eq!(quad.grid_verdict, Verdict::Culled);
    assert_eq!(quad.reason, Reason::NothingBehind);
    assert!(quad.texels.front >= 49, "4 m square: about 64 texels");
    assert_eq!(quad.texels.hidden, 0);
    assert_eq!(quad.texels.behind.nothing, quad.texels.front);

    let cube = of(&explanation, &world, c);
    assert_eq!(cube.reason, Reason::NothingBehind);
    assert!(cube.texels.front >= 9);
    assert_eq!(cube.texels.behind.facing_away, cube.texels.front);
}

/// No terrain. An alpha-tested canopy (y 6) over opaque quad T (y 3) over
/// a second alpha-tested layer L (y 1), both layers covering T. The All
/// pass: the canopy is first with T and L behind (useful), T is hidden.
/// The Opaque pass: T is first, and L has dropped out: nothing behind.
/// So T is culled, front where the canopy is not counted, with only
/// alpha-tested geometry behind it (docs/contract.md §4).
#[test]
fn only_alpha_tested_geometry_behind_does_not_keep_a_caster() {
    for receiver_layer in [false, true] {
        let mut world = World::new(1, 1);
        let top = world.model(canopy(quad_up(1.0, 1.0, 15.0, 15.0, 6.0)));
        let t = world.model(opaque(quad_up(5.0, 5.0, 9.0, 9.0, 3.0)));
        let layer = world.model(canopy(quad_up(1.0, 1.0, 15.0, 15.0, 1.0)));
        let top = world.place((0, 0), &[top], DMat4::IDENTITY, true);
        let t = world.place((0, 0), &[t], DMat4::IDENTITY, true);
        let layer = world.place((0, 0), &[layer], DMat4::IDENTITY, !receiver_layer);
        let explanation = explain_micro(&world);
        assert_eq!(explanation.passes, "all_and_opaque");

        let target = of(&explanation, &world, t);
        assert_eq!(target.grid_verdict, Verdict::Culled, "{target:?}");
        assert_eq!(target.reason, Reason::NothingBehind);
        assert!(target.texels.front >= 49);
        let behind = target.texels.behind;
        let counted = match receiver_layer {
            false => behind.alpha_tested,
            true => behind.receiver_only_alpha_tested,
        };
        assert_eq!(counted, target.texels.front, "{target:?}");
        assert_eq!(
            of(&explanation, &world, top).reason,
            Reason::SomethingBehind
        );
        // The layer: under the canopy in the All pass, out of the Opaque one.
        let under = of(&explanation, &world, layer);
        match receiver_layer {
            false => {
                assert_eq!(under.reason, Reason::Hidden);
                assert_eq!(under.texels.hidden_by[0].caster, name(&world, top));
            }
            true => assert_eq!(under.reason, Reason::ReceiverOnly),
        }
    }
}

/// No terrain. Opaque quad T (y 3) over an opaque receiver-only quad R
/// (y 1): a receiver behind counts (docs/contract.md §4), so T is useful
/// wherever it is first; R is never a caster.
#[test]
fn receiver_only_geometry_behind_keeps_a_caster() {
    let mut world = World::new(1, 1);
    let t = world.model(opaque(quad_up(5.0, 5.0, 9.0, 9.0, 3.0)));
    let r = world.model(opaque(quad_up(1.0, 1.0, 15.0, 15.0, 1.0)));
    let t = world.place((0, 0), &[t], DMat4::IDENTITY, true);
    let r = world.place((0, 0), &[r], DMat4::IDENTITY, false);
    let explanation = explain_micro(&world);
    let target = of(&explanation, &world, t);
    assert_eq!(target.reason, Reason::SomethingBehind);
    assert_eq!(target.texels.useful, target.texels.front);
    let receiver = of(&explanation, &world, r);
    assert_eq!(receiver.grid_verdict, Verdict::Culled);
    assert_eq!(receiver.reason, Reason::ReceiverOnly);
    assert!(receiver.receiver_only);
}

/// A box far smaller than a texel (2 cm) over flat terrain, placed where
/// no texel centre of `config`'s light 0 projects into its footprint.
fn tiny_between_centres(config: &BakeConfig) -> (World, usize) {
    let tiny_at = |x: f32| {
        let mut world = World::new(1, 1);
        world.terrain((0, 0), |_, _| 0.0);
        let (lo, hi) = (Vec3::new(x, 1.0, x), Vec3::new(x + 0.02, 1.02, x + 0.02));
        let m = world.model(opaque(cube(lo, hi)));
        let m = world.place((0, 0), &[m], DMat4::IDENTITY, true);
        (world, m, lo.as_dvec3(), hi.as_dvec3())
    };
    // Corners of the footprint in texel units; a centre lies at k + 0.5.
    let misses_every_centre = |world: &World, lo: DVec3, hi: DVec3| {
        let baked = BakeWorld::new(&world.scene);
        let setup = shadowcull::bake::setup::LightSetup::new(&baked, config, 0).unwrap();
        let corners: Vec<(f64, f64)> = [(lo.x, lo.z), (hi.x, lo.z), (lo.x, hi.z), (hi.x, hi.z)]
            .iter()
            .map(|&(x, z)| setup.grid.project_point(0, DVec3::new(x, hi.y, z)).unwrap())
            .collect();
        let span = |pick: fn(&(f64, f64)) -> f64| {
            let values = corners.iter().map(pick);
            let (min, max) = values.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
            (min - 0.5).floor() == (max - 0.5).floor()
        };
        span(|c| c.0) || span(|c| c.1)
    };
    (0..8)
        .map(|step| tiny_at(5.0 + step as f32 * 0.5))
        .find(|(world, _, lo, hi)| misses_every_centre(world, *lo, *hi))
        .map(|(world, m, _, _)| (world, m))
        .expect("a placement between centres")
}

/// The grid's centre rays miss a box between them (4 m texels), and the
/// conservative grid pass (every texel's beam, terrain behind) keeps it.
#[test]
fn a_caster_the_grid_misses_is_named_and_the_mode_that_keeps_it() {
    let config = BakeConfig {
        grid_mode: GridMode::Conservative,
        ..config(vec![directional(DOWN, 4.0)])
    };
    let (world, m) = tiny_between_centres(&config);
    let explanation = explain_all(&world.scene, &config, 0);
    assert!(explanation.conservative && !explanation.disagrees());
    let tiny = of(&explanation, &world, m);
    assert_eq!(tiny.texels.hit, 0, "{tiny:?}");
    assert_eq!(tiny.reason, Reason::NeverHit);
    assert_eq!(tiny.grid_verdict, Verdict::Culled);
    assert_eq!(tiny.bake_verdict, Verdict::Useful);
    assert_eq!(tiny.kept_by, Some("the conservative grid pass"));

    // Refinement aims rays at the box's own surface, with terrain behind.
    let refined = BakeConfig {
        grid_mode: GridMode::Centres,
        refine_samples: 64,
        refine_density: 8,
        ..config.clone()
    };
    let explanation = explain_all(&world.scene, &refined, 0);
    assert!(explanation.refine && !explanation.conservative);
    let tiny = of(&explanation, &world, m);
    assert_eq!(tiny.grid_verdict, Verdict::Culled);
    assert_eq!(tiny.bake_verdict, Verdict::Useful, "{tiny:?}");
    assert_eq!(tiny.kept_by, Some("refinement"));
}

/// Pixels per [`TexelMark`] (in `TexelMark::ALL` order) of a PNG, and the
/// pixels in any other colour that is not grey.
fn marked_pixels(png_bytes: &[u8]) -> ([u64; 3], u64) {
    let decoder = png::Decoder::new(std::io::Cursor::new(png_bytes));
    let mut reader = decoder.read_info().expect("a PNG");
    let mut rgb = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut rgb).expect("its pixels");
    assert_eq!(info.color_type, png::ColorType::Rgb);
    let mut counts = [0u64; 3];
    let mut other = 0;
    for pixel in rgb[..info.buffer_size()].chunks_exact(3) {
        let found = TexelMark::ALL.iter().position(|m| m.colour() == pixel);
        match found {
            Some(i) => counts[i] += 1,
            None if pixel[0] == pixel[1] && pixel[1] == pixel[2] => {}
            None => other += 1,
        }
    }
    (counts, other)
}

/// A marked picture's PNG bytes (the encoding `files::write_png` uses).
fn picture_png(world: &World, config: &BakeConfig, ids: &[u32]) -> Vec<u8> {
    let baked = BakeWorld::new(&world.scene);
    let picture = explain::picture(&baked, config, 0, ids, None).expect("picture");
    png_write::encode_rgb(picture.width, picture.height, &picture.rgb).unwrap()
}

/// Each caster's marked pixels are its counted texels: useful and front
/// with nothing behind (together its front texels), hidden; the rest of
/// the map is grey. B under A is only hidden, A is useful wherever it is
/// first, a box far from every texel centre is not drawn.
#[test]
fn the_picture_marks_exactly_the_texels_explain_counts() {
    let (world, a, b) = box_over_box();
    let fine = config(vec![directional(DOWN, 0.5)]);
    let explanation = explain_micro(&world);
    for instance in [a, b] {
        let counted = of(&explanation, &world, instance);
        let (marks, other) = marked_pixels(&picture_png(&world, &fine, &[counted.id]));
        let t = &counted.texels;
        assert_eq!(other, 0, "only grey and mark colours");
        assert_eq!(marks[0] + marks[1], t.front, "{counted:?}");
        assert_eq!(marks, [t.useful, t.front - t.useful, t.hidden]);
        assert!(instance != a || marks[0] >= 225, "A is useful: {marks:?}");
    }
    let hidden = of(&explanation, &world, b);
    let (marks, _) = marked_pixels(&picture_png(&world, &fine, &[hidden.id]));
    assert_eq!(marks[2], hidden.texels.hit);
    assert!(hidden.texels.hit > 0 && hidden.texels.front == 0);

    // A box between texel centres: met by no ray, so marked nowhere,
    // while the same map unmarked has colour.
    let coarse = config(vec![directional(DOWN, 4.0)]);
    let (world, tiny) = tiny_between_centres(&coarse);
    let never = of(&explain_all(&world.scene, &coarse, 0), &world, tiny);
    assert_eq!((never.texels.hit, never.reason), (0, Reason::NeverHit));
    let marks = marked_pixels(&picture_png(&world, &coarse, &[never.id]));
    assert_eq!(marks, ([0, 0, 0], 0), "a caster never hit marks no pixel");
    let plain = render::light_view(&world.scene, &coarse, 0, None).unwrap();
    let plain = png_write::encode_rgb(plain.width, plain.height, &plain.rgb).unwrap();
    assert!(marked_pixels(&plain).1 > 0, "the unmarked map is in colour");
}

fn shadowcull(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_shadowcull"))
        .args(args)
        .output()
        .expect("run shadowcull")
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn cli_prints_the_explanation_as_text_and_json() {
    let settings = fixture_dir(Preset::Village).join("bake.xml");
    let settings = settings.to_str().unwrap();
    let scene = load_world(std::path::Path::new(settings));
    let chunk = &scene.chunks[0].name;
    let target = format!("{chunk}:0");
    let text = shadowcull(&["explain", settings, "--light", "sun", "--caster", &target]);
    assert!(text.status.success(), "{}", stderr(&text));
    let text = String::from_utf8(text.stdout).unwrap();
    for needle in [
        "light `sun` (directional",
        &format!("caster {target}:0"),
        "bake verdict: ",
    ] {
        assert!(text.contains(needle), "{needle} in {text}");
    }

    let terrain = format!("{chunk}:terrain");
    let json = shadowcull(&[
        "explain", settings, "--light", "spot", "--caster", &terrain, "--json",
    ]);
    assert!(json.status.success(), "{}", stderr(&json));
    let value: serde_json::Value = serde_json::from_slice(&json.stdout).unwrap();
    assert_eq!(value["light"], "spot");
    let casters = value["casters"].as_array().unwrap();
    assert_eq!(casters.len(), 1);
    let caster = &casters[0];
    assert_eq!(caster["caster"], terrain.as_str());
    assert_eq!(caster["grid_verdict"], caster["bake_verdict"]);
    assert_eq!(caster["disagrees"], false);
    for field in ["hit", "front", "useful", "hidden", "hidden_by", "behind"] {
        assert!(caster["texels"].get(field).is_some(), "{field} in {caster}");
    }

    // The bake's own flags: the verdict is the bake's with them.
    let moded = shadowcull(&[
        "explain",
        settings,
        "--light",
        "sun",
        "--caster",
        &terrain,
        "--supersample",
        "2",
        "--filter-radius",
        "1",
        "--json",
    ]);
    assert!(moded.status.success(), "{}", stderr(&moded));
    let value: serde_json::Value = serde_json::from_slice(&moded.stdout).unwrap();
    assert_eq!(
        (&value["supersample"], &value["filter_radius"]),
        (&2.into(), &1.into())
    );
    assert_eq!(value["casters"][0]["disagrees"], false);
}

/// `-o`: the PNG's marked pixels are the texels the JSON counts, for a
/// terrain block and a model group; a map 1:1 (village's sun fits).
#[test]
fn cli_draws_the_casters_texels_over_the_map() {
    let settings = fixture_dir(Preset::Village).join("bake.xml");
    let settings = settings.to_str().unwrap();
    let scene = load_world(std::path::Path::new(settings));
    let dir = tempfile::tempdir().unwrap();
    let chunk = &scene.chunks[scene.chunks.len() / 2];
    let instance = &scene.instances[chunk.instances.start];
    for (n, target) in [
        format!("{}:terrain", chunk.name),
        format!("{}:{}:0", chunk.name, instance.index),
    ]
    .iter()
    .enumerate()
    {
        let png = dir.path().join(format!("{n}.png"));
        let output = shadowcull(&[
            "explain",
            settings,
            "--light",
            "sun",
            "--caster",
            target,
            "--json",
            "-o",
            png.to_str().unwrap(),
        ]);
        assert!(output.status.success(), "{}", stderr(&output));
        let value: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
        let texels = &value["casters"][0]["texels"];
        let count = |field: &str| texels[field].as_u64().unwrap();
        let (marks, other) = marked_pixels(&std::fs::read(&png).unwrap());
        assert_eq!(other, 0, "{target}: grey and marks only");
        assert_eq!(marks[0] + marks[1], count("front"), "{target}: {texels}");
        assert_eq!(
            marks,
            [
                count("useful"),
                count("front") - count("useful"),
                count("hidden")
            ],
            "{target}"
        );
        if n == 0 {
            assert!(count("front") > 1000, "the terrain block is seen: {texels}");
        }
    }
}

#[test]
fn cli_errors_name_the_settings_file_and_the_valid_range() {
    let settings = fixture_dir(Preset::Village).join("bake.xml");
    let settings = settings.to_str().unwrap();
    let scene = load_world(std::path::Path::new(settings));
    let chunk = &scene.chunks[0];
    let elements = chunk.instance_elements;
    let instance = &scene.instances[chunk.instances.start];
    let groups: usize = instance
        .parts
        .iter()
        .flatten()
        .map(|&m| scene.models[m].groups.len())
        .sum();
    let cases = [
        (
            "moon",
            format!("{}:0", chunk.name),
            "sun, spot, point".to_string(),
        ),
        ("sun", "nochunk:0".into(), "no chunk `nochunk`".into()),
        (
            "sun",
            format!("{}:{elements}", chunk.name),
            format!("0 to {}", elements - 1),
        ),
        (
            "sun",
            format!("{}:{}:{groups}", chunk.name, instance.index),
            format!("0 to {}", groups - 1),
        ),
    ];
    for (light, caster, why) in cases {
        let output = shadowcull(&["explain", settings, "--light", light, "--caster", &caster]);
        assert_eq!(output.status.code(), Some(1), "{caster}");
        let message = stderr(&output);
        assert!(
            message.contains(&why) && message.contains("bake.xml"),
            "{message}"
        );
    }
    for malformed in ["x", "x:y", "x:1:2:3"] {
        let output = shadowcull(&["explain", settings, "--light", "sun", "--caster", malformed]);
        assert_eq!(output.status.code(), Some(2), "{malformed}");
        assert!(stderr(&output).contains("--caster"), "{}", stderr(&output));
    }
}
