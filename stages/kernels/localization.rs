//! Localization against the ground truth (SPEC §3 select): the consensus mask resampled onto
//! the density grid as per-cell coverage, and the Dice, centroid distance and hit of a
//! selected set of cells.
//!
//! A cell's coverage is the fraction of its volume covered by the consensus mask's voxels
//! (exact box overlaps, so cells thinner than the CT's slice spacing are covered too). Dice uses the cells with coverage
//! ≥ 0.5; a selection is a hit when it holds at least one cell with coverage > 0 (it touches
//! the nodule's footprint).

use crate::volume::{Geometry, Volume};
use rayon::prelude::*;

/// The ground truth on the density grid.
#[derive(Debug, Clone)]
pub struct GroundTruthOnGrid {
    /// Coverage of each density cell, in [0, 1].
    pub coverage: Vec<f32>,
    /// Centroid of the consensus voxels, patient mm.
    pub centroid_mm: [f64; 3],
    /// Number of cells with coverage ≥ 0.5.
    pub core_cells: usize,
}

/// How a selected set of cells compares with the ground truth.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Localization {
    pub dice: f64,
    pub centroid_distance_mm: f64,
    pub hit: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum LocalizationError {
    #[error("ground-truth mask and density grid must both be axis-aligned (direction a signed identity); {0} is not")]
    Rotated(&'static str),
    #[error("the ground-truth mask is empty: no consensus voxel to localise against")]
    EmptyMask,
}

/// Resamples the consensus `mask` (non-zero = inside) onto `grid`: each cell's coverage is
/// the volume of the mask's voxels (boxes around their centres) inside the cell over the
/// cell's volume. Axis-aligned grids make the overlap of two boxes a product of per-axis
/// overlaps, so a CT voxel touches only the few cells its extent spans on each axis.
pub fn ground_truth_on_grid(mask: &Volume<u8>, grid: &Geometry) -> Result<GroundTruthOnGrid, LocalizationError> {
    check_axis_aligned(&mask.geometry, "the ground-truth mask")?;
    check_axis_aligned(grid, "the density grid")?;
    // overlaps[a][i]: (cell, overlap length in cell units) for CT index i along axis a.
    let overlaps: [Vec<Vec<(usize, f64)>>; 3] = std::array::from_fn(|a| {
        let cell_mm = grid.spacing_mm[a];
        (0..mask.geometry.dims[a])
            .map(|i| {
                // The CT voxel's extent in continuous cell coordinates (cell c spans [c − ½, c + ½]).
                let centre =
                    (axis_mm(&mask.geometry, a, i as f64) - grid.origin_mm[a]) * grid.direction[a][a] / cell_mm;
                let half = 0.5 * mask.geometry.spacing_mm[a] / cell_mm;
                let (lo, hi) = (centre - half, centre + half);
                let first = ((lo + 0.5).floor() as isize).max(0);
                let last = ((hi + 0.5).ceil() as isize - 1).min(grid.dims[a] as isize - 1);
                (first..=last)
                    .map(|c| (c as usize, hi.min(c as f64 + 0.5) - lo.max(c as f64 - 0.5)))
                    .filter(|&(_, len)| len > 0.0)
                    .collect()
            })
            .collect()
    });
    let [nx, ny, _] = grid.dims;
    let [mx, my, mz] = mask.geometry.dims;
    let mut coverage_sum = vec![0f64; grid.len()];
    let (mut sum_mm, mut count) = ([0f64; 3], 0usize);
    // A nodule fills a few slices of a CT's hundreds: find them first, in parallel, with a
    // branch-free scan (an OR over the bytes vectorises; a search for the first hit does not).
    let any_set = |values: &[u8]| values.iter().fold(0u8, |a, &v| a | v) != 0;
    let occupied: Vec<bool> = mask.data.par_chunks(mx * my).map(any_set).collect();
    for k in (0..mz).filter(|&k| occupied[k]) {
        for j in 0..my {
            let row = &mask.data[mx * (j + my * k)..mx * (j + my * k + 1)];
            if !any_set(row) {
                continue;
            }
            for (i, _) in row.iter().enumerate().filter(|(_, &v)| v != 0) {
                let ijk = [i, j, k];
                for a in 0..3 {
                    sum_mm[a] += axis_mm(&mask.geometry, a, ijk[a] as f64);
                }
                count += 1;
                for &(cz, wz) in &overlaps[2][k] {
                    for &(cy, wy) in &overlaps[1][j] {
                        for &(cx, wx) in &overlaps[0][i] {
                            coverage_sum[cx + nx * (cy + ny * cz)] += wx * wy * wz;
                        }
                    }
                }
            }
        }
    }
    if count == 0 {
        return Err(LocalizationError::EmptyMask);
    }
    // Sums of overlap fractions can exceed 1 by rounding only.
    let coverage: Vec<f32> = coverage_sum.iter().map(|&c| c.min(1.0) as f32).collect();
    let core_cells = coverage.iter().filter(|&&c| c >= 0.5).count();
    Ok(GroundTruthOnGrid { coverage, centroid_mm: sum_mm.map(|s| s / count as f64), core_cells })
}

impl GroundTruthOnGrid {
    /// Dice, centroid distance and hit of the cells where `selected` is true on `grid`.
    pub fn compare(&self, selected: &[bool], grid: &Geometry) -> Localization {
        let labels: Vec<u32> = selected.iter().map(|&s| u32::from(s)).collect();
        self.compare_labels(&labels, 1, grid)[0]
    }

    /// [`compare`](Self::compare) for every label `1..=count` of a label volume, in one pass.
    pub fn compare_labels(&self, labels: &[u32], count: usize, grid: &Geometry) -> Vec<Localization> {
        #[derive(Clone, Copy, Default)]
        struct Tally {
            cells: usize,
            both: usize,
            hit: bool,
            sum: [f64; 3],
        }
        let mut tallies = vec![Tally::default(); count];
        let [nx, ny, _] = grid.dims;
        for (c, &l) in labels.iter().enumerate().filter(|(_, &l)| l != 0) {
            let t = &mut tallies[l as usize - 1];
            let cov = self.coverage[c];
            t.cells += 1;
            t.hit |= cov > 0.0;
            t.both += usize::from(cov >= 0.5);
            for (a, i) in [c % nx, (c / nx) % ny, c / (nx * ny)].into_iter().enumerate() {
                t.sum[a] += i as f64;
            }
        }
        tallies
            .iter()
            .map(|t| {
                let total = t.cells + self.core_cells;
                let dice = if total == 0 { 0.0 } else { 2.0 * t.both as f64 / total as f64 };
                let centroid_distance_mm = if t.cells == 0 {
                    f64::INFINITY
                } else {
                    let mm = grid.voxel_to_patient_mm(t.sum.map(|s| s / t.cells as f64));
                    (0..3).map(|a| (mm[a] - self.centroid_mm[a]).powi(2)).sum::<f64>().sqrt()
                };
                Localization { dice, centroid_distance_mm, hit: t.hit }
            })
            .collect()
    }
}

/// Patient-mm coordinate along axis `a` of index `i` (axis-aligned geometry).
fn axis_mm(g: &Geometry, a: usize, i: f64) -> f64 {
    g.origin_mm[a] + i * g.spacing_mm[a] * g.direction[a][a]
}

fn check_axis_aligned(g: &Geometry, what: &'static str) -> Result<(), LocalizationError> {
    let aligned =
        (0..3).all(|a| (0..3).all(|b| if a == b { g.direction[a][b].abs() == 1.0 } else { g.direction[a][b] == 0.0 }));
    if aligned {
        Ok(())
    } else {
        Err(LocalizationError::Rotated(what))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry(dims: [usize; 3], spacing_mm: [f64; 3], origin_mm: [f64; 3]) -> Geometry {
        Geometry { dims, spacing_mm, origin_mm, direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] }
    }

    #[test]
    fn cells_thinner_than_the_slice_spacing_are_covered() {
        // CT slices 2.5 mm apart, one slice in the mask; density cells 1 mm thick along z: the
        // slab [1.25, 3.75] mm covers cells 2 (fully) and 1, 3 (by a quarter each).
        let ct = geometry([2, 2, 3], [1.0, 1.0, 2.5], [0.0; 3]);
        let mut data = vec![0u8; 12];
        data[4..8].fill(1); // slice k = 1, at z = 2.5 mm
        let grid = geometry([1, 1, 6], [2.0, 2.0, 1.0], [0.5, 0.5, 0.0]);
        let gt = ground_truth_on_grid(&Volume { geometry: ct, data }, &grid).unwrap();
        let expected = [0.0, 0.25, 1.0, 1.0, 0.25, 0.0];
        assert!(gt.coverage.iter().zip(expected).all(|(&c, e)| (c - e).abs() < 1e-6), "{:?}", gt.coverage);
    }

    #[test]
    fn coverage_counts_ct_voxels_per_cell() {
        // CT 1 mm voxels 0..8 per axis; grid cells of 2 mm centred at 0.5, 2.5, …: each holds
        // 2×2×2 CT voxels. Mask: a 3×2×2 block at x 0..3, y 0..2, z 0..2.
        let ct = geometry([8, 8, 8], [1.0; 3], [0.0; 3]);
        let mut data = vec![0u8; 512];
        for z in 0..2 {
            for y in 0..2 {
                for x in 0..3 {
                    data[x + 8 * (y + 8 * z)] = 1;
                }
            }
        }
        let grid = geometry([4, 4, 4], [2.0; 3], [0.5; 3]);
        let gt = ground_truth_on_grid(&Volume { geometry: ct, data }, &grid).unwrap();
        assert_eq!(gt.coverage[0], 1.0);
        assert_eq!(gt.coverage[1], 0.5);
        assert_eq!(gt.coverage[2], 0.0);
        assert_eq!(gt.core_cells, 2);
        assert_eq!(gt.centroid_mm, [1.0, 0.5, 0.5]);
        let mut selected = vec![false; 64];
        selected[1] = true;
        let l = gt.compare(&selected, &grid);
        assert!(l.hit);
        assert!((l.dice - 2.0 / 3.0).abs() < 1e-12);
        selected[1] = false;
        selected[63] = true;
        let miss = gt.compare(&selected, &grid);
        assert!(!miss.hit && miss.dice == 0.0 && miss.centroid_distance_mm > 8.0);
    }
}
