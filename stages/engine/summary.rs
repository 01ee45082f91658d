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
    pub wall_seconds: f64,
}

impl RunSummary {
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
