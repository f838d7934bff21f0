//! `shadowcull diff`: what changed between two bakes, read from two bake
//! reports or two folders of baked chunk files (the work is in
//! `shadowcull::diff`; here the arguments, the output and the exit code).

use super::UsageError;
use anyhow::Result;
use shadowcull::diff::{self, InputKind};
use shadowcull::files;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct DiffArgs {
    /// The earlier bake: its `--report` JSON, or a folder of its chunk files.
    old: PathBuf,
    /// The later bake, of the same kind as OLD.
    new: PathBuf,
    /// Print one JSON object (every differing caster) instead of the summary.
    #[arg(long)]
    json: bool,
    /// Exit 1 when anything differs (for CI).
    #[arg(long)]
    check: bool,
}

pub fn run(args: DiffArgs) -> Result<()> {
    for path in [&args.old, &args.new] {
        anyhow::ensure!(
            files::exists(path),
            "{}: no such file or folder",
            path.display()
        );
    }
    let (old_kind, new_kind) = (InputKind::of(&args.old), InputKind::of(&args.new));
    if old_kind != new_kind {
        return Err(UsageError(format!(
            "OLD {} is {} but NEW {} is {}: diff two bake reports or two folders of chunk files",
            args.old.display(),
            old_kind.describe(),
            args.new.display(),
            new_kind.describe()
        ))
        .into());
    }
    let diff = match old_kind {
        InputKind::Report => diff::diff_reports(&args.old, &args.new)?,
        InputKind::ChunkFolder => diff::diff_chunk_folders(&args.old, &args.new)?,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&diff)?);
    } else {
        print!("{}", diff.to_text());
    }
    anyhow::ensure!(
        !(args.check && diff.differs),
        "--check: {} caster(s) differ between the two bakes (listed above)",
        diff.casters.len()
    );
    Ok(())
}
