//! `summary.json`: the cohort statistics for `all`, `ge10mm` and each size class.
//!
//! Localization comes first: hit rates (guided, blind, oracle) and median Dice. Every APE
//! statistic is given over all scored patients and again over hits only, so no volume error
//! appears without the hit rate it stands on.

use super::rows::{Measured, PatientRow, SizeClass};
use super::Params;
use crate::kernels::stats;
use serde::Serialize;
use std::collections::BTreeMap;

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// Patients scored (with a ground-truth target and a finished select stage).
    pub scored: usize,
    /// Patients that failed before the metrics: reported, excluded, counted.
    pub failed: Vec<String>,
    /// Patients without a ground-truth target (nothing to score).
    pub unscored: Vec<String>,
    pub groups: BTreeMap<&'static str, Group>,
    /// SPEC §5: what the paper reports (its data; guided selection).
    pub paper: Paper,
}

/// One subset of patients.
#[derive(Debug, Clone, Serialize)]
pub struct Group {
    pub n: usize,
    pub localization: Localization,
    /// The primary (guided by default) selection's volumes.
    pub ours: Volumes,
    /// The configured blind rule's volumes.
    pub blind: Volumes,
    /// The sphere baseline V = π/6·d³ from the annotated diameter (no localization).
    pub sphere: Ape,
}

#[derive(Debug, Clone, Serialize)]
pub struct Localization {
    pub hit_rate_ours: Option<f64>,
    pub hit_rate_blind: Option<f64>,
    pub hit_rate_oracle: Option<f64>,
    pub median_dice_ours: Option<f64>,
    pub median_dice_blind: Option<f64>,
}

/// A selection's volume errors over all patients and over its hits only.
#[derive(Debug, Clone, Serialize)]
pub struct Volumes {
    pub hits: usize,
    pub all: Ape,
    pub over_hits: Ape,
}

/// Absolute percentage errors of a set of patients.
#[derive(Debug, Clone, Serialize)]
pub struct Ape {
    pub n: usize,
    pub mean_pct: Option<f64>,
    pub median_pct: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Paper {
    pub ge10mm_n: usize,
    pub ge10mm_median_ape_pct: f64,
    pub ge10mm_mean_ape_pct: f64,
    pub ge10mm_pearson_r: f64,
    pub ge10mm_spearman_rho: f64,
    pub all_median_ape_pct: f64,
    pub all_mean_ape_pct: f64,
    pub all_bland_altman_bias_mm3: f64,
    pub blind_ge10mm_median_ape_pct: [f64; 2],
}

pub const PAPER: Paper = Paper {
    ge10mm_n: 14,
    ge10mm_median_ape_pct: 11.4,
    ge10mm_mean_ape_pct: 18.3,
    ge10mm_pearson_r: 0.983,
    ge10mm_spearman_rho: 0.943,
    all_median_ape_pct: 19.9,
    all_mean_ape_pct: 42.3,
    all_bland_altman_bias_mm3: -77.3,
    blind_ge10mm_median_ape_pct: [24.0, 28.0],
};

/// A named subset of the cohort.
type Subset = (&'static str, fn(&PatientRow) -> bool);

/// The summary of `rows`.
pub fn summarize(rows: &[PatientRow], failed: &[String], unscored: &[String], _params: &Params) -> Summary {
    let subsets: [Subset; 5] = [
        ("all", |_| true),
        ("ge10mm", |r| r.gt_diameter_mm >= 10.0),
        ("small", |r| r.size_class == SizeClass::Small),
        ("medium", |r| r.size_class == SizeClass::Medium),
        ("large", |r| r.size_class == SizeClass::Large),
    ];
    let groups = subsets
        .into_iter()
        .map(|(name, keep)| {
            let members: Vec<&PatientRow> = rows.iter().filter(|r| keep(r)).collect();
            (name, group(&members))
        })
        .collect();
    Summary { scored: rows.len(), failed: failed.to_vec(), unscored: unscored.to_vec(), groups, paper: PAPER }
}

fn ours(r: &PatientRow) -> Option<&Measured> {
    r.ours.as_ref()
}

fn blind(r: &PatientRow) -> Option<&Measured> {
    r.blind.as_ref()
}

fn group(rows: &[&PatientRow]) -> Group {
    let n = rows.len();
    let rate = |count: usize| (n > 0).then(|| count as f64 / n as f64);
    let hits =
        |pick: fn(&PatientRow) -> Option<&Measured>| rows.iter().filter(|r| pick(r).is_some_and(|m| m.hit)).count();
    let median_dice = |pick: fn(&PatientRow) -> Option<&Measured>| {
        // A patient without a selection has Dice 0: nothing overlaps.
        median(&rows.iter().map(|r| pick(r).map_or(0.0, |m| m.dice)).collect::<Vec<_>>())
    };
    Group {
        n,
        localization: Localization {
            hit_rate_ours: rate(hits(ours)),
            hit_rate_blind: rate(hits(blind)),
            hit_rate_oracle: rate(rows.iter().filter(|r| r.oracle_hit).count()),
            median_dice_ours: median_dice(ours),
            median_dice_blind: median_dice(blind),
        },
        ours: volumes(rows, ours),
        blind: volumes(rows, blind),
        sphere: ape(&rows.iter().map(|r| r.sphere_ape_pct).collect::<Vec<_>>()),
    }
}

fn volumes(rows: &[&PatientRow], pick: fn(&PatientRow) -> Option<&Measured>) -> Volumes {
    let chosen: Vec<&Measured> = rows.iter().filter_map(|r| pick(r)).collect();
    let all: Vec<f64> = chosen.iter().map(|m| m.ape_pct).collect();
    let over_hits: Vec<f64> = chosen.iter().filter(|m| m.hit).map(|m| m.ape_pct).collect();
    Volumes { hits: over_hits.len(), all: ape(&all), over_hits: ape(&over_hits) }
}

fn ape(values: &[f64]) -> Ape {
    let mean = (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64);
    Ape { n: values.len(), mean_pct: mean, median_pct: median(values) }
}

fn median(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| stats::median(values))
}
