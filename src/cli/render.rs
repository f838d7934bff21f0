//! `shadowcull render`: load, bake one light, draw its light or camera view,
//! write the PNG and its legend (`FILE.txt` beside it).

use super::{load_config, load_settings, SettingsArgs};
use anyhow::{Context, Result};
use glam::DVec3;
use shadowcull::bake::BakeConfig;
use shadowcull::files;
use shadowcull::render::{self, CameraSpec};
use shadowcull::scene;
use std::path::PathBuf;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum View {
    /// The light's shadow map, one pixel per texel.
    Light,
    /// A perspective picture of the world.
    Camera,
}

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// The light whose verdicts to draw (its <name>, or light0, light1, …).
    #[arg(long, value_name = "NAME")]
    light: String,
    #[arg(long, value_enum, default_value = "light")]
    view: View,
    /// Camera position, "x y z" in world metres (camera view; default: an
    /// overview of the whole world).
    #[arg(long, value_name = "\"X Y Z\"", value_parser = parse_vec3, allow_hyphen_values = true)]
    camera: Option<DVec3>,
    /// Point the camera looks at, "x y z" (default: the world's centre).
    #[arg(long = "look-at", value_name = "\"X Y Z\"", value_parser = parse_vec3, allow_hyphen_values = true)]
    look_at: Option<DVec3>,
    /// Vertical field of view of the camera, degrees.
    #[arg(long, value_name = "DEG", default_value_t = 60.0)]
    fov: f64,
    /// Picture size WxH: the camera view's size (default 800x600), or the
    /// largest size of the light view (default: the shadow map's own size,
    /// at most 2048x2048).
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// The PNG to write; the legend goes to the same path with `.txt`.
    #[arg(short = 'o', long = "output", value_name = "FILE.png")]
    output: PathBuf,
    /// Worker threads (default: one per core). Pictures are identical for any N.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    threads: Option<u16>,
    /// Draw the masks already written in the chunk files (at the light's
    /// bit) instead of baking the light.
    #[arg(long)]
    from_chunks: bool,
}

fn parse_vec3(text: &str) -> Result<DVec3, String> {
    let values: Vec<f64> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<f64>()
                .map_err(|_| format!("`{s}` is not a number"))
        })
        .collect::<Result<_, _>>()?;
    match values[..] {
        [x, y, z] if x.is_finite() && y.is_finite() && z.is_finite() => Ok(DVec3::new(x, y, z)),
        [_, _, _] => Err("coordinates must be finite".into()),
        _ => Err(format!(
            "expected three numbers \"x y z\", got {}",
            values.len()
        )),
    }
}

fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("expected WxH (e.g. 800x600), got `{text}`"))?;
    let side = |s: &str| -> Result<u32, String> {
        let n: u32 = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a whole number of pixels"))?;
        if n == 0 || n > render::MAX_SIDE {
            return Err(format!(
                "each side must be 1 to {} pixels, got {n}",
                render::MAX_SIDE
            ));
        }
        Ok(n)
    };
    Ok((side(w)?, side(h)?))
}

pub fn run(args: RenderArgs) -> Result<()> {
    let settings = load_settings(&args.settings)?;
    let light = render::find_light(&settings.lights, &args.light)
        .with_context(|| args.settings.settings.display().to_string())?;
    if args.view == View::Light && (args.camera.is_some() || args.look_at.is_some()) {
        eprintln!("note: --camera and --look-at only apply to --view camera; ignored");
    }
    let config = BakeConfig::from_settings(&settings);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.map(usize::from).unwrap_or(0))
        .build()
        .context("cannot start worker threads")?;
    let scene = scene::load_scene(&load_config(&settings))?;
    for problem in scene.problems.iter().take(5) {
        eprintln!("  {}: {}", problem.what, problem.why);
    }
    let chunk_masks = if args.from_chunks {
        let casters = shadowcull::bake::casters::CasterTable::new(&scene);
        Some(shadowcull::bake::output::masks_from_chunks(
            &scene, &casters,
        )?)
    } else {
        None
    };
    let source = match &chunk_masks {
        Some(masks) => render::Source::ChunkMasks {
            masks,
            bit: config.bit(light),
        },
        None => render::Source::Bake,
    };
    let picture = pool.install(|| match args.view {
        View::Light => render::light_view_from(&scene, &config, light, args.size, source),
        View::Camera => {
            let (width, height) = args.size.unwrap_or((800, 600));
            let camera = CameraSpec {
                position: args.camera,
                look_at: args.look_at,
                fov_degrees: args.fov,
                width,
                height,
            };
            render::camera_view_from(&scene, &config, light, &camera, source)
        }
    })?;
    files::write_png(&args.output, picture.width, picture.height, &picture.rgb)?;
    let legend_path = args.output.with_extension("txt");
    let legend = picture.legend(&super::command_line());
    files::write_atomic(&legend_path, legend.as_bytes())?;
    let [useful, culled, terrain_useful, terrain_culled, no_mask, receiver, nothing] =
        picture.counts();
    println!(
        "wrote {} ({} × {}) and {}: light `{}`: {} useful / {} culled / {} no-mask casters; pixels: \
         {useful} useful, {culled} culled, {terrain_useful} useful terrain, {terrain_culled} culled \
         terrain, {no_mask} no mask, {receiver} receiver-only, {nothing} nothing",
        args.output.display(),
        picture.width,
        picture.height,
        legend_path.display(),
        picture.light.name,
        picture.light.useful_casters,
        picture.light.culled_casters,
        picture.light.no_mask_casters,
    );
    Ok(())
}
