//! `nodule.png`: axial, coronal and sagittal density slices through the selection, the
//! selection outlined in red and the ground truth (cells with coverage ≥ 0.5) in green — what a
//! reader checks first: is the thing measured the nodule? One row cuts through the selection,
//! a second through the ground truth's centroid, so a miss shows as two separate outlines.
//! When the search's pick was ambiguous, a last row cuts through its rival, the ball its blob
//! stands for outlined in yellow.
//!
//! Display as docs/conventions.md: axial seen from the feet (patient right on the left,
//! anterior up), coronal from the front (superior up), sagittal from the patient's left
//! (anterior on the left, superior up); 1 mm pixels, nearest cell; grey from 0 to the
//! 99.5th percentile of the density.

use crate::formats::png;
use crate::kernels::stats;
use crate::volume::Volume;

const PIXEL_MM: f64 = 1.0;
const RED: [u8; 3] = [230, 40, 40];
const GREEN: [u8; 3] = [40, 210, 60];
const YELLOW: [u8; 3] = [240, 210, 40];

/// The sets a preview outlines: the selection (red), the ground truth (green) and the
/// ambiguous search's rival blob (yellow), each one flag per lattice cell.
pub struct Outlines<'a> {
    pub selected: &'a [bool],
    pub truth: Option<&'a [bool]>,
    pub rival: Option<&'a [bool]>,
}

/// PNG bytes of one row of three panels per cut point in `centers` (e.g. through the
/// selection, then through the ground truth), rows stacked top to bottom.
pub fn nodule_png(density: &Volume<f32>, outlines: &Outlines, centers: &[[usize; 3]]) -> Vec<u8> {
    let values: Vec<f64> = density.data.iter().map(|&v| f64::from(v)).collect();
    let white = stats::percentile(&values, 99.5).unwrap_or(1.0).max(1e-6);
    // Each panel: (horizontal axis, vertical axis, flip vertical so that increasing is up).
    let layouts = [(0, 1, false), (0, 2, true), (1, 2, true)];
    let rows: Vec<Vec<Panel>> = centers
        .iter()
        .map(|&center| layouts.iter().map(|&l| Panel::cut(density, outlines, center, l, white)).collect())
        .collect();
    tile(&rows)
}

/// One picture of a preview: `width × height` RGB pixels, row-major from the top.
pub(super) struct Panel {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

/// Pixels between panels.
const GAP: usize = 6;

/// PNG bytes of `rows` of panels, left to right and top to bottom, `GAP` pixels apart.
pub(super) fn tile(rows: &[Vec<Panel>]) -> Vec<u8> {
    let row_width = |row: &Vec<Panel>| row.iter().map(|p| p.width + GAP).sum::<usize>().saturating_sub(GAP);
    let row_height = |row: &Vec<Panel>| row.iter().map(|p| p.height).max().unwrap_or(0);
    let width = rows.iter().map(row_width).max().unwrap_or(0).max(1);
    let height = (rows.iter().map(|row| row_height(row) + GAP).sum::<usize>().saturating_sub(GAP)).max(1);
    let mut rgb = vec![0u8; 3 * width * height];
    let mut top = 0;
    for row in rows {
        let mut left = 0;
        for p in row {
            for r in 0..p.height {
                let at = left + width * (top + r);
                rgb[3 * at..3 * (at + p.width)].copy_from_slice(&p.rgb[3 * p.width * r..3 * p.width * (r + 1)]);
            }
            left += p.width + GAP;
        }
        top += row_height(row) + GAP;
    }
    png::encode_rgb8(width, height, &rgb)
}

/// Whether pixel (`c`, `r`) of a `width × height` picture lies on the edge of the set `inside`
/// holds: in it, and on the picture's border or beside a pixel outside it.
pub(super) fn on_edge(inside: impl Fn(usize, usize) -> bool, width: usize, height: usize, c: usize, r: usize) -> bool {
    inside(c, r)
        && (c == 0 || r == 0 || c + 1 == width || r + 1 == height || {
            !inside(c - 1, r) || !inside(c + 1, r) || !inside(c, r - 1) || !inside(c, r + 1)
        })
}

impl Panel {
    fn cut(
        density: &Volume<f32>,
        outlines: &Outlines,
        center: [usize; 3],
        (h, v, up): (usize, usize, bool),
        white: f64,
    ) -> Panel {
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
        Panel { width, height, rgb }
    }
}
