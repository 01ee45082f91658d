//! What a run did, unit by unit and stage by stage: what the end table shows and
//! `run_report.json` holds.

use serde::Serialize;

/// What happened to one (unit, stage).
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "outcome", rename_all = "snake_case")]
pub enum Outcome {
    /// Served from the cache (the seconds it originally took to compute).
    Cached {
        seconds: f64,
    },
    /// Served from the remote cache, fetched into the local one (the seconds it originally took
    /// to compute).
    Fetched {
        seconds: f64,
    },
    Computed {
        seconds: f64,
    },
    Failed {
        cause: String,
    },
    /// Not attempted because an upstream stage failed.
    Skipped {
        upstream: String,
    },
    /// Not started because the run was asked to stop ([`StopRequest`]).
    Interrupted,
}

#[derive(Debug, Clone, Serialize)]
pub struct Record {
    pub unit: String,
    pub stage: String,
    #[serde(flatten)]
    pub outcome: Outcome,
}

/// Everything a run did, in unit order then stage order.
#[derive(Debug, Default, Serialize)]
pub struct RunSummary {
    pub records: Vec<Record>,
    /// From the start of the run to its end, waits for locks included.
    pub wall_seconds: f64,
    /// Warnings (a cache entry that failed a check and was computed again) and waits for other
    /// processes' locks, one line each, in the order they happened.
    pub notices: Vec<String>,
    /// Of `wall_seconds`, the time spent waiting for a `gc` on the cache (its live lease, on any
    /// host) to finish before the run could start.
    pub gc_wait_seconds: f64,
    /// Time stages spent waiting for keys other processes were computing, summed over the
    /// stages (so it can exceed `wall_seconds` when several waited at once).
    pub key_lock_wait_seconds: f64,
    /// How many of the records were served from the remote cache ([`Outcome::Fetched`]).
    pub fetched_from_remote: usize,
}

impl RunSummary {
    /// The summary with [`RunSummary::fetched_from_remote`] counted from its records.
    pub fn counted(mut self) -> RunSummary {
        self.fetched_from_remote = self.records.iter().filter(|r| matches!(r.outcome, Outcome::Fetched { .. })).count();
        self
    }

    pub fn failures(&self) -> impl Iterator<Item = &Record> {
        self.records.iter().filter(|r| matches!(r.outcome, Outcome::Failed { .. }))
    }

    pub fn count(&self, stage: &str, pred: impl Fn(&Outcome) -> bool) -> usize {
        self.records.iter().filter(|r| r.stage == stage && pred(&r.outcome)).count()
    }

    /// Whether a stop request left some stage unstarted.
    pub fn interrupted(&self) -> bool {
        self.records.iter().any(|r| matches!(r.outcome, Outcome::Interrupted))
    }
}
