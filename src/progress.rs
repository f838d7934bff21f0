//! Where long work reports how far it got. The library never prints: the
//! loader and the bake call a [`Progress`] the caller chooses (bars, log
//! lines, JSON, nothing), from any thread.

use std::sync::atomic::{AtomicU64, Ordering};

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
    /// Computing and writing chunk files (total: files).
    Writing,
}

impl Phase {
    /// Every phase, in the order a bake meets them.
    pub const ALL: [Phase; 9] = [
        Phase::Chunks,
        Phase::Models,
        Phase::Terrain,
        Phase::BottomLevels,
        Phase::TopLevel,
        Phase::Calibrating,
        Phase::Tracing,
        Phase::Refining,
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
