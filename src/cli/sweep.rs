//! `shadowcull sweep`: the accuracy/run-time ladder, as a table, CSV, JSON
//! and an SVG plot.

use super::{load_config, load_settings, SettingsArgs};
use anyhow::{Context, Result};
use shadowcull::bake::BakeConfig;
use shadowcull::files;
use shadowcull::scene;
use shadowcull::sweep::{self, SweepConfig};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// Folder for sweep.csv, sweep.json and sweep.svg (created).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Reference: the configured grids this many times denser per side.
    #[arg(long, value_name = "F", default_value_t = 8.0)]
    reference_density: f64,
    /// Refinement samples per caster in the reference.
    #[arg(long, value_name = "N", default_value_t = 64)]
    reference_refine_samples: u32,
    /// Refinement samples per caster in the ladder's refinement rows.
    #[arg(long, value_name = "N", default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=4096))]
    refine_samples: u32,
    /// Footprint lattice (rays per texel side) of the refinement rows.
    #[arg(long, value_name = "D", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    refine_density: u32,
    /// Grids at random sub-texel offsets (at the reference density) OR-ed
    /// into the offset reference.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = clap::value_parser!(u32).range(0..=64))]
    offset_references: u32,
    /// Seed of those offsets.
    #[arg(long, value_name = "N", default_value_t = 17)]
    offset_seed: u64,
}

pub fn run(args: SweepArgs) -> Result<()> {
    anyhow::ensure!(
        args.reference_density.is_finite() && args.reference_density >= 1.0,
        "--reference-density must be at least 1, got {}",
        args.reference_density
    );
    let settings = load_settings(&args.settings)?;
    anyhow::ensure!(
        !settings.lights.is_empty(),
        "{}: no <light> in <lights>: nothing to sweep",
        args.settings.settings.display()
    );
    let scene = scene::load_scene(&load_config(&settings))?;
    let config = SweepConfig {
        reference_density: args.reference_density,
        reference_refine_samples: args.reference_refine_samples,
        refine_samples: args.refine_samples,
        refine_density: args.refine_density,
        offset_references: args.offset_references,
        offset_seed: args.offset_seed,
    };
    eprintln!(
        "sweep: reference = grids x{} per side + refinement ({} samples per caster), {} offset grids, then {} settings",
        config.reference_density,
        config.reference_refine_samples,
        config.offset_references,
        sweep::ladder(&config).len()
    );
    let report = sweep::sweep(
        &scene,
        &BakeConfig::from_settings(&settings),
        &config,
        |row| eprintln!("  {}: {} rays, {:.2} s", row.label, row.rays, row.seconds),
    )
    .with_context(|| format!("{}", args.settings.settings.display()))?;
    let files = [
        ("sweep.csv", report.to_csv().into_bytes()),
        (
            "sweep.json",
            serde_json::to_vec_pretty(&report).context("sweep report")?,
        ),
        ("sweep.svg", report.to_svg().into_bytes()),
    ];
    for (name, bytes) in &files {
        files::write_atomic(&args.out.join(name), bytes)?;
    }
    print!("{}", report.to_table());
    println!(
        "wrote sweep.csv, sweep.json and sweep.svg to {}",
        args.out.display()
    );
    Ok(())
}
