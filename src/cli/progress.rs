//! Progress for people and machines: a bar with an ETA on a terminal,
//! plain lines (elapsed time, phase, light, ETA) when standard error is a
//! pipe or a log, one JSON object per line with `--progress json`, nothing
//! with `--quiet`. Everything goes to standard error, through `messages`
//! (which knows the form), like every other line the binary writes there.

use super::messages::{self, StderrForm};
use indicatif::{ProgressBar, ProgressStyle};
use shadowcull::progress::{LinePace, Phase, Progress};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How progress is shown (`--progress`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ProgressMode {
    /// A bar on a terminal, lines otherwise.
    Auto,
    /// Lines with elapsed time, light and ETA.
    Lines,
    /// One JSON object per line: phase, light, done, total, eta_s.
    Json,
    /// Nothing (as `--quiet`).
    None,
}

/// The progress flags every long-running command takes.
#[derive(Debug, Clone, clap::Args)]
pub struct ProgressArgs {
    /// Progress on standard error: auto (a bar on a terminal, lines
    /// otherwise), lines, json (one object per line; every other line on
    /// standard error is then a JSON object too) or none.
    #[arg(long, value_enum, default_value_t = ProgressMode::Auto)]
    progress: ProgressMode,
    /// No progress and no informational messages (errors and warnings
    /// still print).
    #[arg(long, short)]
    pub quiet: bool,
    /// Seconds between progress lines of a phase (lines and json).
    #[arg(long, value_name = "S", default_value_t = 5.0, hide = true)]
    progress_interval: f64,
}

impl ProgressArgs {
    /// The form of every line on standard error: `--progress json` makes
    /// each a JSON object, `--quiet` or not.
    pub fn stderr_form(&self) -> StderrForm {
        match self.progress {
            ProgressMode::Json => StderrForm::Json,
            _ => StderrForm::Text,
        }
    }
}

/// Where a run's grid answers come from, which names its grid phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridAnswers {
    /// Traced here: the phase is `tracing`.
    Traced,
    /// OR-ed from the shards' partial results (`merge`), no grid ray
    /// traced: the phase is `merging`.
    Merged,
}

enum Style {
    Bar,
    Lines,
    Json,
    Silent,
}

struct Open {
    phase: Phase,
    light: Option<String>,
    total: u64,
    started: Instant,
    /// When the next line is due (lines and json).
    pace: LinePace,
    /// The latest count heard.
    done: u64,
    bar: Option<ProgressBar>,
}

/// What the reporting threads and the heartbeat share.
struct Shared {
    style: Style,
    grid: GridAnswers,
    started: Instant,
    interval: Duration,
    open: Mutex<Option<Open>>,
    stop: AtomicBool,
}

pub struct Reporter {
    shared: Arc<Shared>,
    /// `--quiet`: no informational messages either.
    quiet: bool,
}

impl Drop for Reporter {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
    }
}

impl Reporter {
    /// A reporter for a run that traces its grids.
    pub fn new(args: &ProgressArgs) -> Reporter {
        Reporter::with_grid(args, GridAnswers::Traced)
    }

    pub fn with_grid(args: &ProgressArgs, grid: GridAnswers) -> Reporter {
        let style = match (args.quiet, args.progress) {
            (true, _) | (_, ProgressMode::None) => Style::Silent,
            (_, ProgressMode::Json) => Style::Json,
            (_, ProgressMode::Lines) => Style::Lines,
            (_, ProgressMode::Auto) if std::io::stderr().is_terminal() => Style::Bar,
            (_, ProgressMode::Auto) => Style::Lines,
        };
        let lines = matches!(style, Style::Lines | Style::Json);
        let shared = Arc::new(Shared {
            style,
            grid,
            started: Instant::now(),
            interval: Duration::from_secs_f64(
                args.progress_interval
                    .clamp(0.0, LinePace::MAX_SILENCE.as_secs_f64()),
            ),
            open: Mutex::new(None),
            stop: AtomicBool::new(false),
        });
        if lines {
            let beat = Arc::clone(&shared);
            std::thread::spawn(move || beat.heartbeat());
        }
        Reporter {
            shared,
            quiet: args.quiet,
        }
    }

    /// An informational message (not with `--quiet`): `text` for people,
    /// or with `--progress json` the event `name` with `fields` and the
    /// text as its `message`.
    pub fn say(&self, name: &str, text: &str, fields: serde_json::Value) {
        if self.quiet {
            return;
        }
        self.suspend(|| messages::say(name, text, fields));
    }

    fn suspend(&self, f: impl FnOnce()) {
        let bar = self
            .shared
            .open
            .lock()
            .ok()
            .and_then(|o| o.as_ref().and_then(|o| o.bar.clone()));
        match bar {
            Some(bar) => bar.suspend(f),
            None => f(),
        }
    }
}

impl Shared {
    /// The phase's name in lines, bars and JSON.
    fn phase_name(&self, phase: Phase) -> &'static str {
        match (phase, self.grid) {
            (Phase::Tracing, GridAnswers::Merged) => "merging",
            _ => phase.name(),
        }
    }

    /// Until the reporter is dropped: a line for an open phase that has
    /// been silent for [`LinePace::HEARTBEAT`] (a long build hears of no
    /// progress), so a log gets one at least every
    /// [`LinePace::MAX_SILENCE`].
    fn heartbeat(&self) {
        while !self.stop.load(Ordering::Relaxed) {
            std::thread::sleep(LinePace::POLL);
            if let Ok(mut slot) = self.open.lock() {
                if let Some(open) = slot.as_mut() {
                    if open.pace.on_beat(Instant::now()) {
                        self.line(open, open.done);
                    }
                }
            }
        }
    }

    fn line(&self, open: &Open, done: u64) {
        let elapsed = self.started.elapsed().as_secs_f64();
        let eta = eta_seconds(open, done);
        match self.style {
            Style::Json => messages::event(
                "progress",
                serde_json::json!({
                    "phase": self.phase_name(open.phase),
                    "light": open.light,
                    "done": done,
                    "total": open.total,
                    "eta_s": eta,
                    "elapsed_s": (elapsed * 1000.0).round() / 1000.0,
                }),
            ),
            Style::Lines => messages::write_line(&format!(
                "[{elapsed:>7.1} s] {}{}: {done}/{} ({}%), eta {}",
                self.phase_name(open.phase),
                open.light
                    .as_deref()
                    .map(|l| format!(" light {l}"))
                    .unwrap_or_default(),
                open.total,
                done * 100 / open.total.max(1),
                eta.map(|s| format!("{s:.0} s"))
                    .unwrap_or_else(|| "?".into())
            )),
            Style::Bar | Style::Silent => {}
        }
    }
}

/// Seconds left at the phase's rate so far, `None` before anything is done.
fn eta_seconds(open: &Open, done: u64) -> Option<f64> {
    if done == 0 {
        return None;
    }
    let spent = open.started.elapsed().as_secs_f64();
    let left = open.total.saturating_sub(done) as f64;
    Some((spent * left / done as f64 * 10.0).round() / 10.0)
}

impl Progress for Reporter {
    fn begin(&self, phase: Phase, light: Option<&str>, total: u64) {
        super::memory::entering(phase);
        if matches!(self.shared.style, Style::Silent) {
            return;
        }
        let bar = matches!(self.shared.style, Style::Bar).then(|| {
            let bar = ProgressBar::new(total);
            bar.set_style(
                ProgressStyle::with_template(
                    "{prefix:>24} [{bar:40}] {human_pos}/{human_len} {elapsed_precise} eta {eta}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            let name = self.shared.phase_name(phase);
            bar.set_prefix(match light {
                Some(light) => format!("{name} {light}"),
                None => name.to_string(),
            });
            bar
        });
        let now = Instant::now();
        let open = Open {
            phase,
            light: light.map(str::to_string),
            total,
            started: now,
            pace: LinePace::new(self.shared.interval, now),
            done: 0,
            bar,
        };
        if matches!(self.shared.style, Style::Json) {
            self.shared.line(&open, 0);
        }
        if let Ok(mut slot) = self.shared.open.lock() {
            *slot = Some(open);
        }
    }

    fn advance(&self, done: u64) {
        let Ok(mut slot) = self.shared.open.try_lock() else {
            // Another thread is reporting; the next call will.
            return;
        };
        let Some(open) = slot.as_mut() else { return };
        open.done = open.done.max(done);
        if let Some(bar) = &open.bar {
            bar.set_position(done.max(bar.position()));
            return;
        }
        if done < open.total && open.pace.on_progress(Instant::now()) {
            self.shared.line(open, done);
        }
    }

    fn note(&self, event: &str, text: &str, fields: &serde_json::Value) {
        self.say(event, text, fields.clone());
    }

    fn end(&self) {
        let Some(open) = self.shared.open.lock().ok().and_then(|mut o| o.take()) else {
            return;
        };
        // Lines: a phase that was quick gets no line (a log of a small
        // bake stays short); tracing always says what it did.
        let worth_a_line = matches!(self.shared.style, Style::Json)
            || open.phase == Phase::Tracing
            || open.started.elapsed() >= Duration::from_secs(1);
        match &open.bar {
            Some(bar) => bar.finish_and_clear(),
            None if worth_a_line => self.shared.line(&open, open.total),
            None => {}
        }
    }
}
