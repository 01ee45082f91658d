//! The one place the stage graph is declared: which stages a configuration runs, in order, each
//! with its own typed parameters.

use crate::config::{Config, DatasetKind};
use crate::engine::{Stage, StageGraph, SOURCE};
use crate::stage::{blobs, drr, grid, hu, ingest, metrics, phantom, select, sweep, train};

/// The per-patient and cohort stages, configured from `config`.
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
    // The blob search's responses are a stage of their own, so that an edit of how select
    // chooses among the blobs reuses them.
    if config.select.localize == select::Localize::Blob {
        stages.push(Box::new(blobs::Blobs { params: config.select.blob.search() }));
    }
    stages.push(Box::new(select::Select { params: config.select.clone() }));
    stages.push(Box::new(metrics::Metrics { params: config.metrics.clone() }));
    StageGraph::new(stages)
}
