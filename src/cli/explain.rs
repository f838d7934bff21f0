//! `shadowcull explain`: the arguments, loading, and the explanation as
//! text or one JSON object; an explanation that disagrees with the bake
//! fails the command (exit 1), since one of the two is wrong.

use super::bake_shared::VerdictOptions;
use super::{load_config, load_settings, thread_pool, SettingsArgs};
use anyhow::{bail, Context, Result};
use shadowcull::bake::setup::BakeWorld;
use shadowcull::explain::{self, CasterExplanation, Explanation, Target};
use shadowcull::files;
use shadowcull::render::Picture;
use shadowcull::scene;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct ExplainArgs {
    #[command(flatten)]
    settings: SettingsArgs,
    /// The light (its <name>, or light0, light1, …).
    #[arg(long, value_name = "NAME")]
    light: String,
    /// CHUNK:INDEX[:GROUP] (a <model>/<shell> by its index in the chunk,
    /// as the report gives it), CHUNK:speedtree:INDEX[:GROUP], or
    /// CHUNK:terrain. Without GROUP, every group of the instance.
    #[arg(long, value_name = "CHUNK:INDEX[:GROUP]", value_parser = parse_target)]
    caster: Target,
    /// The bake's options that change a verdict (`--supersample`,
    /// `--filter-radius`, `--refine`, `--conservative`, overrides of the
    /// settings' rules): the explanation covers the texel-centre grid pass
    /// at `--supersample`, the bake verdict uses them all and names the
    /// mode that kept a caster the grid pass culls.
    #[command(flatten)]
    verdict: VerdictOptions,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// Also draw the light's map to FILE.png in grey with the caster's
    /// texels in colour: useful (something behind), front with nothing
    /// behind, hidden by a nearer caster. One pixel a texel up to
    /// 2048x2048; a larger map is shown smaller, each pixel the texel
    /// under its centre.
    #[arg(short = 'o', long = "output", value_name = "FILE.png")]
    output: Option<PathBuf>,
    /// Worker threads (default: one per core); the answer is the same for any N.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    threads: Option<u16>,
}

fn parse_target(text: &str) -> Result<Target, String> {
    text.parse()
}

pub fn run(args: ExplainArgs) -> Result<()> {
    let file = args.settings.settings.display().to_string();
    let settings = load_settings(&args.settings)?;
    let config = args.verdict.config(&settings)?;
    let light = explain::find_light(&config, &args.light).with_context(|| file.clone())?;
    let pool = thread_pool(args.threads)?;
    let scene = scene::load_scene(&load_config(&settings))?;
    for problem in scene.problems.iter().take(5) {
        eprintln!("  {}: {}", problem.what, problem.why);
    }
    let (explanation, picture) = pool.install(|| -> Result<(Explanation, Option<Picture>)> {
        let world = BakeWorld::new(&scene);
        let ids =
            explain::resolve(&scene, &world.casters, &args.caster).with_context(|| file.clone())?;
        let explanation =
            explain::explain(&world, &config, light, &ids).with_context(|| file.clone())?;
        let picture = match &args.output {
            Some(_) => Some(
                explain::picture(&world, &config, light, &ids, None)
                    .with_context(|| format!("drawing light `{}` ({file})", args.light))?,
            ),
            None => None,
        };
        Ok((explanation, picture))
    })?;
    if let (Some(path), Some(picture)) = (&args.output, &picture) {
        files::write_png(path, picture.width, picture.height, &picture.rgb)?;
        eprintln!("wrote {}:", path.display());
        for note in &picture.notes {
            eprintln!("  {note}");
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&explanation)?);
    } else {
        print!("{}", text(&explanation));
    }
    if explanation.disagrees() {
        let names: Vec<&str> = explanation
            .casters
            .iter()
            .filter(|c| c.disagrees)
            .map(|c| c.caster.as_str())
            .collect();
        bail!(
            "BUG: the explanation and the bake disagree about {} (light `{}`, {file}); please report it with this command",
            names.join(", "),
            explanation.light
        );
    }
    Ok(())
}

/// The explanation for people.
fn text(explanation: &Explanation) -> String {
    let mut out = format!(
        "light `{}` ({}, {} texels, passes: {})\n",
        explanation.light,
        explanation.kind,
        explanation.texels,
        explanation.passes.replace('_', " ")
    );
    let radius = format!("--filter-radius {}", explanation.filter_radius);
    let modes: Vec<&str> = [
        (explanation.filter_radius > 0, radius.as_str()),
        (explanation.conservative, "--conservative"),
        (explanation.refine, "--refine"),
    ]
    .iter()
    .filter(|m| m.0)
    .map(|m| m.1)
    .collect();
    if explanation.supersample > 1 {
        let k = explanation.supersample;
        out += &format!(
            "supersampled {k}×{k}: the counts below are of rays, {} a texel\n",
            k * k
        );
    }
    if !modes.is_empty() {
        out += &format!(
            "the explanation covers the grid pass; the bake verdict uses {}\n",
            modes.join(" ")
        );
    }
    for caster in &explanation.casters {
        out += &caster_text(caster);
    }
    out
}

fn caster_text(c: &CasterExplanation) -> String {
    let t = &c.texels;
    let mut flags = Vec::new();
    if c.alpha_tested {
        flags.push("alpha-tested");
    }
    if c.receiver_only {
        flags.push("receiver-only");
    }
    let mut out = format!(
        "\ncaster {}{}{}\n  verdict: {}: {}\n",
        c.caster,
        c.resource
            .as_ref()
            .map_or(String::new(), |r| format!(" ({r})")),
        if flags.is_empty() {
            String::new()
        } else {
            format!(" [{}]", flags.join(", "))
        },
        c.grid_verdict.word(),
        c.reason.words()
    );
    out += &format!(
        "  texels whose ray meets it: {}; front hit at {}, of which useful (something behind): {}; hidden at {}\n",
        t.hit, t.front, t.useful, t.hidden
    );
    if !t.hidden_by.is_empty() {
        let hiders: Vec<String> = t
            .hidden_by
            .iter()
            .map(|h| format!("{} ({})", h.caster, h.texels))
            .collect();
        out += &format!("  in front of it (texels): {}", hiders.join(", "));
        if t.hidden_by_others > 0 {
            out += &format!(", others ({})", t.hidden_by_others);
        }
        out += "\n";
    }
    if t.front > t.useful {
        let b = &t.behind;
        out += &format!(
            "  behind it where it is front but not useful: nothing {}, below ground {}, faces turned away {}, \
             alpha-tested {}, receiver-only alpha-tested {}\n",
            b.nothing, b.below_ground, b.facing_away, b.alpha_tested, b.receiver_only_alpha_tested
        );
    }
    if t.dropped_below_ground + t.dropped_facing_away > 0 {
        out += &format!(
            "  texels meeting it only where the hit is ignored: below ground {}, turned away {}\n",
            t.dropped_below_ground, t.dropped_facing_away
        );
    }
    out += &format!("  bake verdict: {}", c.bake_verdict.word());
    if let Some(rule) = c.kept_by {
        out += &format!(" (kept by {rule})");
    }
    if c.disagrees {
        out += "  <- DISAGREES with the explanation";
    }
    out += "\n";
    out
}
