//! Small self-contained SVG line plots (no fonts or scripts needed to view them).

use std::fmt::Write as _;

/// One named series of (x, y) points, drawn in `colour`.
pub struct Series<'a> {
    pub name: &'a str,
    pub colour: &'a str,
    pub points: Vec<(f64, f64)>,
}

/// A line plot with a log-10 y axis (non-positive values are dropped), axes, ticks and a legend.
pub fn log_plot(title: &str, x_label: &str, series: &[Series]) -> String {
    let (w, h, left, right, top, bottom) = (640.0, 400.0, 70.0, 20.0, 40.0, 50.0);
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.iter().copied()).filter(|p| p.1 > 0.0).collect();
    let (x0, x1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (y0, y1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.1), b.max(p.1)));
    let (x0, x1) = if x1 > x0 { (x0, x1) } else { (x0 - 1.0, x0 + 1.0) };
    let (ly0, ly1) = if y1 > y0 { (y0.log10().floor(), y1.log10().ceil()) } else { (-1.0, 1.0) };
    let sx = |x: f64| left + (x - x0) / (x1 - x0) * (w - left - right);
    let sy = |y: f64| top + (ly1 - y.log10()) / (ly1 - ly0) * (h - top - bottom);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    let _ = writeln!(s, r#"<text x="{}" y="22" text-anchor="middle" font-size="15">{title}</text>"#, w / 2.0);
    let _ = writeln!(s, r#"<text x="{}" y="{}" text-anchor="middle">{x_label}</text>"#, w / 2.0, h - 12.0);
    let (px0, px1, py0, py1) = (left, w - right, top, h - bottom);
    let _ = writeln!(s, r#"<path d="M{px0} {py0} V{py1} H{px1}" fill="none" stroke="black"/>"#);
    for e in (ly0 as i32)..=(ly1 as i32) {
        let y = sy(10f64.powi(e));
        let _ = writeln!(
            s,
            r##"<path d="M{px0} {y:.1} H{px1}" stroke="#ddd"/><text x="{}" y="{:.1}" text-anchor="end">1e{e}</text>"##,
            px0 - 6.0,
            y + 4.0
        );
    }
    for k in 0..=4 {
        let x = x0 + (x1 - x0) * k as f64 / 4.0;
        let _ = writeln!(s, r#"<text x="{:.1}" y="{}" text-anchor="middle">{}</text>"#, sx(x), py1 + 16.0, x.round());
    }
    for (k, series) in series.iter().enumerate() {
        let path: Vec<String> = series
            .points
            .iter()
            .filter(|p| p.1 > 0.0)
            .enumerate()
            .map(|(i, &(x, y))| format!("{}{:.1} {:.1}", if i == 0 { "M" } else { "L" }, sx(x), sy(y)))
            .collect();
        let _ =
            writeln!(s, r#"<path d="{}" fill="none" stroke="{}" stroke-width="1.5"/>"#, path.join(" "), series.colour);
        let ly = top + 14.0 + 16.0 * k as f64;
        let _ = writeln!(
            s,
            r#"<path d="M{} {ly} h18" stroke="{}" stroke-width="2"/><text x="{}" y="{}">{}</text>"#,
            px1 - 150.0,
            series.colour,
            px1 - 126.0,
            ly + 4.0,
            series.name
        );
    }
    s.push_str("</svg>\n");
    s
}

/// A set of markers in one colour; `hollow` draws rings (e.g. misses) instead of discs.
pub struct PointSet<'a> {
    pub name: &'a str,
    pub colour: &'a str,
    pub hollow: bool,
    pub points: Vec<(f64, f64)>,
}

/// A straight reference line from `from` to `to` (data coordinates), optionally dashed.
pub struct RefLine<'a> {
    pub label: &'a str,
    pub colour: &'a str,
    pub dashed: bool,
    pub from: (f64, f64),
    pub to: (f64, f64),
}

/// A scatter plot with linear axes, reference lines and a legend.
pub fn scatter_plot(title: &str, x_label: &str, y_label: &str, sets: &[PointSet], lines: &[RefLine]) -> String {
    let (w, h, left, right, top, bottom) = (640.0, 440.0, 80.0, 170.0, 40.0, 50.0);
    let all: Vec<(f64, f64)> = sets
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .chain(lines.iter().flat_map(|l| [l.from, l.to]))
        .filter(|p| p.0.is_finite() && p.1.is_finite())
        .collect();
    let range = |f: fn(&(f64, f64)) -> f64| {
        let (lo, hi) = all.iter().map(f).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
        nice_axis(lo, hi)
    };
    let ((x0, x1, x_step), (y0, y1, y_step)) = (range(|p| p.0), range(|p| p.1));
    let (px0, px1, py0, py1) = (left, w - right, top, h - bottom);
    let sx = |x: f64| px0 + (x - x0) / (x1 - x0) * (px1 - px0);
    let sy = |y: f64| py1 - (y - y0) / (y1 - y0) * (py1 - py0);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    let _ = writeln!(s, r#"<text x="{}" y="22" text-anchor="middle" font-size="15">{title}</text>"#, (px0 + px1) / 2.0);
    let _ = writeln!(s, r#"<text x="{}" y="{}" text-anchor="middle">{x_label}</text>"#, (px0 + px1) / 2.0, h - 12.0);
    let _ = writeln!(
        s,
        r#"<text transform="translate(16 {}) rotate(-90)" text-anchor="middle">{y_label}</text>"#,
        (py0 + py1) / 2.0
    );
    for x in ticks(x0, x1, x_step) {
        let _ = writeln!(
            s,
            r##"<path d="M{:.1} {py0} V{py1}" stroke="#eee"/><text x="{:.1}" y="{}" text-anchor="middle">{}</text>"##,
            sx(x),
            sx(x),
            py1 + 16.0,
            tick(x)
        );
    }
    for y in ticks(y0, y1, y_step) {
        let _ = writeln!(
            s,
            r##"<path d="M{px0} {:.1} H{px1}" stroke="#eee"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
            sy(y),
            px0 - 6.0,
            sy(y) + 4.0,
            tick(y)
        );
    }
    let _ = writeln!(s, r#"<path d="M{px0} {py0} V{py1} H{px1}" fill="none" stroke="black"/>"#);
    let mut legend = 0.0;
    let mut legend_entry = |s: &mut String, swatch: String, label: &str| {
        let ly = top + 10.0 + 18.0 * legend;
        let _ = writeln!(
            s,
            r#"<g transform="translate({} {ly})">{swatch}<text x="22" y="4">{label}</text></g>"#,
            px1 + 14.0
        );
        legend += 1.0;
    };
    for l in lines {
        let dash = if l.dashed { r#" stroke-dasharray="6 4""# } else { "" };
        let _ = writeln!(
            s,
            r#"<path d="M{:.1} {:.1} L{:.1} {:.1}" stroke="{}" stroke-width="1.5"{dash}/>"#,
            sx(l.from.0),
            sy(l.from.1),
            sx(l.to.0),
            sy(l.to.1),
            l.colour
        );
        legend_entry(&mut s, format!(r#"<path d="M0 0 h16" stroke="{}" stroke-width="2"{dash}/>"#, l.colour), l.label);
    }
    for set in sets.iter().filter(|s| !s.points.is_empty()) {
        let fill = |c: &str| {
            if set.hollow {
                format!(r#"fill="white" stroke="{c}" stroke-width="2""#)
            } else {
                format!(r#"fill="{c}""#)
            }
        };
        for &(x, y) in set.points.iter().filter(|p| p.0.is_finite() && p.1.is_finite()) {
            let _ = writeln!(s, r#"<circle cx="{:.1}" cy="{:.1}" r="5" {}/>"#, sx(x), sy(y), fill(set.colour));
        }
        legend_entry(&mut s, format!(r#"<circle cx="8" cy="0" r="5" {}/>"#, fill(set.colour)), set.name);
    }
    s.push_str("</svg>\n");
    s
}

/// A tick label with a sensible number of digits.
/// An axis from `lo` to `hi` (the data's extent) widened to whole steps of 1, 2 or 5 × 10ᵏ,
/// four to eight of them, with that step; an axis whose data are all ≥ 0 starts at 0 or above.
fn nice_axis(lo: f64, hi: f64) -> (f64, f64, f64) {
    let (lo, hi) = match (lo.is_finite() && hi.is_finite(), hi > lo) {
        (false, _) => (0.0, 1.0),
        (true, false) => (lo - 1.0, lo + 1.0),
        (true, true) => (lo, hi),
    };
    let rough = (hi - lo) / 8.0;
    let magnitude = 10f64.powf(rough.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * magnitude).find(|&s| s >= rough).unwrap_or(rough);
    let start = (lo / step).floor() * step;
    let start = if lo >= 0.0 { start.max(0.0) } else { start };
    (start, (hi / step).ceil() * step, step)
}

/// The ticks of an axis from `lo` to `hi` at `step`.
fn ticks(lo: f64, hi: f64, step: f64) -> Vec<f64> {
    let n = ((hi - lo) / step).round() as usize;
    (0..=n).map(|k| lo + k as f64 * step).collect()
}

fn tick(v: f64) -> String {
    let v = if v.abs() < 1e-9 { 0.0 } else { v };
    let a = v.abs();
    if a >= 100.0 || v == 0.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

#[cfg(test)]
mod axis_tests {
    #[test]
    fn axes_run_over_whole_nice_steps_and_volumes_do_not_go_below_zero() {
        assert_eq!(super::nice_axis(3.0, 9870.0), (0.0, 10000.0, 2000.0));
        assert_eq!(super::nice_axis(-730.0, 410.0), (-800.0, 600.0, 200.0));
        assert_eq!(super::nice_axis(0.12, 0.93), (0.0, 1.0, 0.2));
        assert_eq!(super::ticks(0.0, 10000.0, 2000.0).len(), 6);
        let (lo, hi, step) = super::nice_axis(5.0, 5.0);
        assert!(lo < 5.0 && hi > 5.0 && step > 0.0);
    }
}
