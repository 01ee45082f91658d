//! `metrics` (cohort): every patient's volume and localization against the consensus, and the
//! cohort statistics (SPEC §3 metrics).
//!
//! Inputs, per patient: `select/result.json` and `train/train_log.csv`. Patients without a
//! ground-truth target are listed but not scored; patients that failed upstream are reported,
//! excluded and counted. Outputs: `results.csv` (SPEC §4 columns, in order) and `summary.json`
//! (see [`summary`]).

use crate::engine::{Context, Output, Stage};
use crate::stage::select::SelectResult;
use anyhow::Context as _;
use serde::{Deserialize, Serialize};

pub mod rows;
pub mod summary;

pub use rows::{PatientRow, SizeClass};

pub const VERSION: u32 = 2;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Bootstrap resamples for every confidence interval.
    pub bootstrap_resamples: usize,
    /// Seed of the bootstrap.
    pub seed: u64,
}

impl Default for Params {
    fn default() -> Self {
        Params { bootstrap_resamples: 10_000, seed: 0 }
    }
}

pub struct Metrics {
    pub params: Params,
}

impl Stage for Metrics {
    fn name(&self) -> &'static str {
        "metrics"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["train", "select"]
    }
    fn is_cohort(&self) -> bool {
        true
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        (stage, output) == ("select", "result.json") || (stage, output) == ("train", "train_log.csv")
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let mut rows = Vec::new();
        let mut unscored = Vec::new();
        for patient in ctx.cohort_patients() {
            let result: SelectResult = serde_json::from_slice(&ctx.read_patient(patient, "select", "result.json")?)
                .with_context(|| format!("{patient}: select/result.json"))?;
            let log = String::from_utf8(ctx.read_patient(patient, "train", "train_log.csv")?)?;
            let seconds = rows::train_seconds(&log).with_context(|| format!("{patient}: train_log.csv has no time"))?;
            match PatientRow::new(&result, seconds) {
                Some(row) => rows.push(row),
                None => unscored.push(patient.to_string()),
            }
        }
        let summary = summary::summarize(&rows, ctx.failed_patients(), &unscored, &self.params);
        Ok(vec![
            Output::new("results.csv", rows::results_csv(&rows)),
            Output::new("summary.json", serde_json::to_vec_pretty(&summary)?),
        ])
    }
}
