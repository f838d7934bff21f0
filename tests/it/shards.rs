//! The distributed bake through the binary: N shard processes
//! (`bake --shard I/N --partial FILE`) merged (`merge`) must write the same
//! bytes and report the same masks as one `bake`; `merge` refuses partials
//! of other inputs, missing shards, damaged files and disagreeing copies,
//! naming them. `SHADOWCULL_SLOW=1` in a release build (as `.ci/run`
//! runs it) adds the `bench` world.

use crate::cli::shadowcull;
use shadowcull::files::write_tree;
use shadowcull::formats::partial;
use shadowcull::gen::{generate, Preset};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

fn ok(output: Output, what: &str) -> Output {
    assert!(
        output.status.success(),
        "{what}: {}\n{}",
        String::from_utf8_lossy(&output.stderr),
        String::from_utf8_lossy(&output.stdout)
    );
    output
}

/// Exit 1 with stderr containing every one of `needles`.
fn refused(output: Output, needles: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).to_string();
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    for needle in needles {
        assert!(stderr.contains(needle), "`{needle}` not in: {stderr}");
    }
    stderr
}

fn world(preset: Preset, dir: &Path) -> PathBuf {
    write_tree(dir, &generate(preset, crate::generated::FIXTURE_SEED).files).unwrap();
    dir.join("bake.xml")
}

/// Every file under `dir`, relative path → bytes.
fn tree(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(folder) = stack.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                out.insert(path.strip_prefix(dir).unwrap().to_path_buf(), bytes);
            }
        }
    }
    out
}

/// The report's masks and skipped entries (timings differ between runs).
fn masks(report: &Path) -> (serde_json::Value, serde_json::Value, Vec<u64>) {
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(report).unwrap()).unwrap();
    let rays = json["lights"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["rays"].as_u64().unwrap())
        .collect();
    (json["casters"].clone(), json["skipped"].clone(), rays)
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Bakes `settings` in one process and as `shards` shard processes plus a
/// merge (with `extra` flags on every command), and asserts the chunks and
/// report masks are the same.
fn assert_shards_equal_one_bake(settings: &Path, shards: u32, extra: &[&str], work: &Path) {
    let one = work.join(format!("one-{shards}"));
    let merged = work.join(format!("merged-{shards}"));
    let one_report = work.join(format!("one-{shards}.json"));
    let merged_report = work.join(format!("merged-{shards}.json"));
    let mut args = vec![
        "bake",
        s(settings),
        "--out",
        s(&one),
        "--report",
        s(&one_report),
    ];
    args.extend(extra);
    ok(shadowcull(&args), "the single bake");
    let mut partials = Vec::new();
    for index in 0..shards {
        let partial = work.join(format!("p{index}of{shards}.part"));
        let shard = format!("{index}/{shards}");
        let extra_shard: Vec<&str> = extra.iter().copied().filter(|a| *a != "--refine").collect();
        let mut args = vec![
            "bake",
            s(settings),
            "--shard",
            &shard,
            "--partial",
            s(&partial),
        ];
        args.extend(extra_shard);
        ok(shadowcull(&args), &format!("shard {shard}"));
        partials.push(partial);
    }
    let mut args = vec!["merge", s(settings)];
    args.extend(partials.iter().map(|p| s(p)));
    args.extend(["--out", s(&merged), "--report", s(&merged_report)]);
    args.extend(extra);
    ok(shadowcull(&args), "the merge");
    let (a, b) = (tree(&one), tree(&merged));
    assert!(!a.is_empty());
    assert_eq!(
        a.keys().collect::<Vec<_>>(),
        b.keys().collect::<Vec<_>>(),
        "{shards} shards {extra:?}: the same files"
    );
    for (name, bytes) in &a {
        assert!(
            bytes == &b[name],
            "{shards} shards {extra:?}: {} differs",
            name.display()
        );
    }
    assert_eq!(
        masks(&one_report),
        masks(&merged_report),
        "{shards} shards {extra:?}: report"
    );
}

#[test]
fn shards_merged_equal_one_bake_on_the_fixtures() {
    for preset in [Preset::Small, Preset::Village] {
        let dir = tempfile::tempdir().unwrap();
        let settings = world(preset, &dir.path().join("world"));
        for shards in [1, 2, 3, 7] {
            assert_shards_equal_one_bake(&settings, shards, &[], dir.path());
        }
    }
}

#[test]
fn shards_merged_equal_one_bake_with_supersampling_and_refinement() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    for shards in [2, 7] {
        let work = dir.path().join(format!("w{shards}"));
        std::fs::create_dir_all(&work).unwrap();
        assert_shards_equal_one_bake(
            &settings,
            shards,
            &["--supersample", "2", "--refine", "--refine-samples", "8"],
            &work,
        );
    }
}

#[test]
fn shards_merged_equal_one_bake_with_conservative_filter_margin_and_refinement() {
    // The accuracy options: the grid mode and the filter margin run in the
    // shards (tiles with their halo), footprint refinement in the merge.
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    for (shards, extra) in [
        (2, &["--conservative", "--refine"][..]),
        (
            3,
            &["--filter-radius", "1", "--refine", "--refine-density", "4"][..],
        ),
        (3, &["--conservative", "--filter-radius", "2"][..]),
    ] {
        let work = dir.path().join(format!("w{shards}-{}", extra.len()));
        std::fs::create_dir_all(&work).unwrap();
        assert_shards_equal_one_bake(&settings, shards, extra, &work);
    }
}

#[test]
#[cfg_attr(
    any(not(shadowcull_slow), debug_assertions),
    ignore = "eight bakes of bench: run `SHADOWCULL_SLOW=1 cargo test --release --test it shards_merged_equal_one_bake_on_bench` (.ci/run does)"
)]
fn shards_merged_equal_one_bake_on_bench() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Bench, &dir.path().join("world"));
    for shards in [1, 2, 3, 7] {
        assert_shards_equal_one_bake(&settings, shards, &[], dir.path());
    }
}

/// Shards 0..3 of `settings` into `dir`, returned in order.
fn three_shards(settings: &Path, dir: &Path, tag: &str) -> Vec<PathBuf> {
    (0..3)
        .map(|i| {
            let partial = dir.join(format!("{tag}{i}.part"));
            let shard = format!("{i}/3");
            ok(
                shadowcull(&[
                    "bake",
                    s(settings),
                    "--shard",
                    &shard,
                    "--partial",
                    s(&partial),
                ]),
                "shard",
            );
            partial
        })
        .collect()
}

fn merge(settings: &Path, partials: &[&Path], out: &Path) -> Output {
    let mut args = vec!["merge", s(settings)];
    args.extend(partials.iter().map(|p| s(p)));
    args.extend(["--out", s(out)]);
    shadowcull(&args)
}

#[test]
fn a_partial_of_other_inputs_is_refused_naming_it_and_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    let parts = three_shards(&settings, dir.path(), "p");
    // One chunk edited (a value nudged, still a valid chunk), shard 2 baked
    // from it, the chunk put back.
    let chunk = shadowcull::files::find_files(&dir.path().join("world"), ".chunk")
        .unwrap()
        .remove(0);
    let original = std::fs::read(&chunk).unwrap();
    let mut edited = original.clone();
    edited.extend_from_slice(b"\n<!-- edited -->\n");
    std::fs::write(&chunk, &edited).unwrap();
    let other = dir.path().join("other2.part");
    ok(
        shadowcull(&[
            "bake",
            s(&settings),
            "--shard",
            "2/3",
            "--partial",
            s(&other),
        ]),
        "shard of the edited world",
    );
    std::fs::write(&chunk, &original).unwrap();
    let out = dir.path().join("out");
    let chunk_name = chunk.file_name().unwrap().to_str().unwrap();
    let stderr = refused(
        merge(&settings, &[&parts[0], &parts[1], &other], &out),
        &["other2.part", "other inputs", chunk_name, "other content"],
    );
    assert!(
        !stderr.contains("p0.part") && !stderr.contains("p1.part"),
        "{stderr}"
    );
    assert!(!out.exists(), "nothing written");

    // Other settings: the merge names the setting.
    refused(
        shadowcull(&[
            "merge",
            s(&settings),
            s(&parts[0]),
            s(&parts[1]),
            s(&parts[2]),
            "--supersample",
            "2",
            "--out",
            s(&out),
        ]),
        &["p0.part", "p1.part", "p2.part", "supersample"],
    );
    assert!(!out.exists());
    // The grid mode and the filter radius decide the grid's answer too.
    for (flag, setting) in [
        (
            &["--conservative"][..],
            "--conservative is `false` in the partial but `true`",
        ),
        (
            &["--filter-radius", "1"][..],
            "--filter-radius is `0` in the partial but `1`",
        ),
    ] {
        let mut args = vec![
            "merge",
            s(&settings),
            s(&parts[0]),
            s(&parts[1]),
            s(&parts[2]),
        ];
        args.extend(flag);
        args.extend(["--out", s(&out)]);
        refused(shadowcull(&args), &["p0.part", setting]);
        assert!(!out.exists());
    }
    // A light edited in the settings file: the element, both values and
    // the line that sets this merge's, said once for every partial, with
    // no debug text and no shard called missing.
    let original = std::fs::read_to_string(&settings).unwrap();
    let at = original.find("<texelSize>").unwrap();
    let line = original[..at].matches('\n').count() + 1;
    let value_start = at + "<texelSize>".len();
    let value_end = value_start + original[value_start..].find("</texelSize>").unwrap();
    let old_value: f64 = original[value_start..value_end].trim().parse().unwrap();
    let edited = format!(
        "{}\t0.3\t{}",
        &original[..value_start],
        &original[value_end..]
    );
    std::fs::write(&settings, edited).unwrap();
    let stderr = refused(
        merge(&settings, &[&parts[0], &parts[1], &parts[2]], &out),
        &[
            "<lights/light[0]/texelSize>",
            &format!("`{old_value}` in the partial but `0.3` in this merge"),
            &format!("bake.xml:{line})"),
        ],
    );
    assert!(
        !stderr.contains("LightSettings") && !stderr.contains("DVec3"),
        "{stderr}"
    );
    assert!(!stderr.contains("missing shard"), "{stderr}");
    assert_eq!(stderr.matches("settings differ").count(), 1, "{stderr}");
    std::fs::write(&settings, original).unwrap();
    // The right partials merge.
    ok(
        merge(&settings, &[&parts[0], &parts[1], &parts[2]], &out),
        "merge",
    );
}

#[test]
fn a_missing_shard_is_refused_and_rerunning_only_it_completes_the_merge() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    let parts = three_shards(&settings, dir.path(), "p");
    let out = dir.path().join("out");
    refused(
        merge(&settings, &[&parts[0], &parts[2]], &out),
        &["missing shard(s) 1 of 3", "--shard I/3"],
    );
    assert!(!out.exists());
    std::fs::remove_file(&parts[1]).unwrap();
    let rerun = dir.path().join("rerun1.part");
    ok(
        shadowcull(&[
            "bake",
            s(&settings),
            "--shard",
            "1/3",
            "--partial",
            s(&rerun),
        ]),
        "rerun",
    );
    ok(
        merge(&settings, &[&parts[0], &rerun, &parts[2]], &out),
        "merge",
    );
    let one = dir.path().join("one");
    ok(
        shadowcull(&["bake", s(&settings), "--out", s(&one)]),
        "bake",
    );
    assert_eq!(tree(&one), tree(&out));
    // A retried shard given twice agrees with itself: accepted.
    let again = dir.path().join("again");
    ok(
        merge(
            &settings,
            &[&parts[0], &rerun, &parts[2], &parts[0]],
            &again,
        ),
        "duplicate",
    );
    assert_eq!(tree(&one), tree(&again));
}

#[test]
fn damaged_partials_are_refused_naming_each() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    let parts = three_shards(&settings, dir.path(), "p");
    let bytes = std::fs::read(&parts[1]).unwrap();
    let truncated = dir.path().join("truncated.part");
    std::fs::write(&truncated, &bytes[..bytes.len() - 7]).unwrap();
    let flipped = dir.path().join("flipped.part");
    let mut flip = bytes.clone();
    flip[bytes.len() / 2] ^= 0x10;
    std::fs::write(&flipped, &flip).unwrap();
    let out = dir.path().join("out");
    for bad in [&truncated, &flipped] {
        let stderr = refused(
            merge(&settings, &[&parts[0], bad, &parts[2]], &out),
            &[bad.file_name().unwrap().to_str().unwrap(), "damaged"],
        );
        assert!(!stderr.contains("p0.part"), "{stderr}");
    }
    // Both at once: both named.
    refused(
        merge(
            &settings,
            &[&parts[0], &truncated, &flipped, &parts[2]],
            &out,
        ),
        &["truncated.part", "flipped.part"],
    );
    // Not a partial at all.
    refused(
        merge(&settings, &[&parts[0], &settings, &parts[2]], &out),
        &["bake.xml", "not a shadowcull partial"],
    );
    assert!(!out.exists());

    // A well-formed copy of shard 1 whose answer differs (one caster bit
    // flipped, checksum valid): the two copies of shard 1 disagree.
    let mut wrong = shadowcull::files::read_partial(&parts[1]).unwrap();
    wrong.units[0].words[0] ^= 1;
    let wrong_path = dir.path().join("wrong1.part");
    shadowcull::files::write_partial(&wrong_path, &wrong).unwrap();
    refused(
        merge(
            &settings,
            &[&parts[0], &parts[1], &wrong_path, &parts[2]],
            &out,
        ),
        &["wrong1.part", "p1.part", "differ"],
    );
    // Partials of another split.
    let two = dir.path().join("two0.part");
    ok(
        shadowcull(&["bake", s(&settings), "--shard", "0/2", "--partial", s(&two)]),
        "shard 0/2",
    );
    refused(
        merge(&settings, &[&parts[0], &parts[1], &parts[2], &two], &out),
        &["two0.part", "another split"],
    );
    assert!(!out.exists());
}

#[test]
fn shard_auto_reads_the_schedulers_variables_and_says_which() {
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Small, &dir.path().join("world"));
    let template = dir.path().join("s{index}of{count}.part");
    let run = |vars: &[(&str, &str)], extra: &[&str]| {
        let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_shadowcull"));
        command.args([
            "bake",
            s(&settings),
            "--shard",
            "auto",
            "--partial",
            s(&template),
        ]);
        command.args(extra);
        for var in [
            "SLURM_ARRAY_TASK_ID",
            "SLURM_ARRAY_TASK_MIN",
            "SLURM_ARRAY_TASK_STEP",
            "SLURM_ARRAY_TASK_COUNT",
            "JOB_COMPLETION_INDEX",
            "AWS_BATCH_JOB_ARRAY_INDEX",
            "AWS_BATCH_JOB_ARRAY_SIZE",
        ] {
            command.env_remove(var);
        }
        command.envs(vars.iter().copied());
        command.output().unwrap()
    };
    // --array=1-7:2: task id 5 is shard 2 of 4.
    let output = ok(
        run(
            &[
                ("SLURM_ARRAY_TASK_ID", "5"),
                ("SLURM_ARRAY_TASK_MIN", "1"),
                ("SLURM_ARRAY_TASK_STEP", "2"),
                ("SLURM_ARRAY_TASK_COUNT", "4"),
            ],
            &[],
        ),
        "slurm",
    );
    assert!(
        String::from_utf8_lossy(&output.stderr).contains("shard 2/4 from SLURM_ARRAY_TASK_ID=5")
    );
    assert!(dir.path().join("s2of4.part").is_file());
    let output = ok(
        run(&[("JOB_COMPLETION_INDEX", "3")], &["--shards", "5"]),
        "k8s",
    );
    assert!(
        String::from_utf8_lossy(&output.stderr).contains("shard 3/5 from JOB_COMPLETION_INDEX=3")
    );
    assert!(dir.path().join("s3of5.part").is_file());
    let output = ok(
        run(
            &[
                ("AWS_BATCH_JOB_ARRAY_INDEX", "0"),
                ("AWS_BATCH_JOB_ARRAY_SIZE", "2"),
            ],
            &[],
        ),
        "aws",
    );
    assert!(String::from_utf8_lossy(&output.stderr)
        .contains("shard 0/2 from AWS_BATCH_JOB_ARRAY_INDEX=0"));
    refused(run(&[("JOB_COMPLETION_INDEX", "3")], &[]), &["--shards N"]);
    refused(run(&[], &[]), &["SLURM_ARRAY_TASK_ID", "--shard I/N"]);
    // Usage errors: --shard without --partial, with --refine or --out.
    for extra in [
        &["--shard", "0/2"][..],
        &["--shard", "0/2", "--partial", "x.part", "--refine"],
        &["--shard", "0/2", "--partial", "x.part", "--out", "x"],
    ] {
        let mut args = vec!["bake", s(&settings)];
        args.extend(extra);
        assert_eq!(shadowcull(&args).status.code(), Some(2), "{extra:?}");
    }
    for bad in ["3/3", "1", "a/2", "0/0"] {
        let out = shadowcull(&["bake", s(&settings), "--shard", bad, "--partial", "x.part"]);
        refused(out, &["--shard"]);
    }
}

#[test]
fn merging_in_place_twice_works_because_written_masks_are_not_inputs() {
    // The fingerprint hashes chunks with their masks zeroed: a merge (or a
    // bake) writing `<shadow>` into the chunks does not make the partials
    // "other inputs", so a retried merge job succeeds.
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Village, &dir.path().join("world"));
    let parts = three_shards(&settings, dir.path(), "p");
    let merge_in_place = || {
        let mut args = vec!["merge", s(&settings)];
        args.extend(parts.iter().map(|p| s(p)));
        shadowcull(&args)
    };
    let first = ok(merge_in_place(), "first merge");
    assert!(String::from_utf8_lossy(&first.stdout).contains("wrote 9 of 9"));
    let second = ok(merge_in_place(), "second merge");
    assert!(String::from_utf8_lossy(&second.stdout).contains("wrote 0 of 9"));
    // Another value inside a chunk is still another input.
    let chunk = shadowcull::files::find_files(&dir.path().join("world"), ".chunk")
        .unwrap()
        .remove(0);
    let text = std::fs::read_to_string(&chunk).unwrap();
    let edited = text.replacen("<castsShadow>", "<castsShadow> ", 1);
    let edited = if edited == text {
        text.replacen("<resource>", "<resource> ", 1)
    } else {
        edited
    };
    assert_ne!(edited, text);
    std::fs::write(&chunk, edited).unwrap();
    refused(merge_in_place(), &["other inputs", "other content"]);
}

#[test]
fn the_merge_table_gives_the_shards_trace_time_and_rate() {
    // The merge traces no grid ray: its table once divided the shards' rays
    // by the merge's own seconds (e.g. 36 798 Mrays/s).
    let dir = tempfile::tempdir().unwrap();
    let settings = world(Preset::Small, &dir.path().join("world"));
    let parts = three_shards(&settings, dir.path(), "p");
    let report = dir.path().join("merge.json");
    let mut args = vec!["merge", s(&settings)];
    args.extend(parts.iter().map(|p| s(p)));
    args.extend(["--dry-run", "--report", s(&report)]);
    let output = ok(shadowcull(&args), "the merge");
    let table = String::from_utf8_lossy(&output.stdout).to_string();
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let units: Vec<partial::PartialUnit> = parts
        .iter()
        .flat_map(|p| shadowcull::files::read_partial(p).unwrap().units)
        .collect();
    for light in json["lights"].as_array().unwrap() {
        let index = light["index"].as_u64().unwrap() as u32;
        let shard_seconds: f64 = units
            .iter()
            .filter(|u| u.light == index)
            .map(|u| u.seconds)
            .sum();
        let seconds = light["trace_seconds"].as_f64().unwrap();
        assert!(shard_seconds > 0.0);
        assert!(
            seconds >= shard_seconds,
            "{light}: the shards traced for {shard_seconds} s"
        );
        let name = light["name"].as_str().unwrap();
        let row: Vec<&str> = table
            .lines()
            .find(|l| l.split_whitespace().nth(1) == Some(name))
            .unwrap_or_else(|| panic!("no row for {name}: {table}"))
            .split_whitespace()
            .collect();
        let rate: f64 = row[7].parse().unwrap();
        let expected = light["rays"].as_f64().unwrap() / seconds / 1e6;
        assert!(
            (rate - expected).abs() <= 0.01 + expected * 0.01,
            "{name}: {rate} Mrays/s printed, {expected} from the report: {table}"
        );
    }
}
