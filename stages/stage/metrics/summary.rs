//! `summary.json`: the cohort statistics for `all`, `ge10mm`, each size class, the diameter bands
//! at and above 10 mm, each texture and each site.
//!
//! Localization comes first: hit rates (guided, blind, oracle) and median Dice. Every APE
//! statistic is given over all scored patients and again over hits only, so no volume error
//! appears without the hit rate it stands on.

use super::rows::{CentreOnNodule, Measured, PatientRow, Site, SizeClass, Texture};
use super::Params;
use crate::kernels::statistics::{self, BlandAltman, StatisticsError, Wilcoxon};
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
    pub localization: HitRates,
    /// The primary (guided by default) selection's volumes.
    pub ours: Volumes,
    /// The configured blind rule's volumes.
    pub blind: Volumes,
    /// The sphere baseline V = π/6·d³ from the annotated diameter (no localization).
    pub sphere: Ape,
    /// A single radiologist: each patient's median reader APE against the consensus, over the
    /// patients with two readers or more. The spread the ground truth itself carries.
    pub readers: Ape,
}

#[derive(Debug, Clone, Serialize)]
pub struct HitRates {
    pub hit_rate_ours: Option<f64>,
    pub hit_rate_blind: Option<f64>,
    pub hit_rate_oracle: Option<f64>,
    pub median_dice_ours: Option<f64>,
    pub median_dice_blind: Option<f64>,
    /// The fraction of patients whose guided rule's centre lies on the nodule (`None` when no
    /// patient's rule had a centre: `localize = "none"`), and the same for the blind rule.
    pub centre_rate_guided: Option<f64>,
    pub centre_rate_blind: Option<f64>,
    /// The primary and the blind rule's selections whose blob centre had no close rival
    /// (select's `ambiguous`, `[select.blob] rival_ratio`), and how many of those hit: how far a
    /// user may trust a volume the tool does not flag. `None` without blob centres.
    pub unambiguous_ours: Option<Unambiguous>,
    pub unambiguous_blind: Option<Unambiguous>,
}

/// Selections not flagged ambiguous, and their hits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Unambiguous {
    pub n: usize,
    pub hits: usize,
}

/// A selection's volume errors over all patients and over its hits only.
#[derive(Debug, Clone, Serialize)]
pub struct Volumes {
    pub hits: usize,
    pub all: Agreement,
    pub over_hits: Agreement,
}

/// How a set of predicted volumes agrees with the consensus volumes.
#[derive(Debug, Clone, Serialize)]
pub struct Agreement {
    pub n: usize,
    pub mean_ape_pct: Stat<Estimate>,
    pub median_ape_pct: Stat<Estimate>,
    /// Predicted vs consensus volume.
    pub pearson: Stat<CorrelationEstimate>,
    pub spearman: Stat<CorrelationEstimate>,
    /// Predicted − consensus (mm³).
    pub bland_altman: Stat<BlandAltman>,
    /// Our APE against the sphere baseline's APE on the same patients (paired).
    pub wilcoxon_vs_sphere: Stat<Wilcoxon>,
}

/// A value, or why it is undefined here (e.g. "needs at least 3 values").
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum Stat<T> {
    Value(T),
    Undefined { undefined: String },
}

impl<T> Stat<T> {
    fn from(result: Result<T, StatisticsError>) -> Stat<T> {
        match result {
            Ok(v) => Stat::Value(v),
            Err(e) => Stat::Undefined { undefined: e.to_string() },
        }
    }

    pub fn value(&self) -> Option<&T> {
        match self {
            Stat::Value(v) => Some(v),
            Stat::Undefined { .. } => None,
        }
    }
}

/// A statistic with its bootstrap confidence interval.
#[derive(Debug, Clone, Serialize)]
pub struct Estimate {
    pub value: f64,
    pub ci95: [f64; 2],
}

#[derive(Debug, Clone, Serialize)]
pub struct CorrelationEstimate {
    pub value: f64,
    pub p_two_sided: f64,
    pub ci95: [f64; 2],
}

/// Absolute percentage errors of a set of patients (the sphere baseline).
#[derive(Debug, Clone, Serialize)]
pub struct Ape {
    pub n: usize,
    pub mean_pct: Stat<Estimate>,
    pub median_pct: Stat<Estimate>,
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

const CONFIDENCE: f64 = 0.95;

/// The summary of `rows`.
pub fn summarize(rows: &[PatientRow], failed: &[String], unscored: &[String], params: &Params) -> Summary {
    let subsets: [Subset; 16] = [
        ("all", |_| true),
        ("ge10mm", ge10mm),
        ("small", |r| r.size_class == SizeClass::Small),
        ("medium", |r| r.size_class == SizeClass::Medium),
        ("large", |r| r.size_class == SizeClass::Large),
        // The bands a nodule's targets are stated in (the size classes split at 20 mm the other way).
        ("ge10mm_lt15mm", |r| (10.0..15.0).contains(&r.gt_diameter_mm)),
        ("ge15mm_lt20mm", |r| (15.0..20.0).contains(&r.gt_diameter_mm)),
        ("ge20mm", |r| r.gt_diameter_mm >= 20.0),
        // By texture (beside the SPEC's groups): how much of a miss rate is the subsolid
        // nodules', which stand barely above the lung.
        ("solid", solid),
        ("subsolid", subsolid),
        ("ge10mm_solid", |r| ge10mm(r) && solid(r)),
        ("ge10mm_subsolid", |r| ge10mm(r) && subsolid(r)),
        // By site among the solid ones: enclosed by the lung, or fused with its wall.
        ("solid_enclosed", |r| solid(r) && enclosed(r)),
        ("solid_attached", |r| solid(r) && attached(r)),
        ("ge10mm_solid_enclosed", |r| ge10mm(r) && solid(r) && enclosed(r)),
        ("ge10mm_solid_attached", |r| ge10mm(r) && solid(r) && attached(r)),
    ];
    let groups = subsets
        .into_iter()
        .map(|(name, keep)| {
            let members: Vec<&PatientRow> = rows.iter().filter(|r| keep(r)).collect();
            (name, group(&members, params))
        })
        .collect();
    Summary { scored: rows.len(), failed: failed.to_vec(), unscored: unscored.to_vec(), groups, paper: PAPER }
}

fn ge10mm(r: &PatientRow) -> bool {
    r.gt_diameter_mm >= 10.0
}

fn solid(r: &PatientRow) -> bool {
    r.texture == Some(Texture::Solid)
}

fn subsolid(r: &PatientRow) -> bool {
    r.texture == Some(Texture::Subsolid)
}

fn enclosed(r: &PatientRow) -> bool {
    r.site == Some(Site::Enclosed)
}

fn attached(r: &PatientRow) -> bool {
    r.site == Some(Site::Attached)
}

fn ours(r: &PatientRow) -> Option<&Measured> {
    r.ours.as_ref()
}

fn blind(r: &PatientRow) -> Option<&Measured> {
    r.blind.as_ref()
}

fn group(rows: &[&PatientRow], params: &Params) -> Group {
    let n = rows.len();
    let rate = |count: usize| (n > 0).then(|| count as f64 / n as f64);
    let hits =
        |pick: fn(&PatientRow) -> Option<&Measured>| rows.iter().filter(|r| pick(r).is_some_and(|m| m.hit)).count();
    let median_dice = |pick: fn(&PatientRow) -> Option<&Measured>| {
        // A patient without a selection has Dice 0: nothing overlaps.
        let dice: Vec<f64> = rows.iter().map(|r| pick(r).map_or(0.0, |m| m.dice)).collect();
        (!dice.is_empty()).then(|| stats::median(&dice))
    };
    let centre_rate = |pick: fn(&CentreOnNodule) -> Option<bool>| {
        // A patient without a centre counts as not on the nodule, once any patient has one.
        let found: Vec<bool> = rows.iter().filter_map(|r| pick(&r.centre_on_nodule)).collect();
        if found.is_empty() {
            None
        } else {
            rate(found.iter().filter(|&&on| on).count())
        }
    };
    let unambiguous = |pick: fn(&PatientRow) -> Option<&Measured>| {
        let flagged: Vec<(bool, bool)> =
            rows.iter().filter_map(|r| pick(r).and_then(|m| m.ambiguous.map(|a| (a, m.hit)))).collect();
        (!flagged.is_empty()).then(|| Unambiguous {
            n: flagged.iter().filter(|(a, _)| !a).count(),
            hits: flagged.iter().filter(|&&(a, hit)| !a && hit).count(),
        })
    };
    Group {
        n,
        localization: HitRates {
            hit_rate_ours: rate(hits(ours)),
            hit_rate_blind: rate(hits(blind)),
            hit_rate_oracle: rate(rows.iter().filter(|r| r.oracle_hit).count()),
            median_dice_ours: median_dice(ours),
            median_dice_blind: median_dice(blind),
            centre_rate_guided: centre_rate(|c| c.guided),
            centre_rate_blind: centre_rate(|c| c.blind),
            unambiguous_ours: unambiguous(ours),
            unambiguous_blind: unambiguous(blind),
        },
        ours: volumes(rows, ours, params),
        blind: volumes(rows, blind, params),
        sphere: ape(&rows.iter().map(|r| r.sphere_ape_pct).collect::<Vec<f64>>(), params),
        readers: ape(&rows.iter().filter_map(|r| r.reader_ape_pct).collect::<Vec<f64>>(), params),
    }
}

/// The mean and median of `apes` with their intervals.
fn ape(apes: &[f64], params: &Params) -> Ape {
    Ape { n: apes.len(), mean_pct: estimate(apes, mean_of, params), median_pct: estimate(apes, median_of, params) }
}

fn volumes(rows: &[&PatientRow], pick: fn(&PatientRow) -> Option<&Measured>, params: &Params) -> Volumes {
    let chosen: Vec<(&PatientRow, &Measured)> = rows.iter().filter_map(|r| pick(r).map(|m| (*r, m))).collect();
    let over_hits: Vec<(&PatientRow, &Measured)> = chosen.iter().copied().filter(|(_, m)| m.hit).collect();
    Volumes { hits: over_hits.len(), all: agreement(&chosen, params), over_hits: agreement(&over_hits, params) }
}

fn agreement(pairs: &[(&PatientRow, &Measured)], params: &Params) -> Agreement {
    let apes: Vec<f64> = pairs.iter().map(|(_, m)| m.ape_pct).collect();
    let predicted: Vec<f64> = pairs.iter().map(|(_, m)| m.volume_mm3).collect();
    let truth: Vec<f64> = pairs.iter().map(|(r, _)| r.gt_volume_mm3).collect();
    let sphere: Vec<f64> = pairs.iter().map(|(r, _)| r.sphere_ape_pct).collect();
    let correlation = |f: fn(&[f64], &[f64]) -> Result<statistics::Correlation, StatisticsError>| {
        Stat::from(f(&predicted, &truth).and_then(|c| {
            let ci = statistics::bootstrap_ci_paired(
                &predicted,
                &truth,
                |x, y| f(x, y).map_or(f64::NAN, |c| c.r),
                params.bootstrap_resamples,
                CONFIDENCE,
                params.seed,
            )?;
            Ok(CorrelationEstimate { value: c.r, p_two_sided: c.p_two_sided, ci95: [ci.lo, ci.hi] })
        }))
    };
    Agreement {
        n: pairs.len(),
        mean_ape_pct: estimate(&apes, mean_of, params),
        median_ape_pct: estimate(&apes, median_of, params),
        pearson: correlation(statistics::pearson),
        spearman: correlation(statistics::spearman),
        bland_altman: Stat::from(statistics::bland_altman(&predicted, &truth)),
        wilcoxon_vs_sphere: Stat::from(statistics::wilcoxon_signed_rank(&apes, &sphere)),
    }
}

fn mean_of(v: &[f64]) -> f64 {
    statistics::mean(v).unwrap_or(f64::NAN)
}

fn median_of(v: &[f64]) -> f64 {
    statistics::median(v).unwrap_or(f64::NAN)
}

/// `statistic` of `values` with its seeded percentile-bootstrap interval.
fn estimate(values: &[f64], statistic: fn(&[f64]) -> f64, params: &Params) -> Stat<Estimate> {
    Stat::from(statistics::mean(values).and_then(|_| {
        let ci = statistics::bootstrap_ci(values, statistic, params.bootstrap_resamples, CONFIDENCE, params.seed)?;
        Ok(Estimate { value: statistic(values), ci95: [ci.lo, ci.hi] })
    }))
}

/// The lines `aret-pipe run` ends with: per group, n, hit rates, and the median APE, Pearson r
/// and Bland–Altman bias of our selection — the APE always beside its hit rate.
pub fn headline(summary_json: &[u8]) -> anyhow::Result<String> {
    let s: serde_json::Value = serde_json::from_slice(summary_json)?;
    let pct = |v: &serde_json::Value| v.as_f64().map_or("–".to_string(), |x| format!("{:.0}%", 100.0 * x));
    let num = |v: &serde_json::Value, digits: usize| v.as_f64().map_or("–".to_string(), |x| format!("{x:.digits$}"));
    let mut out = format!(
        "cohort: {} scored, {} failed, {} without ground truth\n",
        s["scored"],
        s["failed"].as_array().map_or(0, Vec::len),
        s["unscored"].as_array().map_or(0, Vec::len)
    );
    for name in ["ge10mm", "all"] {
        let g = &s["groups"][name];
        let (loc, all) = (&g["localization"], &g["ours"]["all"]);
        out += &format!(
            "  {name:<6} n={:<3} hit {} (blind {}, oracle {}; centre on the nodule {} / {}; {}) | median APE {} (over {} hits: {}) | Pearson r {} | bias {} mm³\n",
            g["n"],
            pct(&loc["hit_rate_ours"]),
            pct(&loc["hit_rate_blind"]),
            pct(&loc["hit_rate_oracle"]),
            pct(&loc["centre_rate_guided"]),
            pct(&loc["centre_rate_blind"]),
            match (loc["unambiguous_ours"]["hits"].as_u64(), loc["unambiguous_ours"]["n"].as_u64()) {
                (Some(hits), Some(n)) => format!("{hits} hits of {n} not ambiguous"),
                _ => "no blob centres".into(),
            },
            num(&all["median_ape_pct"]["value"], 1) + "%",
            g["ours"]["hits"],
            num(&g["ours"]["over_hits"]["median_ape_pct"]["value"], 1),
            num(&all["pearson"]["value"], 3),
            num(&all["bland_altman"]["bias"], 0),
        );
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(patient: &str, gt: f64, d: f64, predicted: f64, hit: bool) -> PatientRow {
        let m = Measured {
            volume_mm3: predicted,
            ape_pct: super::super::rows::ape_pct(predicted, gt),
            hit,
            dice: if hit { 0.6 } else { 0.0 },
            centroid_dist_mm: 1.0,
            // B's miss and C's hit had a close rival.
            ambiguous: Some(patient != "A"),
        };
        let sphere = std::f64::consts::PI / 6.0 * d.powi(3);
        PatientRow {
            patient: patient.into(),
            size_class: SizeClass::of(d),
            // B, the miss, is ground glass.
            texture: Some(if patient == "B" { Texture::Subsolid } else { Texture::Solid }),
            // C, the small one, lies against the lung's wall.
            site: Some(if patient == "C" { Site::Attached } else { Site::Enclosed }),
            gt_volume_mm3: gt,
            gt_diameter_mm: d,
            ours: Some(m),
            mesh_volume_mm3: None,
            percentile: Some(90.0),
            blind: None,
            sphere_volume_mm3: sphere,
            sphere_ape_pct: super::super::rows::ape_pct(sphere, gt),
            // Two readers at 0.9× and 1.3× the consensus, three at 1.0×, 0.8× and 1.5×: 20 % and 20 %.
            reader_ape_pct: super::super::rows::reader_ape_pct(
                &if hit { vec![0.9 * gt, 1.3 * gt] } else { vec![gt, 0.8 * gt, 1.5 * gt] },
                gt,
            ),
            oracle_hit: hit,
            centre_on_nodule: CentreOnNodule { guided: Some(hit), blind: None },
        }
    }

    #[test]
    fn hits_and_misses_are_counted_and_small_groups_say_why_a_statistic_is_undefined() {
        let params = Params { bootstrap_resamples: 200, seed: 1 };
        let rows = [
            row("A", 1000.0, 14.0, 1100.0, true),
            row("B", 500.0, 12.0, 2000.0, false),
            row("C", 50.0, 5.0, 60.0, true),
        ];
        let s = summarize(&rows, &["F".into()], &[], &params);
        assert_eq!((s.scored, s.failed.len()), (3, 1));
        let all = &s.groups["all"];
        assert_eq!(all.localization.hit_rate_ours, Some(2.0 / 3.0));
        assert_eq!(all.localization.median_dice_ours, Some(0.6));
        // Centres: the guided rule's on the nodule for the two hits; the blind rule found none.
        assert_eq!(all.localization.centre_rate_guided, Some(2.0 / 3.0));
        assert_eq!(all.localization.centre_rate_blind, None);
        // Only A's centre had no close rival, and it hit; the blind rule sized no centre.
        assert_eq!(all.localization.unambiguous_ours, Some(Unambiguous { n: 1, hits: 1 }));
        assert_eq!(all.localization.unambiguous_blind, None);
        assert_eq!(all.ours.hits, 2);
        // Over hits only (A, C): APE 10% and 20%.
        assert_eq!(all.ours.over_hits.median_ape_pct.value().unwrap().value, 15.0);
        // n = 2: no correlation, a clear reason instead.
        let ge10 = &s.groups["ge10mm"];
        assert_eq!(ge10.n, 2);
        assert!(matches!(&ge10.ours.all.pearson, Stat::Undefined { undefined } if undefined.contains('3')));
        // The blind rule chose nothing anywhere: zero hits, Dice 0, statistics undefined.
        assert_eq!(all.localization.hit_rate_blind, Some(0.0));
        assert!(all.blind.all.mean_ape_pct.value().is_none());
        // One radiologist against the consensus: 20 % for every patient here.
        assert_eq!(all.readers.n, 3);
        assert!((all.readers.median_pct.value().unwrap().value - 20.0).abs() < 1e-9);
        // By texture: the two solid nodules hit, the subsolid B missed; ≥ 10 mm splits A from B.
        assert_eq!((s.groups["solid"].n, s.groups["solid"].localization.hit_rate_ours), (2, Some(1.0)));
        assert_eq!((s.groups["subsolid"].n, s.groups["subsolid"].localization.hit_rate_ours), (1, Some(0.0)));
        assert_eq!((s.groups["ge10mm_solid"].n, s.groups["ge10mm_subsolid"].n), (1, 1));
        // By site among the solid: A enclosed, C attached; the subsolid B is in neither.
        assert_eq!((s.groups["solid_enclosed"].n, s.groups["solid_attached"].n), (1, 1));
        assert_eq!((s.groups["ge10mm_solid_enclosed"].n, s.groups["ge10mm_solid_attached"].n), (1, 0));
        // By band: A and B lie in 10–15 mm, one hit of two.
        let band = &s.groups["ge10mm_lt15mm"];
        assert_eq!((band.n, band.localization.hit_rate_ours), (2, Some(0.5)));
        // An empty class is reported, not dropped.
        assert_eq!(s.groups["large"].n, 0);
        assert_eq!(s.groups["large"].localization.hit_rate_ours, None);
    }

    #[test]
    fn each_band_holds_its_lower_edge_and_the_bands_cover_10_mm_and_above_once() {
        let params = Params { bootstrap_resamples: 20, seed: 1 };
        let diameters: [f64; 7] = [9.9, 10.0, 14.9, 15.0, 19.9, 20.0, 31.0];
        let rows: Vec<PatientRow> =
            diameters.iter().map(|&d| row(&format!("{d}"), d.powi(3), d, d.powi(3), true)).collect();
        let s = summarize(&rows, &[], &[], &params);
        let n = |group: &str| s.groups[group].n;
        assert_eq!([n("ge10mm_lt15mm"), n("ge15mm_lt20mm"), n("ge20mm")], [2, 2, 2]);
        assert_eq!(n("ge10mm_lt15mm") + n("ge15mm_lt20mm") + n("ge20mm"), n("ge10mm"));
        // The SPEC's classes split at 20 mm the other way: 20.0 is medium, and ≥ 20 mm.
        assert_eq!((n("medium"), n("large")), (5, 1));
    }
}
