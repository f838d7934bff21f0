//! `shadowcull xcheck`: the ray-cast bake against the rasterized method,
//! or with `--savings` each light's shadow pass timed with all casters and
//! with the kept ones (cargo feature `raster`); without the feature it
//! says how to get it.

use super::SettingsArgs;
use anyhow::{bail, Result};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct XcheckArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// Write the comparison as JSON (pairs, agreeing, unexplained,
    /// disagreements), or with --savings the timings.
    #[arg(long, value_name = "FILE")]
    report: Option<PathBuf>,
    /// Instead of the comparison: bake, then per light render the shadow
    /// pass (depth only, the bake's grid) with every caster and with the
    /// kept ones, and report the median GPU and CPU time of each.
    #[arg(long)]
    savings: bool,
    /// Timed renders of each pass for --savings (after one warm-up).
    #[arg(long, value_name = "N", default_value_t = 7, value_parser = clap::value_parser!(u32).range(1..=1000), requires = "savings")]
    repetitions: u32,
    /// How the raster counts each caster's passing samples: per-caster
    /// atomic counters, occlusion queries, or both compared caster by caster.
    #[arg(long, value_enum, default_value_t = CounterArg::Atomics)]
    counter: CounterArg,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum CounterArg {
    Atomics,
    Queries,
    Both,
}

/// How to get a binary that can rasterize.
#[cfg(not(feature = "raster"))]
const REBUILD: &str = "rebuild with `cargo build --release --features raster` (and Mesa's libegl1 libegl-mesa0 libgl1-mesa-dri, or a GPU driver)";

#[cfg(not(feature = "raster"))]
pub fn run(args: XcheckArgs) -> Result<()> {
    if args.savings {
        bail!("xcheck --savings renders shadow passes with OpenGL, but this binary was built without the cargo feature `raster`: {REBUILD}");
    }
    bail!("xcheck needs the rasterized method, but this binary was built without the cargo feature `raster`: {REBUILD}")
}

#[cfg(feature = "raster")]
pub fn run(args: XcheckArgs) -> Result<()> {
    use super::{load_config, load_settings};
    use shadowcull::bake::setup::BakeWorld;
    use shadowcull::bake::BakeConfig;
    use shadowcull::raster::{self, Counter, RasterOptions};
    let settings = load_settings(&args.settings)?;
    let scene = shadowcull::scene::load_scene(&load_config(&settings))?;
    // Both methods mark light i at bit i (the file's <bit>s play no part).
    let config = BakeConfig {
        bits: Vec::new(),
        ..BakeConfig::from_settings(&settings)
    };
    let world = BakeWorld::new(&scene);
    if args.savings {
        return savings(&world, &config, &args);
    }
    let options = RasterOptions {
        counter: match args.counter {
            CounterArg::Atomics => Counter::Atomics,
            CounterArg::Queries => Counter::Queries,
            CounterArg::Both => Counter::Both,
        },
        ..Default::default()
    };
    // Both halves take seconds to minutes on a big world: say what runs.
    let started = std::time::Instant::now();
    eprintln!(
        "xcheck: rasterizing {} light(s), counting samples with {:?}…",
        config.lights.len(),
        options.counter
    );
    let result = raster::raster(&world, &config, &options)
        .map_err(|e| anyhow::anyhow!("the rasterized method could not run: {e}"))?;
    eprintln!(
        "xcheck: raster done in {:.1} s; ray casting the same texels and re-testing disagreements…",
        started.elapsed().as_secs_f64()
    );
    let report = raster::xcheck::compare(&world, &config, &result);
    println!("renderer: {}", report.renderer);
    for note in &report.notes {
        println!("note: {note}");
    }
    for l in &report.lights {
        println!(
            "light {} \"{}\": useful texels ray cast {} ({} of them in ε ties) raster {} ({:.2} s ray cast, {:.2} s raster)",
            l.light, l.name, l.ray_cast, l.ray_cast_tied, l.raster, l.ray_seconds, l.raster_seconds
        );
    }
    println!(
        "{} of {} (caster, light) pairs agree; {} disagreements, {} unexplained",
        report.agreeing,
        report.pairs,
        report.disagreements.len(),
        report.unexplained
    );
    for d in &report.disagreements {
        println!(
            "  {} {} {:?} group {:?} light {} \"{}\": ray cast {} raster {}: {}",
            d.chunk,
            d.kind,
            d.index,
            d.group,
            d.light,
            d.light_name,
            d.ray_cast,
            d.raster,
            d.cause.as_deref().unwrap_or("UNEXPLAINED")
        );
    }
    if let Some(path) = &args.report {
        let json = serde_json::to_string_pretty(&report)?;
        shadowcull::files::write_atomic(path, json.as_bytes())?;
    }
    if report.unexplained > 0 {
        bail!("{} disagreements stay unexplained", report.unexplained);
    }
    Ok(())
}

/// `--savings`: bake, time both passes of every light, print the table
/// and write the report.
#[cfg(feature = "raster")]
fn savings(
    world: &shadowcull::bake::setup::BakeWorld,
    config: &shadowcull::bake::BakeConfig,
    args: &XcheckArgs,
) -> Result<()> {
    use shadowcull::bake::{self, Silent};
    use shadowcull::raster::savings::{self, SavingsOptions};
    eprintln!(
        "xcheck: baking {} light(s) for the kept casters…",
        config.lights.len()
    );
    let baked = bake::bake(world.scene, config, &Silent)?;
    let options = SavingsOptions {
        repetitions: args.repetitions,
        ..Default::default()
    };
    eprintln!(
        "xcheck: timing each light's shadow pass, all casters and kept ones, {} times each…",
        options.repetitions
    );
    let report = savings::measure(world, config, &baked.masks, &options)
        .map_err(|e| anyhow::anyhow!("the shadow passes could not be rendered: {e}"))?;
    print!("{}", savings_table(&report));
    if let Some(path) = &args.report {
        let json = serde_json::to_string_pretty(&report)?;
        shadowcull::files::write_atomic(path, json.as_bytes())?;
    }
    Ok(())
}

/// The timings for people: per light what each pass draws and its median
/// times, in milliseconds, and kept / all.
#[cfg(feature = "raster")]
fn savings_table(report: &shadowcull::raster::savings::SavingsReport) -> String {
    use std::fmt::Write as _;
    let mut out = format!(
        "renderer: {}\nshadow pass, depth only, per light: every caster in reach (all) and the kept ones; \
         median of {} runs; GPU: GL_TIME_ELAPSED, CPU: first draw to glFinish\n",
        report.renderer, report.repetitions
    );
    for note in &report.notes {
        let _ = writeln!(out, "note: {note}");
    }
    let _ = writeln!(
        out,
        "{:<3} {:<16} {:>5} {:>17} {:>21} {:>10} {:>10} {:>6} {:>10} {:>10} {:>6}",
        "#",
        "light",
        "tiles",
        "draw calls",
        "triangles",
        "GPU ms all",
        "kept",
        "ratio",
        "CPU ms all",
        "kept",
        "ratio"
    );
    let ratio = |r: Option<f64>| r.map_or("-".to_string(), |r| format!("{r:.2}"));
    for l in &report.lights {
        let _ = writeln!(
            out,
            "{:<3} {:<16} {:>5} {:>17} {:>21} {:>10.3} {:>10.3} {:>6} {:>10.3} {:>10.3} {:>6}",
            l.light,
            l.name,
            l.tiles,
            format!("{} → {}", l.all.draw_calls, l.kept.draw_calls),
            format!("{} → {}", l.all.triangles, l.kept.triangles),
            l.all.gpu_seconds * 1e3,
            l.kept.gpu_seconds * 1e3,
            ratio(l.gpu_ratio),
            l.all.cpu_seconds * 1e3,
            l.kept.cpu_seconds * 1e3,
            ratio(l.cpu_ratio),
        );
    }
    out
}
