//! Everything the binary writes to standard error passes through here, so
//! that `--progress json` can keep its promise: every line on standard
//! error is then one JSON object with an `event` field (`progress`,
//! `loaded`, `plan`, `warning`, `problem`, `error`, …), and a log reader
//! never meets a line of plain text. In the default text form each event
//! is the line a person reads. Standard output is not touched here.
//!
//! The form is process-wide (set once from the command line) because the
//! last word of a failed run (`main`'s error, the allocator's out-of-memory
//! message, a panic) comes from places that see no command's arguments.

use serde_json::{json, Map, Value};
use std::io::Write as _;
use std::sync::atomic::{AtomicBool, Ordering};

/// How lines on standard error are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StderrForm {
    /// Lines for people.
    Text,
    /// One JSON object per line (`--progress json`).
    Json,
}

static JSON: AtomicBool = AtomicBool::new(false);

/// Chooses the form for the rest of the process. In the JSON form a panic
/// is reported as an `error` event too.
pub fn set_form(form: StderrForm) {
    JSON.store(form == StderrForm::Json, Ordering::Relaxed);
    if form == StderrForm::Json {
        std::panic::set_hook(Box::new(|info| {
            event(
                "error",
                json!({ "message": format!("internal error (please report it): {info}") }),
            );
        }));
    }
}

/// Whether standard error takes JSON objects. Reads one atomic, allocates
/// nothing (the out-of-memory path asks).
pub fn is_json() -> bool {
    JSON.load(Ordering::Relaxed)
}

/// Writes one line whole, in one write: threads and the progress
/// heartbeat write too, and a reader of a pipe gets no torn line.
pub fn write_line(line: &str) {
    let mut bytes = Vec::with_capacity(line.len() + 1);
    bytes.extend_from_slice(line.as_bytes());
    bytes.push(b'\n');
    let _ = std::io::stderr().lock().write_all(&bytes);
}

/// Writes `{"event": NAME, ...fields}` as one line, whatever the form:
/// for callers that have already decided on JSON.
pub fn event(name: &str, fields: Value) {
    let mut object = Map::new();
    object.insert("event".into(), Value::from(name));
    if let Value::Object(fields) = fields {
        object.extend(fields);
    }
    write_line(&Value::Object(object).to_string());
}

/// An event with a text for people: `text` (one or more lines) in the text
/// form, `{"event": NAME, "message": text, ...fields}` in the JSON form.
pub fn say(name: &str, text: &str, fields: Value) {
    if is_json() {
        let mut fields = match fields {
            Value::Object(map) => map,
            _ => Map::new(),
        };
        fields.insert("message".into(), Value::from(text));
        event(name, Value::Object(fields));
    } else {
        write_line(text);
    }
}

/// `warning: MESSAGE`.
pub fn warning(message: &str) {
    if is_json() {
        event("warning", json!({ "message": message }));
    } else {
        write_line(&format!("warning: {message}"));
    }
}

/// What a listed problem does to the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProblemOutcome {
    /// The run fails after the list (the text form indents it under the
    /// error that follows).
    Fails,
    /// `--keep-going`: what the problem names is left out, the run goes on.
    LeftOut,
}

/// One problem of the input: `what` (a file, an element) and `why`.
pub fn problem(what: &str, why: &str, outcome: ProblemOutcome) {
    if is_json() {
        event(
            "problem",
            json!({
                "what": what,
                "why": why,
                "left_out": outcome == ProblemOutcome::LeftOut,
            }),
        );
    } else if outcome == ProblemOutcome::LeftOut {
        write_line(&format!("warning: left out: {what}: {why}"));
    } else {
        write_line(&format!("  {what}: {why}"));
    }
}

/// The error a run ends with (exit status 1 or 2).
pub fn error(message: &str) {
    if is_json() {
        event("error", json!({ "message": message }));
    } else {
        write_line(&format!("error: {message}"));
    }
}

/// Whether a command line asks for `--progress json` (read from the raw
/// arguments, for the usage errors found before they parse).
pub fn json_asked<I, S>(args: I) -> bool
where
    I: IntoIterator<Item = S>,
    S: AsRef<std::ffi::OsStr>,
{
    let mut previous_was_flag = false;
    for arg in args {
        let arg = arg.as_ref().to_string_lossy();
        if arg == "--progress=json" || (previous_was_flag && arg == "json") {
            return true;
        }
        previous_was_flag = arg == "--progress";
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_json_is_found_in_either_spelling() {
        assert!(json_asked([
            "shadowcull",
            "bake",
            "x.xml",
            "--progress",
            "json"
        ]));
        assert!(json_asked([
            "shadowcull",
            "bake",
            "--progress=json",
            "x.xml"
        ]));
        assert!(!json_asked([
            "shadowcull",
            "bake",
            "x.xml",
            "--progress",
            "lines"
        ]));
        // A settings file named `json` is not the flag's value.
        assert!(!json_asked(["shadowcull", "plan", "json", "--json"]));
    }
}
