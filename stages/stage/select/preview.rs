//! `nodule.png`: axial, coronal and sagittal density slices through the selection, the
//! selection outlined in red and the ground truth (cells with coverage ≥ 0.5) in green — what a
//! reader checks first: is the thing measured the nodule? One row cuts through the selection,
//! a second through the ground truth's centroid, so a miss shows as two separate outlines.
//! When the search's pick was ambiguous, a last row cuts through its rival, the ball its blob
//! stands for outlined in yellow. Each row ends with the axial cut enlarged 4× around its
//! point, for nodules a few pixels wide.
//!
//! The sheet says what it shows: the patient, rule and verdict (HIT, MISS or UNVERIFIED) on
//! top, a legend of the outlines, each column's view and each row's cut, orientation letters
//! on every panel's edges and a 20 mm scale bar. Display as docs/conventions.md: axial seen
//! from the feet (patient right on the left, anterior up), coronal from the front (superior
//! up), sagittal from the patient's left (anterior on the left, superior up); 1 mm pixels,
//! nearest cell; grey from 0 to the 99.5th percentile of the density.

use crate::formats::canvas::{text_width, Canvas, GLYPH_PX};
use crate::kernels::stats;
use crate::volume::Volume;

const PIXEL_MM: f64 = 1.0;
pub(super) const RED: [u8; 3] = [230, 40, 40];
const GREEN: [u8; 3] = [40, 210, 60];
const YELLOW: [u8; 3] = [240, 210, 40];
const WHITE: [u8; 3] = [255, 255, 255];
const BLACK: [u8; 3] = [0, 0, 0];
const GREY: [u8; 3] = [150, 150, 150];
/// The side of the enlarged crop around a cut point, mm, and its enlargement.
const INSET_MM: f64 = 32.0;
const INSET_ZOOM: usize = 4;
/// The scale bar's length, mm.
const SCALE_BAR_MM: f64 = 20.0;

/// The sets a preview outlines: the selection (red), the ground truth (green) and the
/// ambiguous search's rival blob (yellow), each one flag per lattice cell.
pub struct Outlines<'a> {
    pub selected: &'a [bool],
    pub truth: Option<&'a [bool]>,
    pub rival: Option<&'a [bool]>,
}

/// One row of `nodule.png`: what it cuts through (its label) and the cell it cuts at.
pub struct Cut {
    pub label: String,
    pub center: [usize; 3],
}

/// PNG bytes of `title` and `verdict` (the selection's) over one row of panels per cut.
pub fn nodule_png(density: &Volume<f32>, outlines: &Outlines, cuts: &[Cut], title: &str, verdict: &str) -> Vec<u8> {
    let values: Vec<f64> = density.data.iter().map(|&v| f64::from(v)).collect();
    let white = stats::percentile(&values, 99.5).unwrap_or(1.0).max(1e-6);
    // Each panel: (horizontal axis, vertical axis, flip vertical so that increasing is up), and
    // the letters on its left, right, top and bottom edges.
    let layouts = [
        ((0, 1, false), ["R", "L", "A", "P"]),
        ((0, 2, true), ["R", "L", "S", "I"]),
        ((1, 2, true), ["A", "P", "S", "I"]),
    ];
    let rows: Vec<(String, Vec<Canvas>)> = cuts
        .iter()
        .map(|cut| {
            let mut panels: Vec<Canvas> = layouts
                .iter()
                .map(|&(layout, letters)| {
                    let mut panel = cut_panel(density, outlines, cut.center, layout, white);
                    annotate(&mut panel, letters, SCALE_BAR_MM / PIXEL_MM);
                    panel
                })
                .collect();
            let inset = enlarged(&panels[0], density, cut.center);
            panels.push(inset);
            (cut.label.clone(), panels)
        })
        .collect();
    // The verdict's first word: "hit", "MISS" or another ("unverified" without a ground truth).
    let outcome = match verdict.split(|c: char| !c.is_ascii_alphabetic()).next().unwrap_or("") {
        "hit" => ("HIT", GREEN),
        "MISS" => ("MISS", RED),
        _ => ("UNVERIFIED", GREY),
    };
    let legend: Vec<([u8; 3], &str)> = [
        Some((RED, "measured (nodule_mask)")),
        outlines.truth.map(|_| (GREEN, "ground truth: >= 50% of readers")),
        outlines.rival.map(|_| (YELLOW, "rival blob")),
    ]
    .into_iter()
    .flatten()
    .collect();
    let columns = ["axial, from the feet", "coronal, from the front", "sagittal, from the left", "axial 4x, 32 mm"];
    Sheet { title, badge: Some(outcome), legend: &legend, columns: &columns, rows }.png()
}

/// A labelled grid of panels: a title (and a badge), a legend, the columns' names, and rows of
/// panels each under its label.
pub(super) struct Sheet<'a> {
    pub title: &'a str,
    pub badge: Option<(&'a str, [u8; 3])>,
    pub legend: &'a [([u8; 3], &'a str)],
    pub columns: &'a [&'a str],
    pub rows: Vec<(String, Vec<Canvas>)>,
}

/// Pixels between panels and around the sheet.
const GAP: usize = 6;
/// A text line's height at scale 1, with its spacing.
const LINE: usize = GLYPH_PX + 6;

impl Sheet<'_> {
    pub(super) fn png(&self) -> Vec<u8> {
        let columns = self.rows.iter().map(|(_, row)| row.len()).max().unwrap_or(0).max(self.columns.len());
        let column_width = |k: usize| {
            let panels = self.rows.iter().filter_map(|(_, row)| row.get(k)).map(|p| p.width).max().unwrap_or(0);
            panels.max(self.columns.get(k).map_or(0, |c| text_width(c, 1)))
        };
        let widths: Vec<usize> = (0..columns).map(column_width).collect();
        let lefts: Vec<usize> = widths.iter().scan(GAP, |x, w| Some(std::mem::replace(x, *x + w + 2 * GAP))).collect();
        let title_width = text_width(self.title, 2) + self.badge.map_or(0, |(b, _)| text_width(b, 2) + 4 * GAP);
        let legend_width: usize = self.legend.iter().map(|(_, l)| text_width(l, 1) + 2 * GLYPH_PX + 2 * GAP).sum();
        let width = (lefts.last().zip(widths.last()).map_or(0, |(l, w)| l + w + GAP)).max(title_width + 2 * GAP);
        let width = width.max(legend_width + 2 * GAP);
        let row_height = |row: &Vec<Canvas>| row.iter().map(|p| p.height).max().unwrap_or(0);
        let head = GAP + 2 * GLYPH_PX + GAP + LINE + LINE;
        let height = head + self.rows.iter().map(|(_, row)| LINE + row_height(row) + GAP).sum::<usize>() + GAP;
        let mut sheet = Canvas::new(width, height, BLACK);
        let drawn = sheet.text(GAP, GAP, self.title, WHITE, 2);
        if let Some((badge, colour)) = self.badge {
            sheet.label(GAP + drawn + 2 * GAP, GAP - 2, badge, (BLACK, colour), 2);
        }
        let mut x = GAP;
        let legend_top = GAP + 2 * GLYPH_PX + GAP;
        for &(colour, text) in self.legend {
            sheet.fill(x, legend_top, GLYPH_PX, GLYPH_PX, colour);
            x += 2 * GLYPH_PX + sheet.text(x + 2 * GLYPH_PX - GLYPH_PX / 2, legend_top, text, WHITE, 1) + 2 * GAP;
        }
        for (k, name) in self.columns.iter().enumerate() {
            sheet.text(lefts[k], legend_top + LINE, name, GREY, 1);
        }
        let mut top = head;
        for (label, row) in &self.rows {
            sheet.text(GAP, top, label, WHITE, 1);
            top += LINE;
            for (k, panel) in row.iter().enumerate() {
                sheet.paste(lefts[k], top, panel.width, &panel.rgb);
            }
            top += row_height(row) + GAP;
        }
        sheet.png()
    }
}

/// Whether pixel (`c`, `r`) of a `width × height` picture lies on the edge of the set `inside`
/// holds: in it, and on the picture's border or beside a pixel outside it.
pub(super) fn on_edge(inside: impl Fn(usize, usize) -> bool, width: usize, height: usize, c: usize, r: usize) -> bool {
    inside(c, r)
        && (c == 0 || r == 0 || c + 1 == width || r + 1 == height || {
            !inside(c - 1, r) || !inside(c + 1, r) || !inside(c, r - 1) || !inside(c, r + 1)
        })
}

/// The orientation letters at the middle of `panel`'s left, right, top and bottom edges, and a
/// scale bar of `bar_px` pixels at its bottom left.
fn annotate(panel: &mut Canvas, [left, right, top, bottom]: [&str; 4], bar_px: f64) {
    let (w, h) = (panel.width, panel.height);
    let colours = (YELLOW, BLACK);
    let middle_row = (h / 2).saturating_sub(GLYPH_PX / 2);
    panel.label(1, middle_row, left, colours, 1);
    panel.label(w.saturating_sub(GLYPH_PX + 3), middle_row, right, colours, 1);
    panel.label((w / 2).saturating_sub(GLYPH_PX / 2), 1, top, colours, 1);
    panel.label((w / 2).saturating_sub(GLYPH_PX / 2), h.saturating_sub(GLYPH_PX + 3), bottom, colours, 1);
    let bar = bar_px.round() as usize;
    let bar_top = h.saturating_sub(6);
    panel.fill(4, bar_top, bar, 2, WHITE);
    panel.text(4, bar_top.saturating_sub(GLYPH_PX + 2), &format!("{SCALE_BAR_MM:.0} mm"), WHITE, 1);
}

/// The axial `panel`'s square of `INSET_MM` around `center`, enlarged `INSET_ZOOM`× (nearest),
/// with its scale bar.
fn enlarged(axial: &Canvas, density: &Volume<f32>, center: [usize; 3]) -> Canvas {
    let g = &density.geometry;
    let side = (INSET_MM / PIXEL_MM).round() as usize;
    let at = |a: usize| ((center[a] as f64 + 0.5) * g.spacing_mm[a] / PIXEL_MM) as i64;
    let (c0, r0) = (at(0) - side as i64 / 2, at(1) - side as i64 / 2);
    let zoomed = side * INSET_ZOOM;
    let mut inset = Canvas::new(zoomed, zoomed, [0, 0, 64]);
    for r in 0..zoomed {
        for c in 0..zoomed {
            let (x, y) = (c0 + (c / INSET_ZOOM) as i64, r0 + (r / INSET_ZOOM) as i64);
            if (0..axial.width as i64).contains(&x) && (0..axial.height as i64).contains(&y) {
                let from = 3 * (x as usize + axial.width * y as usize);
                inset.rgb[3 * (c + zoomed * r)..3 * (c + zoomed * r) + 3].copy_from_slice(&axial.rgb[from..from + 3]);
            }
        }
    }
    let bar_px = 10.0 / PIXEL_MM * INSET_ZOOM as f64;
    let bar_top = zoomed - 6;
    inset.fill(4, bar_top, bar_px.round() as usize, 2, WHITE);
    inset.text(4, bar_top - GLYPH_PX - 2, "10 mm", WHITE, 1);
    inset
}

/// The slice through `center` across axes `h` (left to right) and `v` (top to bottom, or
/// bottom to top with `up`), the outlines drawn over it.
fn cut_panel(
    density: &Volume<f32>,
    outlines: &Outlines,
    center: [usize; 3],
    (h, v, up): (usize, usize, bool),
    white: f64,
) -> Canvas {
    let g = &density.geometry;
    let extent = |a: usize| g.dims[a] as f64 * g.spacing_mm[a];
    let (width, height) = ((extent(h) / PIXEL_MM).round() as usize, (extent(v) / PIXEL_MM).round() as usize);
    // The cell under each pixel.
    let cell_of = |col: usize, row: usize| {
        let row = if up { height - 1 - row } else { row };
        let mut ijk = center;
        ijk[h] = (((col as f64 + 0.5) * PIXEL_MM / g.spacing_mm[h]) as usize).min(g.dims[h] - 1);
        ijk[v] = (((row as f64 + 0.5) * PIXEL_MM / g.spacing_mm[v]) as usize).min(g.dims[v] - 1);
        g.index(ijk[0], ijk[1], ijk[2])
    };
    let cells: Vec<usize> =
        (0..height).flat_map(|r| (0..width).map(move |c| (c, r))).map(|(c, r)| cell_of(c, r)).collect();
    let mut rgb: Vec<u8> = cells
        .iter()
        .flat_map(|&i| {
            let grey = (f64::from(density.data[i]) / white).clamp(0.0, 1.0) * 255.0;
            [grey.round() as u8; 3]
        })
        .collect();
    let mut outline = |set: &[bool], colour: [u8; 3]| {
        for r in 0..height {
            for c in 0..width {
                if on_edge(|c, r| set[cells[c + width * r]], width, height, c, r) {
                    rgb[3 * (c + width * r)..3 * (c + width * r) + 3].copy_from_slice(&colour);
                }
            }
        }
    };
    if let Some(t) = outlines.truth {
        outline(t, GREEN);
    }
    if let Some(rival) = outlines.rival {
        outline(rival, YELLOW);
    }
    outline(outlines.selected, RED);
    Canvas { width, height, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Geometry;

    fn decode(bytes: &[u8]) -> (usize, usize, Vec<u8>) {
        let decoder = ::png::Decoder::new(bytes);
        let mut reader = decoder.read_info().unwrap();
        let mut rgb = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut rgb).unwrap();
        (info.width as usize, info.height as usize, rgb)
    }

    fn count(rgb: &[u8], colour: [u8; 3]) -> usize {
        rgb.chunks_exact(3).filter(|p| *p == colour).count()
    }

    #[test]
    fn the_sheet_names_its_verdict_outlines_views_and_scale() {
        let geometry = Geometry {
            dims: [40, 30, 20],
            spacing_mm: [2.0, 2.0, 3.0],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let n = geometry.len();
        let density = Volume { geometry: geometry.clone(), data: (0..n).map(|i| (i % 7) as f32).collect() };
        let ball = geometry.ball_mask([40.0, 30.0, 30.0], 6.0);
        let outlines = Outlines { selected: &ball, truth: Some(&ball), rival: None };
        let cuts = [Cut { label: "through the guided selection".into(), center: [20, 15, 10] }];
        let sheet = |verdict: &str| decode(&nodule_png(&density, &outlines, &cuts, "P1: guided selection", verdict));
        let (width, height, hit) = sheet("hit; the guided search found no blob of the annotated size");
        // Three 80 × 60 … mm panels at 1 mm pixels and a 128-pixel inset, under a title, a legend,
        // the views' names and the row's label.
        assert!(width >= 80 + 80 + 60 + 128 && height >= 128 + 4 * GLYPH_PX, "{width} × {height}");
        let (_, _, miss) = sheet("MISS: the selection does not touch the nodule");
        let (_, _, unverified) = sheet("unverified: no annotation");
        // The badge: green for a hit, red for a miss, grey without a ground truth.
        assert!(count(&hit, GREEN) > count(&miss, GREEN) && count(&miss, RED) > count(&hit, RED));
        assert!(count(&unverified, GREY) > count(&hit, GREY));
        // Orientation letters on yellow-lettered black boxes, and white scale bars and text.
        assert!(count(&hit, YELLOW) > 4 * 12 && count(&hit, WHITE) > 200);
        // The outlines are drawn: the selection (red) over the truth (green) in the panels.
        assert!(count(&hit, RED) > 0);
    }
}
