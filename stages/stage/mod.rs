//! The pipeline's stages, one module each, and the one place their graph is declared.
//!
//! Each module reads like the SPEC: its `Params`, its inputs and outputs, a `VERSION`, and one
//! pure `run`. Stages know nothing about caching.

pub mod hu;
pub mod ingest;

use crate::config::Config;
use crate::engine::{Stage, StageGraph, SOURCE};

/// Every stage name, in pipeline order (later stages arrive in later releases).
pub const STAGE_NAMES: &[&str] = &["ingest", "hu", "drr", "train", "grid", "sweep", "select", "metrics"];

/// The per-patient and cohort stages this build runs, configured from `config`.
pub fn graph(config: &Config) -> anyhow::Result<StageGraph> {
    let stages: Vec<Box<dyn Stage>> = vec![
        Box::new(ingest::Ingest { params: config.ingest.clone(), input: &[SOURCE] }),
        Box::new(hu::Hu { params: config.hu.clone() }),
    ];
    StageGraph::new(stages)
}

/// Serialises a stage's parameters for its cache key.
pub(crate) fn params_json<P: serde::Serialize>(params: &P) -> serde_json::Value {
    serde_json::to_value(params).expect("stage parameters serialise to JSON")
}
