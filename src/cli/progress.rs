//! Bake progress for people: a bar per light on a terminal, a few plain
//! lines otherwise (batch logs should not fill with control characters).

use indicatif::{ProgressBar, ProgressStyle};
use shadowcull::bake::{LightReport, Progress};
use shadowcull::formats::bake_settings::LightSettings;
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

pub struct Reporter {
    terminal: bool,
    bar: Mutex<Option<ProgressBar>>,
    /// Plain mode: rays at which the next line is due, and the total.
    next_line: AtomicU64,
    total: AtomicU64,
}

impl Reporter {
    pub fn new() -> Reporter {
        Reporter {
            terminal: std::io::stderr().is_terminal(),
            bar: Mutex::new(None),
            next_line: AtomicU64::new(u64::MAX),
            total: AtomicU64::new(0),
        }
    }
}

impl Progress for Reporter {
    fn bottom_levels_building(&self, models: usize, terrain_blocks: usize) {
        // A bar cannot move during the build; one line says what happens.
        eprintln!(
            "building the bottom levels: {models} model BVHs, {terrain_blocks} terrain height fields"
        );
    }

    fn light_started(&self, index: usize, light: &LightSettings, rays: u64) {
        let label = format!("light {index} {} ({})", light.name, light.kind.type_name());
        if self.terminal {
            let bar = ProgressBar::new(rays);
            bar.set_style(
                ProgressStyle::with_template(
                    "{prefix} [{bar:40}] {human_pos}/{human_len} rays, eta {eta}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            bar.set_prefix(label);
            if let Ok(mut slot) = self.bar.lock() {
                *slot = Some(bar);
            }
        } else {
            eprintln!("{label}: tracing {rays} rays");
            self.total.store(rays, Ordering::Relaxed);
            self.next_line.store(rays / 4, Ordering::Relaxed);
        }
    }

    fn rays_traced(&self, index: usize, done: &AtomicU64) {
        let done = done.load(Ordering::Relaxed);
        if self.terminal {
            if let Ok(slot) = self.bar.lock() {
                if let Some(bar) = slot.as_ref() {
                    bar.set_position(done);
                }
            }
        } else {
            let due = self.next_line.load(Ordering::Relaxed);
            let total = self.total.load(Ordering::Relaxed);
            if done >= due
                && done < total
                && self
                    .next_line
                    .compare_exchange(due, due + total / 4, Ordering::Relaxed, Ordering::Relaxed)
                    .is_ok()
            {
                eprintln!(
                    "light {index}: {}% of rays traced",
                    done * 100 / total.max(1)
                );
            }
        }
    }

    fn light_finished(&self, report: &LightReport) {
        if let Ok(mut slot) = self.bar.lock() {
            if let Some(bar) = slot.take() {
                bar.finish_and_clear();
            }
        }
        if !self.terminal {
            eprintln!(
                "light {} {}: done in {:.2} s",
                report.index, report.name, report.seconds
            );
        }
    }
}
