//! Shared helpers of the integration tests.

use std::path::PathBuf;

/// Name of the environment variable that points at the real BigWorld data:
/// a folder holding `bigworld-14.4.1/res` and `fantasydemo-arctic/res`
/// (README.md, "Development").
pub const REALDATA_VAR: &str = "SHADOWCULL_REALDATA";

/// The real BigWorld data folder, or `None` after printing loudly that the
/// calling test did not run. `.ci/run` sets the variable, so in CI these
/// tests always run; `SHADOWCULL_REQUIRE_REALDATA=1` turns a missing folder
/// into a failure.
#[allow(dead_code)]
pub fn realdata(test: &str) -> Option<PathBuf> {
    match std::env::var_os(REALDATA_VAR) {
        Some(dir) => {
            let dir = PathBuf::from(dir);
            assert!(
                dir.is_dir(),
                "{REALDATA_VAR}={} is not a folder",
                dir.display()
            );
            // Absolute, so that tests which write the path into a settings
            // file in a temporary folder (read from there) find it when the
            // variable is relative, as the message below suggests.
            Some(dir.canonicalize().unwrap_or(dir))
        }
        None => {
            assert!(
                std::env::var_os("SHADOWCULL_REQUIRE_REALDATA").is_none(),
                "{test}: SHADOWCULL_REQUIRE_REALDATA is set but {REALDATA_VAR} is not"
            );
            say_not_run(&format!(
                "{test} needs real BigWorld data; set {REALDATA_VAR} to the folder holding \
                 bigworld-14.4.1/res and fantasydemo-arctic/res (README.md, Development)"
            ));
            None
        }
    }
}

/// Says that `test` did not run where a user sees it: the test harness
/// captures `eprintln!` of passing tests, but not writes to the standard
/// error handle itself, so plain `cargo test` shows these lines.
pub fn say_not_run(message: &str) {
    use std::io::Write as _;
    static COUNT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = COUNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
    let _ = writeln!(
        std::io::stderr(),
        "NOT RUN ({n}): {message} (the test passes without checking this)"
    );
}

/// The `<model>` elements of chunk text `text`, as byte ranges.
pub fn model_elements(text: &str) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(start) = text[from..].find("\t<model>") {
        let start = from + start;
        let end = start + text[start..].find("</model>\n").unwrap() + "</model>\n".len();
        out.push(start..end);
        from = end;
    }
    out
}

/// `element` (a `<model>` element's text) with its translation moved by
/// `dx`, `dz` metres.
pub fn moved(element: &str, dx: f64, dz: f64) -> String {
    let start = element.find("<row3>\t").unwrap() + "<row3>\t".len();
    let end = start + element[start..].find('\t').unwrap();
    let v: Vec<f64> = element[start..end]
        .split(' ')
        .map(|n| n.parse().unwrap())
        .collect();
    let row = format!("{:.6} {:.6} {:.6}", v[0] + dx, v[1], v[2] + dz);
    format!("{}{row}{}", &element[..start], &element[end..])
}
