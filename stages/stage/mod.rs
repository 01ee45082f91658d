//! The pipeline's stages, one module each, and the one place their graph is declared.
//!
//! Each module reads like the SPEC: its `Params`, its inputs and outputs, a `VERSION`, and one
//! pure `run`. Stages know nothing about caching.

pub mod drr;
pub mod grid;
pub mod hu;
pub mod ingest;
pub mod metrics;
pub mod phantom;
pub mod select;
pub mod sweep;
pub mod train;

use crate::config::{Config, DatasetKind};
use crate::engine::{Stage, StageGraph, SOURCE};

/// Every stage name, in pipeline order (`phantom` only for phantom datasets; later stages
/// arrive in later releases).
pub const STAGE_NAMES: &[&str] = &["phantom", "ingest", "hu", "drr", "train", "grid", "sweep", "select", "metrics"];

/// The per-patient and cohort stages this build runs, configured from `config`.
pub fn graph(config: &Config) -> anyhow::Result<StageGraph> {
    let mut stages: Vec<Box<dyn Stage>> = Vec::new();
    // A phantom dataset generates each patient's DICOM first; ingest then reads those files.
    let ingest_input: &'static [&'static str] = if config.dataset.kind == DatasetKind::Phantom {
        stages.push(Box::new(phantom::Phantom { params: config.dataset.phantom.clone().unwrap_or_default() }));
        &["phantom"]
    } else {
        &[SOURCE]
    };
    stages.push(Box::new(ingest::Ingest { params: config.ingest.clone(), input: ingest_input }));
    stages.push(Box::new(hu::Hu { params: config.hu.clone() }));
    stages.push(Box::new(drr::Drr { params: config.drr.clone() }));
    stages.push(Box::new(train::Train { params: config.train.clone() }));
    stages.push(Box::new(grid::Grid { params: config.grid.clone() }));
    stages.push(Box::new(sweep::Sweep { params: config.sweep.clone() }));
    stages.push(Box::new(select::Select { params: config.select.clone() }));
    stages.push(Box::new(metrics::Metrics { params: config.metrics.clone() }));
    StageGraph::new(stages)
}

/// Serialises a stage's parameters for its cache key.
pub(crate) fn params_json<P: serde::Serialize>(params: &P) -> serde_json::Value {
    serde_json::to_value(params).expect("stage parameters serialise to JSON")
}

/// The MetaImage volume `<name>.mhd` + `<name>.raw` that input stage `stage` produced.
pub(crate) fn read_volume<T: crate::formats::mhd::MetaElement>(
    ctx: &crate::engine::Context,
    stage: &str,
    name: &str,
) -> anyhow::Result<crate::volume::Volume<T>> {
    use anyhow::Context as _;
    let header = String::from_utf8(ctx.read(stage, &format!("{name}.mhd"))?)
        .with_context(|| format!("{stage}/{name}.mhd is not text"))?;
    Ok(crate::formats::mhd::decode(&header, &ctx.read(stage, &format!("{name}.raw"))?)?)
}
