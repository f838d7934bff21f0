//! Where long work reports how far it got. The library never prints: the
//! loader and the bake call a [`Progress`] the caller chooses (bars, log
//! lines, JSON, nothing), from any thread. [`LinePace`] is the rule for
//! when a display that prints lines (a log, a pipe) prints one, kept here
//! with its times passed in so the promise "a line at least every 10 s"
//! is tested without waiting.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A stretch of work that can take more than a second.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Parsing the chunk files (total: chunk files).
    Chunks,
    /// Loading each distinct model (total: models).
    Models,
    /// Reading terrain blocks (total: blocks).
    Terrain,
    /// One BVH per distinct model and one height field per block, built
    /// once per bake (total: models + blocks).
    BottomLevels,
    /// A light's top level over the parts in its reach (total: 1).
    TopLevel,
    /// Sampling a light's rays to measure this machine's ray rate (total:
    /// rays in the sample).
    Calibrating,
    /// A light's texel rays (total: rays).
    Tracing,
    /// Refinement rays at casters not yet proven useful (total: casters).
    Refining,
    /// Every chunk file read back, its kept bits taken and its new
    /// `<shadow>`s written in memory, before anything is written (total:
    /// chunk files).
    Output,
    /// Writing the chunk files that change (total: files).
    Writing,
}

impl Phase {
    /// Every phase, in the order a bake meets them.
    pub const ALL: [Phase; 10] = [
        Phase::Chunks,
        Phase::Models,
        Phase::Terrain,
        Phase::BottomLevels,
        Phase::TopLevel,
        Phase::Calibrating,
        Phase::Tracing,
        Phase::Refining,
        Phase::Output,
        Phase::Writing,
    ];

    /// The name in progress lines and JSON.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Chunks => "chunks",
            Phase::Models => "models",
            Phase::Terrain => "terrain",
            Phase::BottomLevels => "bottom-levels",
            Phase::TopLevel => "top-level",
            Phase::Calibrating => "calibrating",
            Phase::Tracing => "tracing",
            Phase::Refining => "refining",
            Phase::Output => "output",
            Phase::Writing => "writing",
        }
    }
}

/// Receives progress. `begin` opens a phase (for one light, or the whole
/// world when `light` is `None`); `advance` gives the running count of
/// the open phase and may come from several threads at once; `end` closes
/// it.
pub trait Progress: Sync {
    fn begin(&self, _phase: Phase, _light: Option<&str>, _total: u64) {}
    fn advance(&self, _done: u64) {}
    fn end(&self) {}
    /// A line of what a phase did (the bake cache's: what was reused,
    /// what was computed and why): `text` for people, `event` and `fields`
    /// for machines.
    fn note(&self, _event: &str, _text: &str, _fields: &serde_json::Value) {}
}

/// No progress output.
pub struct Silent;
impl Progress for Silent {}

/// Counts finished work items from worker threads and passes the running
/// total on.
pub struct Counter<'a> {
    progress: &'a dyn Progress,
    done: AtomicU64,
}

impl<'a> Counter<'a> {
    /// Opens `phase` on `progress`; [`Counter::finish`] closes it.
    pub fn begin(
        progress: &'a dyn Progress,
        phase: Phase,
        light: Option<&str>,
        total: u64,
    ) -> Self {
        progress.begin(phase, light, total);
        Counter {
            progress,
            done: AtomicU64::new(0),
        }
    }

    pub fn add(&self, n: u64) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        self.progress.advance(done);
    }

    /// The running total.
    pub fn done(&self) -> u64 {
        self.done.load(Ordering::Relaxed)
    }

    pub fn finish(self) {
        self.progress.end();
    }
}

/// When a display that prints lines prints one during an open phase: on
/// progress at most every `interval`, and from a heartbeat (a caller's
/// thread calling [`LinePace::on_beat`] every [`LinePace::POLL`]) when the
/// phase has printed nothing for [`LinePace::HEARTBEAT`]. So a person
/// tailing a log, or a CI job that kills silent steps, hears of a long
/// phase at least every [`LinePace::MAX_SILENCE`], whether its work
/// advances in many small steps, a few large ones, or not at all (a top
/// level being built).
#[derive(Debug, Clone)]
pub struct LinePace {
    interval: Duration,
    last_line: Instant,
}

impl LinePace {
    /// The promise: never longer than this without a line.
    pub const MAX_SILENCE: Duration = Duration::from_secs(10);
    /// A silent phase gets a line after this long.
    pub const HEARTBEAT: Duration = Duration::from_secs(8);
    /// How often the heartbeat must be asked; with [`LinePace::HEARTBEAT`]
    /// it stays under [`LinePace::MAX_SILENCE`].
    pub const POLL: Duration = Duration::from_millis(250);

    /// A phase opened at `now` (its first line, if any, is the caller's);
    /// lines on progress at most every `interval`, which is cut to
    /// [`LinePace::MAX_SILENCE`].
    pub fn new(interval: Duration, now: Instant) -> LinePace {
        LinePace {
            interval: interval.min(Self::MAX_SILENCE),
            last_line: now,
        }
    }

    /// Progress was heard at `now`: whether to print a line (then counted
    /// as printed).
    pub fn on_progress(&mut self, now: Instant) -> bool {
        self.due(now, self.interval)
    }

    /// The heartbeat at `now`: whether the phase has been silent long
    /// enough for a line (then counted as printed).
    pub fn on_beat(&mut self, now: Instant) -> bool {
        self.due(now, Self::HEARTBEAT)
    }

    fn due(&mut self, now: Instant, after: Duration) -> bool {
        let due = now.saturating_duration_since(self.last_line) >= after;
        if due {
            self.last_line = now;
        }
        due
    }
}

/// Every call kept in order: what tests assert phases and counts on.
#[cfg(test)]
#[derive(Default)]
pub(crate) struct Recorded {
    pub calls: std::sync::Mutex<Vec<Call>>,
}

#[cfg(test)]
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Call {
    Begin(Phase, Option<String>, u64),
    Advance(u64),
    End,
}

#[cfg(test)]
impl Recorded {
    pub fn calls(&self) -> Vec<Call> {
        self.calls.lock().unwrap().clone()
    }
}

#[cfg(test)]
impl Progress for Recorded {
    fn begin(&self, phase: Phase, light: Option<&str>, total: u64) {
        let call = Call::Begin(phase, light.map(str::to_string), total);
        self.calls.lock().unwrap().push(call);
    }
    fn advance(&self, done: u64) {
        self.calls.lock().unwrap().push(Call::Advance(done));
    }
    fn end(&self) {
        self.calls.lock().unwrap().push(Call::End);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Drives a pace through `span` of a phase: the heartbeat every
    /// [`LinePace::POLL`], progress at the times `progress` gives (those
    /// within `span`); returns the times a line was printed, the phase's
    /// start and end included as a reader's reference points.
    fn lines_over(interval: Duration, span: Duration, progress: &[Duration]) -> Vec<Duration> {
        let start = Instant::now();
        let mut pace = LinePace::new(interval, start);
        let mut lines = vec![Duration::ZERO];
        let within = progress.iter().filter(|&&t| t <= span);
        let mut events: Vec<(Duration, bool)> = within.map(|&t| (t, true)).collect();
        let beats = (span.as_millis() / LinePace::POLL.as_millis()) as u32;
        events.extend((1..=beats).map(|k| (LinePace::POLL * k, false)));
        events.sort();
        for (at, is_progress) in events {
            let now = start + at;
            let printed = if is_progress {
                pace.on_progress(now)
            } else {
                pace.on_beat(now)
            };
            if printed {
                lines.push(at);
            }
        }
        lines.push(span);
        lines
    }

    fn longest_silence(lines: &[Duration]) -> Duration {
        lines.windows(2).map(|w| w[1] - w[0]).max().unwrap()
    }

    #[test]
    fn a_long_phase_prints_a_line_at_least_every_ten_seconds() {
        // The heartbeat, asked every poll, fires before the promise runs out.
        assert!(LinePace::HEARTBEAT + LinePace::POLL <= LinePace::MAX_SILENCE);
        let span = Duration::from_secs(600);
        let ms = Duration::from_millis;
        // No progress at all (a top level being built).
        let silent = lines_over(ms(5000), span, &[]);
        assert!(
            longest_silence(&silent) <= LinePace::MAX_SILENCE,
            "{silent:?}"
        );
        // Progress every millisecond: a line every `interval`; an interval
        // asked above the promise is cut, and the heartbeat comes first.
        let steady: Vec<Duration> = (1..600_000).map(ms).collect();
        for (interval, longest) in [
            (ms(0), ms(1)),
            (ms(5000), ms(5000)),
            (ms(60_000), LinePace::HEARTBEAT),
        ] {
            let lines = lines_over(interval, span, &steady);
            assert_eq!(longest_silence(&lines), longest, "{interval:?}");
        }
        // Progress at seeded random moments, with gaps of up to 30 s.
        let mut rng = crate::rng::Rng::new(14);
        for _ in 0..50 {
            let mut at = Duration::ZERO;
            let mut progress = Vec::new();
            while at < span {
                at += ms((rng.unit() * rng.unit() * 30_000.0) as u64);
                progress.push(at);
            }
            let lines = lines_over(ms(5000), span, &progress);
            assert!(
                longest_silence(&lines) <= LinePace::MAX_SILENCE,
                "{progress:?}"
            );
        }
    }

    #[test]
    fn a_line_on_progress_only_after_the_interval() {
        let start = Instant::now();
        let mut pace = LinePace::new(Duration::from_secs(5), start);
        assert!(!pace.on_progress(start + Duration::from_secs(4)));
        assert!(pace.on_progress(start + Duration::from_secs(5)));
        assert!(!pace.on_beat(start + Duration::from_secs(12)));
        assert!(pace.on_beat(start + Duration::from_secs(13)));
    }
}
