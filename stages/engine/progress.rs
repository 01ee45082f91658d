//! What a run shows while it works, and the table it ends with.
//!
//! On a terminal: one indicatif bar per stage (done/cached/failed of total). Not on a terminal:
//! a plain line per computed or failed stage. In CI (`CI` set): only failures until the end table.

use super::summary::{Outcome, RunSummary};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::sync::Mutex;

#[derive(Default, Clone, Copy)]
struct Counts {
    computed: u64,
    cached: u64,
    failed: u64,
}

enum Mode {
    Bars { multi: MultiProgress, bars: BTreeMap<String, ProgressBar> },
    Lines,
    Quiet,
}

pub struct Progress {
    mode: Mode,
    counts: Mutex<BTreeMap<String, Counts>>,
}

impl Progress {
    /// Bars on a terminal, lines otherwise, silence in CI.
    pub fn auto(stages: &[(&str, u64)]) -> Progress {
        if std::env::var_os("CI").is_some_and(|v| !v.is_empty() && v != "false") {
            Progress::with_mode(Mode::Quiet, stages)
        } else if std::io::stderr().is_terminal() {
            let multi = MultiProgress::with_draw_target(ProgressDrawTarget::stderr());
            let style = ProgressStyle::with_template("{prefix:>8} [{bar:30.cyan/blue}] {pos}/{len} {msg}")
                .expect("valid template")
                .progress_chars("=> ");
            let bars = stages
                .iter()
                .map(|&(name, total)| {
                    let bar =
                        multi.add(ProgressBar::new(total).with_style(style.clone()).with_prefix(name.to_string()));
                    (name.to_string(), bar)
                })
                .collect();
            Progress::with_mode(Mode::Bars { multi, bars }, stages)
        } else {
            Progress::with_mode(Mode::Lines, stages)
        }
    }

    /// No output at all (tests, library use).
    pub fn hidden(stages: &[(&str, u64)]) -> Progress {
        Progress::with_mode(Mode::Quiet, stages)
    }

    fn with_mode(mode: Mode, stages: &[(&str, u64)]) -> Progress {
        let counts = stages.iter().map(|(n, _)| (n.to_string(), Counts::default())).collect();
        Progress { mode, counts: Mutex::new(counts) }
    }

    pub fn started(&self, stage: &str, unit: &str) {
        if let Mode::Bars { bars, .. } = &self.mode {
            if let Some(bar) = bars.get(stage) {
                bar.set_message(format!("{} · {unit}", self.tally(stage)));
            }
        }
    }

    pub fn finished(&self, stage: &str, unit: &str, outcome: &Outcome) {
        {
            let mut counts = self.counts.lock().expect("progress counts");
            let c = counts.entry(stage.to_string()).or_default();
            match outcome {
                // The tally counts a result fetched from the remote cache as cached.
                Outcome::Cached { .. } | Outcome::Fetched { .. } => c.cached += 1,
                Outcome::Computed { .. } => c.computed += 1,
                Outcome::Failed { .. } => c.failed += 1,
                // The tally names computed, cached and failed; the end table lists the rest.
                Outcome::Skipped { .. } | Outcome::Interrupted => {}
            }
        }
        match &self.mode {
            Mode::Bars { bars, .. } => {
                if let Some(bar) = bars.get(stage) {
                    bar.inc(1);
                    bar.set_message(self.tally(stage));
                    if bar.position() >= bar.length().unwrap_or(0) {
                        bar.finish();
                    }
                }
            }
            Mode::Lines | Mode::Quiet => match outcome {
                Outcome::Computed { seconds } if matches!(self.mode, Mode::Lines) => {
                    eprintln!("{stage:>8} {unit}: computed in {seconds:.2} s")
                }
                // A failure is never noise: it reaches stderr in CI too.
                Outcome::Failed { cause } => eprintln!("{stage:>8} {unit}: FAILED: {cause}"),
                _ => {}
            },
        }
    }

    /// A line that must be seen (a warning, a wait): above the bars on a terminal, else on
    /// stderr, in CI too.
    pub fn notice(&self, line: &str) {
        match &self.mode {
            Mode::Bars { multi, .. } => {
                if multi.println(format!("aret-pipe: {line}")).is_err() {
                    eprintln!("aret-pipe: {line}");
                }
            }
            Mode::Lines | Mode::Quiet => eprintln!("aret-pipe: {line}"),
        }
    }

    fn tally(&self, stage: &str) -> String {
        let c = self.counts.lock().expect("progress counts").get(stage).copied().unwrap_or_default();
        format!("{} computed · {} cached · {} failed", c.computed, c.cached, c.failed)
    }
}

/// A patient × stage grid of short cells; stages with no cell for a unit show `·`.
pub fn grid(cells: &[(String, String, String)], stages: &[&str]) -> String {
    let mut units: Vec<&str> = Vec::new();
    let mut by_key: BTreeMap<(&str, &str), &str> = BTreeMap::new();
    for (unit, stage, cell) in cells {
        if !units.contains(&unit.as_str()) {
            units.push(unit);
        }
        by_key.insert((unit, stage), cell);
    }
    let first = units.iter().map(|u| u.len()).max().unwrap_or(0).max("patient".len());
    let widths: Vec<usize> = stages.iter().map(|s| s.len().max(8)).collect();
    let mut out = format!("{:<first$}", "patient");
    for (s, w) in stages.iter().zip(&widths) {
        out.push_str(&format!("  {s:>w$}"));
    }
    out.push('\n');
    for unit in &units {
        out.push_str(&format!("{unit:<first$}"));
        for (s, w) in stages.iter().zip(&widths) {
            let cell = by_key.get(&(*unit, *s)).copied().unwrap_or("·");
            out.push_str(&format!("  {cell:>w$}"));
        }
        out.push('\n');
    }
    out
}

/// The end-of-run table: cached / fetched (from the remote cache) / seconds computed / FAILED /
/// stopped (not started after a stop request) per patient and stage, totals, causes.
pub fn table(summary: &RunSummary, stages: &[&str]) -> String {
    let cells: Vec<(String, String, String)> = summary
        .records
        .iter()
        .map(|r| {
            let cell = match &r.outcome {
                Outcome::Cached { .. } => "cached".to_string(),
                Outcome::Fetched { .. } => "fetched".to_string(),
                Outcome::Computed { seconds } => format!("{seconds:.2}s"),
                Outcome::Failed { .. } => "FAILED".to_string(),
                Outcome::Skipped { .. } => "skipped".to_string(),
                Outcome::Interrupted => "stopped".to_string(),
            };
            (r.unit.clone(), r.stage.clone(), cell)
        })
        .collect();
    let mut out = grid(&cells, stages);
    let n = |f: fn(&Outcome) -> bool| summary.records.iter().filter(|r| f(&r.outcome)).count();
    let fetched = n(|o| matches!(o, Outcome::Fetched { .. }));
    out.push_str(&format!(
        "{} computed, {} cached{}, {} failed, {} skipped in {:.2} s{}\n",
        n(|o| matches!(o, Outcome::Computed { .. })),
        n(|o| matches!(o, Outcome::Cached { .. })),
        if fetched > 0 { format!(", {fetched} fetched from the remote cache") } else { String::new() },
        n(|o| matches!(o, Outcome::Failed { .. })),
        n(|o| matches!(o, Outcome::Skipped { .. })),
        summary.wall_seconds,
        waits(summary)
    ));
    for line in &summary.notices {
        out.push_str(&format!("note: {line}\n"));
    }
    for r in summary.failures() {
        if let Outcome::Failed { cause } = &r.outcome {
            out.push_str(&format!("failed: {} · {}: {cause}\n", r.unit, r.stage));
        }
    }
    let stopped = n(|o| matches!(o, Outcome::Interrupted));
    if stopped > 0 {
        out.push_str(&format!(
            "stopped: {stopped} stages were not started; run the same command again to go on (what finished is cached)\n"
        ));
    }
    out
}

/// What the run's time includes of waiting for other processes (empty when it waited for none).
fn waits(summary: &RunSummary) -> String {
    let mut parts = Vec::new();
    if summary.gc_wait_seconds >= 0.01 {
        parts.push(format!("{:.2} s of it waiting for gc", summary.gc_wait_seconds));
    }
    if summary.key_lock_wait_seconds >= 0.01 {
        parts.push(format!("stages waited {:.2} s for keys other processes computed", summary.key_lock_wait_seconds));
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!(" ({})", parts.join("; "))
    }
}
