//! `report.html` with `scatter.svg` and `bland_altman.svg`: one self-contained page (SVGs and
//! thumbnails inline, no network) a reader can open from the out folder.
//!
//! Localization leads: every table that shows an APE shows the hit rate beside it, and a miss
//! is marked in red in the per-patient table, with its `nodule.png` (selection in red, truth in
//! green) as the thumbnail.

use super::rows::{PatientRow, SizeClass};
use super::summary::{Agreement, Group, Summary, Unambiguous, PAPER};
use crate::formats::svg::{scatter_plot, PointSet, RefLine};
use base64::Engine as _;
use std::fmt::Write as _;

/// Per-patient images shown in the table (PNG bytes).
pub struct Thumbnails {
    pub drr_coronal: Option<Vec<u8>>,
    pub nodule: Option<Vec<u8>>,
}

/// What the run was configured with, shown at the end of the page, and the names of its
/// primary and blind rules (`[select] primary`, `blind`).
pub struct RunInfo {
    pub lines: Vec<(String, String)>,
    pub primary: String,
    pub blind: String,
}

const CLASS_COLOURS: [(SizeClass, &str); 3] =
    [(SizeClass::Small, "#2ca02c"), (SizeClass::Medium, "#1f77b4"), (SizeClass::Large, "#d62728")];

/// Predicted against consensus volume, coloured by size class, misses hollow, identity line.
pub fn scatter_svg(rows: &[PatientRow]) -> String {
    let mut sets = Vec::new();
    for (class, colour) in CLASS_COLOURS {
        for hit in [true, false] {
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.size_class == class)
                .filter_map(|r| r.ours.as_ref().filter(|m| m.hit == hit).map(|m| (r.gt_volume_mm3, m.volume_mm3)))
                .collect();
            if !points.is_empty() {
                let name = match (class, hit) {
                    (SizeClass::Small, true) => "small (< 10 mm), hit",
                    (SizeClass::Small, false) => "small, MISS",
                    (SizeClass::Medium, true) => "medium (10–20 mm), hit",
                    (SizeClass::Medium, false) => "medium, MISS",
                    (SizeClass::Large, true) => "large (> 20 mm), hit",
                    (SizeClass::Large, false) => "large, MISS",
                };
                sets.push(PointSet { name, colour, hollow: !hit, points });
            }
        }
    }
    let top = rows
        .iter()
        .flat_map(|r| [Some(r.gt_volume_mm3), r.ours.as_ref().map(|m| m.volume_mm3)])
        .flatten()
        .fold(1.0, f64::max);
    let identity = RefLine { label: "identity", colour: "#555", dashed: true, from: (0.0, 0.0), to: (top, top) };
    scatter_plot(
        "Predicted vs consensus volume",
        "consensus volume (mm³)",
        "predicted volume (mm³)",
        &sets,
        &[identity],
    )
}

/// Bland–Altman: the mean of predicted and consensus against their difference, with the bias
/// and 95% limits of agreement.
pub fn bland_altman_svg(rows: &[PatientRow], all: &Agreement) -> String {
    let points = |hit: bool| -> Vec<(f64, f64)> {
        rows.iter()
            .filter_map(|r| {
                r.ours
                    .as_ref()
                    .filter(|m| m.hit == hit)
                    .map(|m| ((m.volume_mm3 + r.gt_volume_mm3) / 2.0, m.volume_mm3 - r.gt_volume_mm3))
            })
            .collect()
    };
    let sets = [
        PointSet { name: "hit", colour: "#1f77b4", hollow: false, points: points(true) },
        PointSet { name: "MISS", colour: "#d62728", hollow: true, points: points(false) },
    ];
    let xs: Vec<f64> = sets.iter().flat_map(|s| s.points.iter().map(|p| p.0)).collect();
    let (lo, hi) = xs.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
    let (lo, hi) = if lo.is_finite() { (lo, hi) } else { (0.0, 1.0) };
    let mut lines = Vec::new();
    if let Some(ba) = all.bland_altman.value() {
        lines.push(RefLine { label: "bias", colour: "#000", dashed: false, from: (lo, ba.bias), to: (hi, ba.bias) });
        for (label, y) in [("+1.96 SD", ba.loa[1]), ("−1.96 SD", ba.loa[0])] {
            lines.push(RefLine { label, colour: "#888", dashed: true, from: (lo, y), to: (hi, y) });
        }
    }
    scatter_plot(
        "Bland–Altman (all scored patients)",
        "mean of predicted and consensus (mm³)",
        "predicted − consensus (mm³)",
        &sets,
        &lines,
    )
}

/// The whole page.
pub fn html(
    summary: &Summary,
    rows: &[PatientRow],
    thumbs: &[Thumbnails],
    scatter: &str,
    bland_altman: &str,
    info: &RunInfo,
) -> String {
    let mut h = String::from(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>aret-pipe cohort report</title>\n<style>\
         body{font-family:sans-serif;margin:24px;max-width:1280px;color:#222}\
         table{border-collapse:collapse;margin:12px 0;display:block;overflow-x:auto;max-width:100%}\
         td,th{border:1px solid #ccc;padding:3px 7px;text-align:right;white-space:nowrap}th{background:#f3f3f3}\
         td.l,th.l{text-align:left}.ci{color:#777;font-size:85%}.miss{color:#c00;font-weight:bold}.hit{color:#080}\
         .note{color:#555;font-size:90%}.weak{color:#999}img{image-rendering:pixelated}\
         .plots{display:flex;gap:16px;flex-wrap:wrap}</style></head><body>\n<h1>aret-pipe cohort report</h1>\n",
    );
    let _ = writeln!(
        h,
        "<p>{} patients scored, {} failed upstream{}, {} without ground truth{}. A volume is only as good as its \
         localization: every APE below stands beside the hit rate of the selections it comes from, and APE over hits \
         counts only selections that touch the nodule.</p>",
        summary.scored,
        summary.failed.len(),
        list(&summary.failed),
        summary.unscored.len(),
        list(&summary.unscored)
    );
    let groups: Vec<(&&str, &Group)> = summary.groups.iter().filter(|(_, g)| g.n > 0).collect();
    h.push_str("<h2>Cohort</h2>\n<table><tr><th class=l>group</th><th>n</th><th>hit rate (ours)</th><th>blind</th><th>oracle</th><th>centre on the nodule<br>(guided / blind)</th><th>median Dice</th><th>median APE over hits<br>(95% CI)</th><th>median APE, all<br>(95% CI)</th></tr>\n");
    for (name, g) in &groups {
        cohort_row(&mut h, name, g);
    }
    h.push_str("</table>\n<h2>Agreement by group</h2>\n<table><tr><th class=l>group</th><th>mean APE, all</th><th>Pearson r</th><th>Spearman ρ</th><th>Bland–Altman bias (mm³)</th><th>sphere median APE</th><th>Wilcoxon vs sphere<br>(W, p)</th><th>one reader's median APE (n)</th><th>hits of those not ambiguous<br>(ours / blind)</th></tr>\n");
    for (name, g) in &groups {
        agreement_row(&mut h, name, g);
    }
    h.push_str(
        "</table>\n<p class=note>Intervals are 95% bootstrap intervals. One reader's median APE: each patient's \
         readers' own volumes against their consensus (the median over the readers), over the patients two or more \
         radiologists read. The ground truth carries that spread; a method within it measures as well as one \
         radiologist does.</p>\n",
    );
    let _ = writeln!(
        h,
        "<h2>The paper's numbers beside ours</h2>\n<p class=note>The paper's numbers come from its 19 real LIDC CTs with guided selection (SPEC §5); it reports no localization. Ours are given over every selection and over the hits alone, beside the hit rate they come from: an error over selections that miss the nodule measures something else, and is greyed.</p>\n<table><tr><th class=l>statistic</th><th>paper</th><th>ours, every selection</th><th>ours, over hits</th><th>hit rate</th></tr>\n{}</table>",
        paper_rows(summary)
    );
    h.push_str("<h2>The primary rule beside the blind one</h2>\n<table><tr><th class=l>group</th><th>rule</th><th>hit rate</th><th>median Dice</th><th>median APE, all</th><th>median APE over hits</th></tr>\n");
    for (name, g) in &groups {
        for (rule, hit_rate, dice, v) in [
            (info.primary.as_str(), g.localization.hit_rate_ours, g.localization.median_dice_ours, &g.ours),
            (info.blind.as_str(), g.localization.hit_rate_blind, g.localization.median_dice_blind, &g.blind),
        ] {
            let _ = writeln!(
                h,
                "<tr><td class=l>{name}</td><td class=l>{rule}</td><td>{}</td><td>{}</td><td>{}</td><td>{} ({} hits)</td></tr>",
                pct(hit_rate),
                num(dice, 2),
                estimate(&v.all.median_ape_pct),
                estimate(&v.over_hits.median_ape_pct),
                v.hits
            );
        }
    }
    h.push_str("</table>\n<h2>Agreement</h2>\n<div class=plots>\n");
    h.push_str(scatter);
    h.push_str(bland_altman);
    h.push_str("</div>\n<h2>Patients</h2>\n<table><tr><th class=l>patient</th><th>class</th><th>GT (mm³)</th><th>d (mm)</th><th>predicted</th><th>APE</th><th>localization</th><th>Dice</th><th>centroid (mm)</th><th>percentile</th><th>blind</th><th>blind APE</th><th>blind hit</th><th>sphere APE</th><th>oracle</th><th>DRR</th><th>nodule.png</th></tr>\n");
    for (r, t) in rows.iter().zip(thumbs) {
        patient_row(&mut h, r, t);
    }
    h.push_str("</table>\n<h2>Configuration</h2>\n<table>\n");
    for (k, v) in &info.lines {
        let _ = writeln!(h, "<tr><td class=l>{}</td><td class=l>{}</td></tr>", escape(k), escape(v));
    }
    h.push_str("</table>\n</body></html>\n");
    h
}

fn cohort_row(h: &mut String, name: &str, g: &Group) {
    let loc = &g.localization;
    let _ = writeln!(
        h,
        "<tr><td class=l>{name}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{} / {}</td><td>{}</td><td>{} ({} hits)</td><td>{}</td></tr>",
        g.n,
        pct(loc.hit_rate_ours),
        pct(loc.hit_rate_blind),
        pct(loc.hit_rate_oracle),
        pct(loc.centre_rate_guided),
        pct(loc.centre_rate_blind),
        num(loc.median_dice_ours, 2),
        estimate(&g.ours.over_hits.median_ape_pct),
        g.ours.hits,
        estimate(&g.ours.all.median_ape_pct),
    );
}

fn agreement_row(h: &mut String, name: &str, g: &Group) {
    let all = &g.ours.all;
    let corr = |c: &super::summary::Stat<super::summary::CorrelationEstimate>| match c.value() {
        Some(c) => format!("{:.3} <span class=ci>[{:.3}, {:.3}]</span>", c.value, c.ci95[0], c.ci95[1]),
        None => "–".into(),
    };
    let bias = all.bland_altman.value().map_or("–".into(), |b| {
        format!("{:.0} <span class=ci>[{:.0}, {:.0}]</span>", b.bias, b.bias_ci[0], b.bias_ci[1])
    });
    let _ = writeln!(
        h,
        "<tr><td class=l>{name}</td><td>{}</td><td>{}</td><td>{}</td><td>{bias}</td><td>{}</td><td>{}</td><td>{} ({})</td><td>{} / {}</td></tr>",
        estimate(&all.mean_ape_pct),
        corr(&all.pearson),
        corr(&all.spearman),
        estimate(&g.sphere.median_pct),
        all.wilcoxon_vs_sphere.value().map_or("–".into(), |w| format!("{:.0}, {}", w.w, p_value(w.p_two_sided))),
        estimate(&g.readers.median_pct),
        g.readers.n,
        unambiguous(g.localization.unambiguous_ours),
        unambiguous(g.localization.unambiguous_blind),
    );
}

/// A p-value to three decimals for an HTML cell; below 0.001 as "< 0.001", never as 0.000.
fn p_value(p: f64) -> String {
    if p < 0.001 {
        "&lt; 0.001".into()
    } else {
        format!("{p:.3}")
    }
}

fn paper_rows(summary: &Summary) -> String {
    let (ge, all) = (&summary.groups["ge10mm"], &summary.groups["all"]);
    type Pick = fn(&Agreement) -> Option<f64>;
    let median: Pick = |a| a.median_ape_pct.value().map(|e| e.value);
    let mean: Pick = |a| a.mean_ape_pct.value().map(|e| e.value);
    // (statistic, the paper's value, the group, ours over every selection and over hits, digits)
    type PaperRow<'a> = (&'a str, f64, &'a Group, Option<f64>, Option<f64>, usize);
    let rows: [PaperRow; 8] = [
        ("≥10 mm: n", PAPER.ge10mm_n as f64, ge, Some(ge.n as f64), None, 0),
        ("≥10 mm: median APE %", PAPER.ge10mm_median_ape_pct, ge, median(&ge.ours.all), median(&ge.ours.over_hits), 1),
        ("≥10 mm: mean APE %", PAPER.ge10mm_mean_ape_pct, ge, mean(&ge.ours.all), mean(&ge.ours.over_hits), 1),
        ("≥10 mm: Pearson r", PAPER.ge10mm_pearson_r, ge, ge.ours.all.pearson.value().map(|c| c.value), None, 3),
        ("≥10 mm: Spearman ρ", PAPER.ge10mm_spearman_rho, ge, ge.ours.all.spearman.value().map(|c| c.value), None, 3),
        ("all: median APE %", PAPER.all_median_ape_pct, all, median(&all.ours.all), median(&all.ours.over_hits), 1),
        ("all: mean APE %", PAPER.all_mean_ape_pct, all, mean(&all.ours.all), mean(&all.ours.over_hits), 1),
        (
            "all: Bland–Altman bias mm³",
            PAPER.all_bland_altman_bias_mm3,
            all,
            all.ours.all.bland_altman.value().map(|b| b.bias),
            None,
            1,
        ),
    ];
    rows.iter()
        .map(|(k, paper, g, every, hits, digits)| {
            let rate = g.localization.hit_rate_ours;
            // An error over selections that mostly miss measures other things: greyed.
            let weak = if rate.is_some_and(|r| r < 0.5) { " class=weak" } else { "" };
            format!(
                "<tr><td class=l>{k}</td><td>{paper}</td><td{weak}>{}</td><td>{}</td><td>{}</td></tr>\n",
                num(*every, *digits),
                num(*hits, *digits),
                pct(rate)
            )
        })
        .collect()
}

fn patient_row(h: &mut String, r: &PatientRow, t: &Thumbnails) {
    let o = r.ours.as_ref();
    let loc = match o {
        Some(m) if m.hit => "<span class=hit>hit</span>".to_string(),
        Some(_) => "<span class=miss>MISS</span>".to_string(),
        None => "<span class=miss>no candidate</span>".to_string(),
    };
    let b = r.blind.as_ref();
    // Each thumbnail links to its full-size file in the patient's folder beside this page.
    let img = |png: &Option<Vec<u8>>, height: u32, file: &str| {
        png.as_ref().map_or(String::new(), |bytes| {
            format!(
                "<a href=\"{}/{file}\"><img height={height} alt=\"{file}\" src=\"data:image/png;base64,{}\"></a>",
                escape(&r.patient),
                base64::engine::general_purpose::STANDARD.encode(bytes)
            )
        })
    };
    let _ = writeln!(
        h,
        "<tr><td class=l>{}</td><td>{}</td><td>{:.0}</td><td>{:.1}</td><td>{}</td><td>{}</td><td>{loc}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.1}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
        escape(&r.patient),
        [Some(r.size_class.name()), r.texture.map(|t| t.name()), r.site.map(|s| s.name())]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join(", "),
        r.gt_volume_mm3,
        r.gt_diameter_mm,
        num(o.map(|m| m.volume_mm3), 0),
        num(o.map(|m| m.ape_pct), 1),
        num(o.map(|m| m.dice), 2),
        num(o.map(|m| m.centroid_dist_mm), 1),
        num(r.percentile, 0),
        num(b.map(|m| m.volume_mm3), 0),
        num(b.map(|m| m.ape_pct), 1),
        b.map_or("–", |m| if m.hit { "hit" } else { "MISS" }),
        r.sphere_ape_pct,
        if r.oracle_hit { "yes" } else { "no" },
        img(&t.drr_coronal, 120, "drr_coronal.png"),
        img(&t.nodule, 160, "nodule.png"),
    );
}

fn estimate(e: &super::summary::Stat<super::summary::Estimate>) -> String {
    match e.value() {
        Some(e) => format!("{:.1}% <span class=ci>[{:.1}, {:.1}]</span>", e.value, e.ci95[0], e.ci95[1]),
        None => "–".into(),
    }
}

fn pct(v: Option<f64>) -> String {
    v.map_or("–".into(), |x| format!("{:.0}%", 100.0 * x))
}

/// "hits of n", or – without blob centres.
fn unambiguous(u: Option<Unambiguous>) -> String {
    u.map_or("–".into(), |u| format!("{} of {}", u.hits, u.n))
}

fn num(v: Option<f64>, digits: usize) -> String {
    v.filter(|x| x.is_finite()).map_or("–".into(), |x| format!("{x:.digits$}"))
}

fn list(names: &[String]) -> String {
    if names.is_empty() {
        String::new()
    } else {
        format!(" ({})", escape(&names.join(", ")))
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    #[test]
    fn small_p_values_read_as_below_a_thousandth_not_as_zero() {
        assert_eq!(super::p_value(0.00048828125), "&lt; 0.001");
        assert_eq!(super::p_value(0.044769287109375), "0.045");
        assert_eq!(super::p_value(1.0), "1.000");
    }
}
