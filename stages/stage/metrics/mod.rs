//! `metrics` (cohort): every patient's volume and localization against the consensus, and the
//! cohort statistics (SPEC §3 metrics).
//!
//! Inputs, per patient: `select/result.json`, `train/train_log.csv` and the target's texture
//! rating from `ingest/ground_truth.json` (for the solid / subsolid groups) and its site from
//! `ingest/target_site.json` (enclosed by the lung or attached to its wall). Patients without a
//! ground-truth target are listed but not scored; patients that failed upstream are reported,
//! excluded and counted. Outputs: `results.csv` (SPEC §4 columns, in order) and `summary.json`
//! (see [`summary`]), and `report.html` with `scatter.svg` and `bland_altman.svg` (see
//! [`report`]).

use crate::artifacts::{
    Artifact, BLAND_ALTMAN_PLOT, DRR_CORONAL_PREVIEW, GROUND_TRUTH, MODEL, NODULE_PREVIEW, REPORT, RESULT, RESULTS_CSV,
    SCATTER_PLOT, SUMMARY, TARGET_SITE,
};
use crate::engine::{Context, Output, Stage};
use crate::formats::model;
use crate::stage::ingest::site::TargetSite;
use crate::stage::ingest::truth::GroundTruth;
use crate::stage::select::SelectResult;
use anyhow::Context as _;
use serde::{Deserialize, Serialize};

pub mod report;
pub mod rows;
pub mod summary;

pub use rows::{PatientRow, Site, SizeClass};

/// 10: the solid nodules' groups by site (`ingest/target_site.json`); 11: the diameter bands
/// at and above 10 mm.
pub const VERSION: u32 = 12;

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

/// What the cohort reads of each patient.
const READ: [Artifact; 6] = [GROUND_TRUTH, TARGET_SITE, RESULT, NODULE_PREVIEW, MODEL, DRR_CORONAL_PREVIEW];

impl Stage for Metrics {
    fn name(&self) -> &'static str {
        "metrics"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["ingest", "drr", "train", "select"]
    }
    fn is_cohort(&self) -> bool {
        true
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        READ.iter().any(|a| (a.stage, a.file) == (stage, output))
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let mut rows = Vec::new();
        let mut thumbs = Vec::new();
        let mut unscored = Vec::new();
        let mut info = report::RunInfo { lines: Vec::new(), primary: String::new(), blind: String::new() };
        for patient in ctx.cohort_patients() {
            let read = |a: Artifact| ctx.read_patient(patient, a.stage, a.file);
            let json = |a: Artifact| -> anyhow::Result<serde_json::Value> {
                serde_json::from_slice(&read(a)?).with_context(|| format!("{patient}: {}/{}", a.stage, a.file))
            };
            let result: SelectResult = serde_json::from_value(json(RESULT)?)?;
            let truth: GroundTruth = serde_json::from_value(json(GROUND_TRUTH)?)?;
            let texture_mean = truth.target.and_then(|t| truth.nodules.get(t)).map(|n| n.texture_mean);
            let site: TargetSite = serde_json::from_value(json(TARGET_SITE)?)?;
            if info.lines.is_empty() {
                (info.primary, info.blind) = (result.primary.name().into(), result.blind_rule.name().into());
                let (_, _, meta) = model::decode(&ctx.read_patient_replica(patient, 0, MODEL.stage, MODEL.file)?)?;
                info.lines = vec![
                    (
                        "field".into(),
                        format!("{}³ lattice, rank {} per pair, {} parameters", meta.grid, meta.rank, meta.parameters),
                    ),
                    (
                        "training".into(),
                        format!(
                            "{} iterations, Δ = {}, s = {}, seed {}, backend {}",
                            meta.iterations, meta.shift, meta.scale, meta.seed, meta.backend
                        ),
                    ),
                    ("scene box (units)".into(), format!("{:?} – {:?}", meta.aabb.min, meta.aabb.max)),
                    (
                        "selection".into(),
                        format!("primary {}, blind {}", result.primary.name(), result.blind_rule.name()),
                    ),
                    (
                        "bootstrap".into(),
                        format!("{} resamples, seed {}", self.params.bootstrap_resamples, self.params.seed),
                    ),
                ];
            }
            if result.tiles.len() > 1 && info.lines.iter().all(|(k, _)| k != "tiling") {
                info.lines.push((
                    "tiling".into(),
                    format!("{} boxes a patient, ranked by response × depth", result.tiles.len()),
                ));
            }
            match PatientRow::new(&result, texture_mean, site.attached.map(Site::of)) {
                Some(row) => {
                    rows.push(row);
                    thumbs.push(report::Thumbnails {
                        drr_coronal: ctx
                            .read_patient_replica(
                                patient,
                                shown_box(&result),
                                DRR_CORONAL_PREVIEW.stage,
                                DRR_CORONAL_PREVIEW.file,
                            )
                            .ok(),
                        nodule: read(NODULE_PREVIEW).ok(),
                    });
                }
                None => unscored.push(patient.to_string()),
            }
        }
        let summary = summary::summarize(&rows, ctx.failed_patients(), &unscored, &self.params);
        let scatter = report::scatter_svg(&rows);
        let bland_altman = report::bland_altman_svg(&rows, &summary.groups["all"].ours.all);
        let html = report::html(&summary, &rows, &thumbs, &scatter, &bland_altman, &info);
        Ok(vec![
            Output::new(RESULTS_CSV.file, rows::results_csv(&rows)),
            Output::new(SUMMARY.file, serde_json::to_vec_pretty(&summary)?),
            Output::new(SCATTER_PLOT.file, scatter),
            Output::new(BLAND_ALTMAN_PLOT.file, bland_altman),
            Output::new(REPORT.file, html),
        ])
    }
}

/// The box a tiled patient's primary selection was found in (its preview's DRR); 0 otherwise.
fn shown_box(result: &SelectResult) -> usize {
    let tile = result.selection(result.primary).and_then(|s| s.tile.as_deref());
    tile.and_then(|t| result.tiles.iter().position(|b| b.tile == t)).unwrap_or(0)
}
