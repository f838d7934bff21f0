//! `shadowcull xcheck`: the ray-cast bake against the rasterized method
//! (cargo feature `raster`); without the feature it says how to get it.

use super::SettingsArgs;
use anyhow::{bail, Result};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct XcheckArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// Write the comparison as JSON (pairs, agreeing, unexplained, disagreements).
    #[arg(long, value_name = "FILE")]
    report: Option<PathBuf>,
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

#[cfg(not(feature = "raster"))]
pub fn run(_args: XcheckArgs) -> Result<()> {
    bail!("xcheck needs the rasterized method: rebuild with `cargo build --release --features raster` (and Mesa's libegl1 libegl-mesa0 libgl1-mesa-dri, or a GPU driver)")
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
