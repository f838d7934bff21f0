//! `render`: the light view shows each texel's front caster with the bake's
//! verdict (counted against texel centres worked out from the geometry and
//! against the bake's masks), the camera view is deterministic and shows
//! verdict colours, and the CLI's bad arguments give clear errors.

use crate::generated::fixture_dir;
use crate::micro::*;
use glam::{DMat4, DVec3, Vec3};
use shadowcull::formats::bake_settings::{LightKind, LightSettings};
use shadowcull::gen::Preset;
use shadowcull::render::{self, CameraSpec, Class, Picture};
use std::process::{Command, Output};

const DOWN: DVec3 = DVec3::new(0.0, -1.0, 0.0);

/// Two chunks in x. Chunk (0, 0) has flat terrain at y 0 and box A
/// (x, z 4..8, y 2..3) over it: first hit, terrain behind → useful. Chunk
/// (1, 0) has no terrain and box C (world x 20..22, z 4..7, y 1..2): its top
/// face is first, its bottom face is a back face for a light from above, so
/// only one crossing → culled. The terrain has nothing behind it → culled.
fn useful_and_culled() -> (World, usize, usize) {
    let mut world = World::new(2, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let a = world.model(Mesh {
        groups: vec![(
            cube(Vec3::new(4.0, 2.0, 4.0), Vec3::new(8.0, 3.0, 8.0)),
            OPAQUE,
        )],
    });
    let c = world.model(Mesh {
        groups: vec![(
            cube(Vec3::new(4.0, 1.0, 4.0), Vec3::new(6.0, 2.0, 7.0)),
            OPAQUE,
        )],
    });
    let a = world.place((0, 0), &[a], DMat4::IDENTITY, true);
    let c = world.place((1, 0), &[c], DMat4::IDENTITY, true);
    (world, a, c)
}

/// The class whose colour, times some shade, is `rgb` (±1 per channel for
/// rounding); black is Nothing.
fn hue_class(rgb: [u8; 3]) -> Option<Class> {
    if rgb == [0, 0, 0] {
        return Some(Class::Nothing);
    }
    Class::ALL
        .into_iter()
        .filter(|c| *c != Class::Nothing)
        .find(|class| {
            let c = class.colour().map(f64::from);
            let p = rgb.map(f64::from);
            let k = (0..3).max_by(|&i, &j| c[i].total_cmp(&c[j])).unwrap();
            let shade = p[k] / c[k];
            (0..3).all(|i| (p[i] - c[i] * shade).abs() <= 1.0)
        })
}

fn pixel(picture: &Picture, x: u32, y: u32) -> [u8; 3] {
    let i = (y * picture.width + x) as usize * 3;
    [picture.rgb[i], picture.rgb[i + 1], picture.rgb[i + 2]]
}

/// (count, bounding rectangle width, height) of the pixels whose hue is
/// `class`.
fn footprint(picture: &Picture, class: Class) -> (usize, u32, u32) {
    let (mut count, mut x0, mut y0, mut x1, mut y1) = (0, u32::MAX, u32::MAX, 0, 0);
    for y in 0..picture.height {
        for x in 0..picture.width {
            if hue_class(pixel(picture, x, y)) == Some(class) {
                count += 1;
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
            }
        }
    }
    if count == 0 {
        return (0, 0, 0);
    }
    (count, x1 - x0 + 1, y1 - y0 + 1)
}

#[test]
fn light_view_shows_useful_green_and_culled_red_exactly_where_they_are_first() {
    let (world, a, c) = useful_and_culled();
    let config = config(vec![directional(DOWN, 0.25)]);
    let result = run(&world, &config);
    assert_eq!(instance_masks(&result, &world, a), vec![1]);
    assert_eq!(instance_masks(&result, &world, c), vec![0]);
    assert_eq!(terrain_mask(&result, 0), 0);

    let picture = render::light_view(&world.scene, &config, 0, None).unwrap();
    // World bounds x 0..22, z 0..16 (terrain 0..16 square, box C to x 22);
    // texel 0.25 m → 88 × 64 texels, shown 1:1. Straight down, u and v are
    // the world x and z axes, texel centres sit 0.125 m off every
    // quarter-metre edge, so a box covers exactly (side / 0.25)² centres.
    assert_eq!(
        (picture.width as u64) * (picture.height as u64),
        88 * 64,
        "{}×{}",
        picture.width,
        picture.height
    );
    let total = 88 * 64;
    let a_texels = 16 * 16; // 4 m × 4 m
    let c_texels = 8 * 12; // 2 m × 3 m
    let terrain_texels = 64 * 64 - a_texels; // terrain square minus A on top
    let nothing = total - 64 * 64 - c_texels;

    let mut by_hue = std::collections::BTreeMap::new();
    for y in 0..picture.height {
        for x in 0..picture.width {
            let class = hue_class(pixel(&picture, x, y)).expect("every pixel has a class hue");
            *by_hue.entry(class).or_insert(0usize) += 1;
        }
    }
    let expected = [
        (Class::Useful, a_texels),
        (Class::Culled, c_texels),
        (Class::TerrainCulled, terrain_texels),
        (Class::Nothing, nothing),
    ];
    assert_eq!(by_hue, expected.into_iter().collect());
    // The picture's own classes agree with its colours.
    let counts = picture.counts();
    for (class, n) in expected {
        let i = Class::ALL.iter().position(|c| *c == class).unwrap();
        assert_eq!(counts[i] as usize, n, "{class:?}");
    }
    // Where: one solid rectangle each (4 m × 4 m and 2 m × 3 m, in either
    // orientation of the map).
    assert_eq!(footprint(&picture, Class::Useful), (256, 16, 16));
    let (n, w, h) = footprint(&picture, Class::Culled);
    assert_eq!(n, 96);
    assert!((w, h) == (8, 12) || (w, h) == (12, 8), "{w}×{h}");
    // Nearer is brighter: A's top (y 3) is nearer the light than C's (y 2)
    // and the terrain (y 0); the terrain is the farthest, at the floor.
    let brightest = |class: Class| {
        (0..picture.height)
            .flat_map(|y| (0..picture.width).map(move |x| (x, y)))
            .map(|(x, y)| pixel(&picture, x, y))
            .filter(|p| hue_class(*p) == Some(class))
            .map(|p| *p.iter().max().unwrap())
            .max()
            .unwrap()
    };
    assert_eq!(brightest(Class::Useful), Class::Useful.colour()[2]);
    let culled_full = *Class::Culled.colour().iter().max().unwrap();
    assert!(brightest(Class::Culled) < culled_full && brightest(Class::Culled) > 100);
    assert_eq!(
        brightest(Class::TerrainCulled),
        (f64::from(*Class::TerrainCulled.colour().iter().max().unwrap()) * 0.3).round() as u8
    );
    // The bake's totals for the light: A useful; C and the terrain culled.
    assert_eq!(picture.light.useful_casters, 1);
    assert_eq!(picture.light.culled_casters, 2);
    let legend = picture.legend("shadowcull render …");
    assert!(
        legend.contains("`sun` (directional)") && legend.contains("1:1"),
        "{legend}"
    );
}

#[test]
fn light_view_reduced_to_a_size_samples_texel_centres() {
    let (world, _, _) = useful_and_culled();
    let config = config(vec![directional(DOWN, 0.25)]);
    let picture = render::light_view(&world.scene, &config, 0, Some((44, 44))).unwrap();
    // 88 × 64 (or 64 × 88) into 44 × 44: half size, aspect kept; every
    // pixel is the texel under its centre, so box A still covers 8 × 8.
    assert_eq!(picture.width * picture.height, 44 * 32);
    assert_eq!(footprint(&picture, Class::Useful), (64, 8, 8));
    assert!(render::light_view(&world.scene, &config, 0, Some((0, 10))).is_err());
}

#[test]
fn point_light_faces_stand_side_by_side_with_up_at_the_top() {
    // A point light 4 m above flat terrain (16 m square) sees only terrain
    // through its −Y face (the 90° cone reaches ±4 m), nothing through +Y,
    // and through a side face terrain in the lower half, nothing above.
    let mut world = World::new(1, 1);
    world.terrain((0, 0), |_, _| 0.0);
    let light = LightSettings {
        name: "lamp".into(),
        kind: LightKind::Point {
            position: DVec3::new(8.0, 4.0, 8.0),
            near: 0.1,
            far: 100.0,
            resolution: 16,
        },
    };
    let picture = render::light_view(&world.scene, &config(vec![light]), 0, None).unwrap();
    assert_eq!((picture.width, picture.height), (6 * 16, 16));
    let class_at = |x: u32, y: u32| picture.classes[(y * picture.width + x) as usize];
    for y in 0..16 {
        for x in 0..16 {
            assert_eq!(class_at(2 * 16 + x, y), Class::Nothing, "+Y face");
            assert_eq!(class_at(3 * 16 + x, y), Class::TerrainCulled, "-Y face");
        }
    }
    for x in 0..16 {
        assert_eq!(class_at(x, 0), Class::Nothing, "+X face, top row");
        assert_eq!(class_at(x, 15), Class::TerrainCulled, "+X face, bottom row");
    }
}

fn camera_over(point: DVec3) -> CameraSpec {
    CameraSpec {
        position: Some(point + DVec3::new(0.0, 6.0, 0.0)),
        look_at: Some(point),
        fov_degrees: 30.0,
        width: 64,
        height: 48,
    }
}

#[test]
fn camera_view_shows_verdict_colours_and_is_the_same_for_any_thread_count() {
    let (world, _, _) = useful_and_culled();
    let config = config(vec![directional(DVec3::new(-0.3, -1.0, 0.2), 0.25)]);
    let result = run(&world, &config);
    assert_eq!(result.lights[0].useful_casters, 1, "A stays useful");
    let centre = |picture: &Picture| {
        let x = picture.width / 2;
        let y = picture.height / 2;
        picture.classes[(y * picture.width + x) as usize]
    };
    // Straight down onto A's top (centre 6, 3, 6) and C's (21, 2, 5.5).
    let on_a = render::camera_view(
        &world.scene,
        &config,
        0,
        &camera_over(DVec3::new(6.0, 3.0, 6.0)),
    )
    .unwrap();
    assert_eq!(centre(&on_a), Class::Useful);
    let mid = ((on_a.height / 2 * on_a.width + on_a.width / 2) * 3) as usize;
    assert_eq!(
        hue_class([on_a.rgb[mid], on_a.rgb[mid + 1], on_a.rgb[mid + 2]]),
        Some(Class::Useful)
    );
    let on_c = render::camera_view(
        &world.scene,
        &config,
        0,
        &camera_over(DVec3::new(21.0, 2.0, 5.5)),
    )
    .unwrap();
    assert_eq!(centre(&on_c), Class::Culled);

    let overview = CameraSpec {
        width: 96,
        height: 64,
        ..CameraSpec::default()
    };
    let draw = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| render::camera_view(&world.scene, &config, 0, &overview).unwrap())
    };
    let one = draw(1);
    let two = draw(2);
    let three = draw(3);
    assert_eq!(one.rgb, two.rgb);
    assert_eq!(one.rgb, three.rgb);
    let png = |p: &Picture| {
        shadowcull::formats::png_write::encode_rgb(p.width, p.height, &p.rgb).unwrap()
    };
    assert_eq!(png(&one), png(&two));
    // The overview sees the whole world: both boxes, terrain and sky.
    let counts = one.counts();
    for class in [
        Class::Useful,
        Class::Culled,
        Class::TerrainCulled,
        Class::Nothing,
    ] {
        let i = Class::ALL.iter().position(|c| *c == class).unwrap();
        assert!(counts[i] > 0, "{class:?} missing from the overview");
    }
    // Sky is dark blue, not black.
    let sky = one
        .classes
        .iter()
        .position(|c| *c == Class::Nothing)
        .unwrap();
    assert!(one.rgb[sky * 3 + 2] > one.rgb[sky * 3]);
}

#[test]
fn camera_with_no_direction_is_an_error() {
    let (world, _, _) = useful_and_culled();
    let config = config(vec![directional(DOWN, 0.25)]);
    let same = CameraSpec {
        position: Some(DVec3::ONE),
        look_at: Some(DVec3::ONE),
        ..CameraSpec::default()
    };
    let message = render::camera_view(&world.scene, &config, 0, &same)
        .unwrap_err()
        .to_string();
    assert!(message.contains("same point"), "{message}");
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
fn cli_writes_the_picture_and_its_legend() {
    let settings = fixture_dir(Preset::Small).join("bake.xml");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("view.png");
    let run = |threads: &str| {
        let output = shadowcull(&[
            "render",
            settings.to_str().unwrap(),
            "--light",
            "spot",
            "--view",
            "camera",
            "--camera",
            "-5 30 -5",
            "--look-at",
            "20 0 20",
            "--size",
            "80x60",
            "--threads",
            threads,
            "-o",
            out.to_str().unwrap(),
        ]);
        assert!(output.status.success(), "{}", stderr(&output));
        std::fs::read(&out).unwrap()
    };
    let one = run("1");
    let two = run("2");
    assert_eq!(one, two, "same bytes for any thread count");
    assert!(one.starts_with(b"\x89PNG"));
    let legend = std::fs::read_to_string(dir.path().join("view.txt")).unwrap();
    for needle in [
        "`spot` (spot)",
        "useful caster (blue)",
        "Okabe-Ito",
        "culled casters (chunk, index, resource):",
        "camera view: from (-5.00, 30.00, -5.00)",
        "command: shadowcull render",
    ] {
        assert!(legend.contains(needle), "{needle} in {legend}");
    }
}

#[test]
fn cli_bad_arguments_give_clear_errors_and_exit_codes() {
    let settings = fixture_dir(Preset::Small).join("bake.xml");
    let settings = settings.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.png");
    let out = out.to_str().unwrap();

    let unknown = shadowcull(&["render", settings, "--light", "moon", "-o", out]);
    assert_eq!(unknown.status.code(), Some(1));
    let message = stderr(&unknown);
    assert!(
        message.contains("`moon`") && message.contains("sun, spot, point"),
        "{message}"
    );

    for size in ["0x10", "10x0", "10", "axb"] {
        let bad = shadowcull(&[
            "render", settings, "--light", "sun", "--size", size, "-o", out,
        ]);
        assert_eq!(bad.status.code(), Some(2), "--size {size}");
        assert!(stderr(&bad).contains("--size"), "{}", stderr(&bad));
    }
    for (vector, why) in [("1 2", "three numbers"), ("1 a 3", "`a` is not a number")] {
        let bad_vector = shadowcull(&[
            "render", settings, "--light", "sun", "--view", "camera", "--camera", vector, "-o", out,
        ]);
        assert_eq!(bad_vector.status.code(), Some(2), "--camera {vector}");
        assert!(stderr(&bad_vector).contains(why), "{}", stderr(&bad_vector));
    }
    assert!(
        !std::path::Path::new(out).exists(),
        "no picture after a usage error"
    );

    // A folder path that runs through a regular file cannot be created.
    let blocker = dir.path().join("not-a-folder");
    std::fs::write(&blocker, b"x").unwrap();
    let target = blocker.join("out.png");
    let unwritable = shadowcull(&[
        "render",
        settings,
        "--light",
        "sun",
        "-o",
        target.to_str().unwrap(),
    ]);
    assert_eq!(unwritable.status.code(), Some(1));
    assert!(
        stderr(&unwritable).contains("not-a-folder"),
        "{}",
        stderr(&unwritable)
    );
    assert!(!target.exists());
}
