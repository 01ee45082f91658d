//! Radiologist contours in index space, and pylidc 0.2.3's per-annotation numbers: the
//! z → slice mapping, `Annotation.boolean_mask`, `bbox`, `centroid` and `diameter`.
//!
//! Index convention, as pylidc's: `i` = row (`yCoord`), `j` = column (`xCoord`), `k` = index
//! into the ascending slice z positions; bounding boxes are inclusive.

use super::mask::{BBox, BoxMask, GroundTruthError};
use super::polygon::MplPolygon;
use crate::formats::lidc_xml::NoduleRead;
use std::cmp::Ordering;

/// What the annotation kernels need to know about the CT series.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanGeometry {
    /// Slice z positions (mm), strictly ascending; `k` indexes this list.
    pub z_positions_mm: Vec<f64>,
    /// In-plane pixel spacing (mm), the same along rows and columns (as pylidc assumes).
    pub pixel_spacing_mm: f64,
    pub rows: usize,
    pub cols: usize,
}

impl ScanGeometry {
    /// Checked: at least two slices, strictly ascending z, positive spacing, non-empty image.
    pub fn new(
        z_positions_mm: Vec<f64>,
        pixel_spacing_mm: f64,
        rows: usize,
        cols: usize,
    ) -> Result<Self, GroundTruthError> {
        let geometry_error = |m: String| Err(GroundTruthError::Geometry(m));
        if z_positions_mm.len() < 2 {
            return geometry_error(format!("{} slice(s); need at least 2", z_positions_mm.len()));
        }
        if let Some(w) = z_positions_mm.windows(2).find(|w| w[1].partial_cmp(&w[0]) != Some(Ordering::Greater)) {
            return geometry_error(format!(
                "slice z positions must be strictly ascending, found {} then {}",
                w[0], w[1]
            ));
        }
        if !(pixel_spacing_mm.is_finite() && pixel_spacing_mm > 0.0) {
            return geometry_error(format!("pixel spacing {pixel_spacing_mm} mm"));
        }
        if rows == 0 || cols == 0 {
            return geometry_error(format!("image of {cols}×{rows} pixels"));
        }
        Ok(Self { z_positions_mm, pixel_spacing_mm, rows, cols })
    }

    pub fn slices(&self) -> usize {
        self.z_positions_mm.len()
    }

    /// pylidc's `Scan.slice_spacing`: the median gap between consecutive slice positions
    /// (numpy's median: the mean of the two middle gaps when their count is even).
    pub fn slice_spacing_mm(&self) -> f64 {
        super::stats::median_gap(&self.z_positions_mm)
    }

    /// Farthest an ROI's z may lie from its slice: a tenth of the slice spacing.
    pub fn z_tolerance_mm(&self) -> f64 {
        0.1 * self.slice_spacing_mm()
    }

    /// The slice nearest to `z_mm` (pylidc's `Contour.image_k_position`: `argmin |zs - z|`,
    /// first on ties), or an error when it is farther than [`Self::z_tolerance_mm`].
    pub fn slice_index(&self, z_mm: f64) -> Result<usize, GroundTruthError> {
        let mut best = 0;
        for (k, z) in self.z_positions_mm.iter().enumerate() {
            if (z - z_mm).abs() < (self.z_positions_mm[best] - z_mm).abs() {
                best = k;
            }
        }
        let nearest_mm = self.z_positions_mm[best];
        let tolerance_mm = self.z_tolerance_mm();
        if (nearest_mm - z_mm).abs() > tolerance_mm {
            return Err(GroundTruthError::ZOffGrid { z_mm, nearest_mm, tolerance_mm });
        }
        Ok(best)
    }

    /// z (mm) at a fractional slice index, linear between slice positions (clamped to the
    /// last slice).
    pub fn z_at_index_mm(&self, k: f64) -> f64 {
        let k0 = (k.floor() as usize).min(self.slices() - 1);
        let k1 = (k0 + 1).min(self.slices() - 1);
        let t = k - k0 as f64;
        self.z_positions_mm[k0] + t * (self.z_positions_mm[k1] - self.z_positions_mm[k0])
    }
}

/// One contour in index space.
#[derive(Debug, Clone, PartialEq)]
pub struct Contour {
    pub k: usize,
    pub inclusion: bool,
    /// `(i = row, j = column)` in drawing order.
    pub points_ij: Vec<[i64; 2]>,
}

/// One radiologist's outline of one nodule, in index space (pylidc's `Annotation`).
#[derive(Debug, Clone, PartialEq)]
pub struct Annotation {
    /// In document order (pylidc's `Contour.id` order); never empty.
    pub contours: Vec<Contour>,
}

impl Annotation {
    /// Maps each ROI's z to its slice and its `(x, y)` points to `(i = y, j = x)`.
    pub fn from_read(read: &NoduleRead, geometry: &ScanGeometry) -> Result<Self, GroundTruthError> {
        if read.rois.is_empty() {
            return Err(GroundTruthError::EmptyAnnotation(format!("`{}`", read.nodule_id)));
        }
        let contours = read
            .rois
            .iter()
            .map(|roi| {
                let k = geometry.slice_index(roi.z_mm)?;
                let points_ij =
                    roi.points.iter().map(|&(x, y)| point_ij(x, y, roi.z_mm, geometry)).collect::<Result<_, _>>()?;
                Ok(Contour { k, inclusion: roi.inclusion, points_ij })
            })
            .collect::<Result<_, GroundTruthError>>()?;
        Ok(Self { contours })
    }

    /// Every contour point as `(i, j, k)` (pylidc's `contours_matrix`, up to row order).
    pub fn points_ijk(&self) -> impl Iterator<Item = [i64; 3]> + '_ {
        self.contours.iter().flat_map(|c| c.points_ij.iter().map(move |&[i, j]| [i, j, c.k as i64]))
    }

    /// pylidc's `Annotation.bbox_matrix()` with `pad=None`: min and max of all contour points,
    /// exclusion contours included.
    pub fn bbox(&self) -> BBox {
        let mut min = [i64::MAX; 3];
        let mut max = [i64::MIN; 3];
        for p in self.points_ijk() {
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        // Points were checked to lie in the image, so they are non-negative.
        BBox { min_ijk: min.map(|v| v as usize), max_ijk: max.map(|v| v as usize) }
    }

    /// pylidc's `Annotation.centroid`: the mean `(i, j, k)` of all contour points.
    pub fn centroid_ijk(&self) -> [f64; 3] {
        let mut sum = [0i64; 3];
        let mut n = 0i64;
        for p in self.points_ijk() {
            for a in 0..3 {
                sum[a] += p[a];
            }
            n += 1;
        }
        sum.map(|s| s as f64 / n as f64)
    }

    /// pylidc's `Annotation.diameter`: the largest distance (mm) between two points of one
    /// contour, over all contours of two or more points, exclusion contours included.
    pub fn diameter_mm(&self, pixel_spacing_mm: f64) -> f64 {
        self.contours
            .iter()
            .filter(|c| c.points_ij.len() > 1)
            .map(|c| contour_diameter_mm(&c.points_ij, pixel_spacing_mm))
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// pylidc's `Annotation.boolean_mask(bbox=bbox)`, `bbox` holding [`Self::bbox`]:
    /// 1. each inclusion contour, in document order, ORs in the pixels matplotlib's
    ///    `Path.contains_points` counts inside it (pixel centres at integer `(i, j)`, the path
    ///    built over `(i, j)`), then switches that contour's own points off;
    /// 2. then each exclusion contour switches off the pixels inside it and its own points.
    ///
    /// Because points are switched off per contour, a later inclusion contour on the same slice
    /// may switch an earlier contour's points back on, exactly as in pylidc.
    pub fn boolean_mask(&self, bbox: &BBox) -> BoxMask {
        let mut mask = BoxMask::empty(*bbox);
        for contour in self.contours.iter().filter(|c| c.inclusion) {
            for_each_inside(contour, |i, j| mask.set(i, j, contour.k, true));
            switch_off_points(&mut mask, contour);
        }
        for contour in self.contours.iter().filter(|c| !c.inclusion) {
            for_each_inside(contour, |i, j| mask.set(i, j, contour.k, false));
            switch_off_points(&mut mask, contour);
        }
        mask
    }
}

fn point_ij(x: i32, y: i32, z_mm: f64, geometry: &ScanGeometry) -> Result<[i64; 2], GroundTruthError> {
    let inside = |v: i32, n: usize| v >= 0 && (v as usize) < n;
    if !(inside(x, geometry.cols) && inside(y, geometry.rows)) {
        return Err(GroundTruthError::PointOutsideImage { x, y, z_mm, cols: geometry.cols, rows: geometry.rows });
    }
    Ok([i64::from(y), i64::from(x)])
}

/// Largest pairwise distance, scaling each coordinate to mm before subtracting as
/// `scipy.spatial.distance.pdist(points * pixel_spacing)` does (same rounding).
///
/// Only the convex hull's corners are compared: the farthest pair is always two of them (the
/// distance to a point is strictly convex along any segment), and on integer pixels two
/// different true distances differ far more than rounding could reorder. So the value is
/// pdist's, bit for bit. The points cost a sort; the pairs are the corners', of which a convex
/// polygon on a slice's pixel grid has a few hundred at most, however many points it has.
fn contour_diameter_mm(points_ij: &[[i64; 2]], pixel_spacing_mm: f64) -> f64 {
    let hull = hull_corners(points_ij);
    let mm: Vec<[f64; 2]> = hull.iter().map(|p| p.map(|v| v as f64 * pixel_spacing_mm)).collect();
    let mut largest = 0.0f64;
    for (n, a) in mm.iter().enumerate() {
        for b in &mm[n + 1..] {
            let (di, dj) = (a[0] - b[0], a[1] - b[1]);
            largest = largest.max((di * di + dj * dj).sqrt());
        }
    }
    largest
}

/// The strict corners of the points' convex hull (Andrew's monotone chain; collinear and
/// repeated points dropped), or the distinct points themselves when there are fewer than three.
fn hull_corners(points: &[[i64; 2]]) -> Vec<[i64; 2]> {
    let mut sorted = points.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    if sorted.len() < 3 {
        return sorted;
    }
    // Cross product > 0: o → a → b turns left (counter-clockwise).
    let turns_left =
        |o: [i64; 2], a: [i64; 2], b: [i64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]) > 0;
    let mut hull: Vec<[i64; 2]> = Vec::with_capacity(2 * sorted.len());
    // The lower chain left to right, then the upper chain right to left; each chain starts at
    // the corner the previous one ended on (`chain_start`) and never pops it.
    let lower = sorted.iter();
    let upper = sorted[..sorted.len() - 1].iter().rev();
    for chain in [lower.collect::<Vec<_>>(), upper.collect::<Vec<_>>()] {
        let chain_start = hull.len().saturating_sub(1);
        for &p in chain {
            while hull.len() >= chain_start + 2 && !turns_left(hull[hull.len() - 2], hull[hull.len() - 1], p) {
                hull.pop();
            }
            hull.push(p);
        }
    }
    hull.pop(); // the first corner, reached again at the end of the upper chain
    hull
}

/// Calls `f(i, j)` for every pixel matplotlib counts inside the contour. Only the contour's own
/// bounding rectangle is visited: the crossings test never counts a point outside it.
fn for_each_inside(contour: &Contour, mut f: impl FnMut(usize, usize)) {
    MplPolygon::from_contour(&contour.points_ij).for_each_inside(|i, j| f(i as usize, j as usize));
}

fn switch_off_points(mask: &mut BoxMask, contour: &Contour) {
    for &[i, j] in &contour.points_ij {
        mask.set(i as usize, j as usize, contour.k, false);
    }
}

/// Every annotation must have a contour: an empty one has no bbox (pylidc fails on it too).
pub(crate) fn check_not_empty<'a>(
    annotations: impl IntoIterator<Item = &'a Annotation>,
) -> Result<(), GroundTruthError> {
    match annotations.into_iter().position(|a| a.contours.is_empty()) {
        Some(n) => Err(GroundTruthError::EmptyAnnotation(format!("#{n}"))),
        None => Ok(()),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    pub(crate) fn geometry() -> ScanGeometry {
        ScanGeometry::new(vec![0.0, 2.5, 5.0, 7.5, 10.0], 0.5, 32, 32).unwrap()
    }

    pub(crate) fn square_contour(k: usize, i0: i64, j0: i64, side: i64, inclusion: bool) -> Contour {
        let points_ij = vec![[i0, j0], [i0, j0 + side], [i0 + side, j0 + side], [i0 + side, j0]];
        Contour { k, inclusion, points_ij }
    }

    /// One square inclusion contour, corners (i0, j0) → (i0, j0 + side) → …, on each slice `ks`.
    pub(crate) fn square_annotation(ks: &[usize], i0: i64, j0: i64, side: i64) -> Annotation {
        Annotation { contours: ks.iter().map(|&k| square_contour(k, i0, j0, side, true)).collect() }
    }

    #[test]
    fn slice_index_matches_nearest_and_rejects_off_grid() {
        let g = geometry();
        assert_eq!(g.slice_spacing_mm(), 2.5);
        assert_eq!(g.slice_index(5.1), Ok(2));
        assert_eq!(g.slice_index(-0.2), Ok(0));
        let err = g.slice_index(6.0).unwrap_err();
        assert_eq!(
            err.to_string(),
            "ROI at z = 6 mm matches no slice: the nearest slice is at 5 mm, more than 0.25 mm away"
        );
    }

    #[test]
    fn median_gap_of_an_even_count_averages_the_middle_two() {
        let g = ScanGeometry::new(vec![0.0, 1.0, 3.0, 6.0, 7.0], 1.0, 4, 4).unwrap();
        // gaps 1, 2, 3, 1 → sorted 1, 1, 2, 3 → (1 + 2) / 2
        assert_eq!(g.slice_spacing_mm(), 1.5);
        assert!(ScanGeometry::new(vec![0.0, 0.0], 1.0, 4, 4).is_err());
    }

    #[test]
    fn square_mask_drops_vertices_and_follows_matplotlib_on_edges() {
        // Corners (2,2) → (2,6) → (6,6) → (6,2), path x = i, y = j. For this orientation
        // matplotlib counts the edge j = 6 inside and the edges j = 2, i = 2, i = 6 outside
        // (checked against a line-by-line Python port of `point_in_path_impl`): i 3..=5 ×
        // j 3..=6 = 12 pixels, none of them a vertex.
        let a = square_annotation(&[1], 2, 2, 4);
        let mask = a.boolean_mask(&a.bbox());
        assert_eq!(mask.count(), 12);
        assert!(mask.get(4, 6, 1), "edge j = jmax is inside");
        assert!(!mask.get(4, 2, 1), "edge j = jmin is outside");
        assert!(!mask.get(2, 4, 1) && !mask.get(6, 4, 1), "edges i = imin, imax are outside");
        assert!(!mask.get(6, 6, 1), "vertices are off");
        assert_eq!(mask.count_per_slice(), vec![12]);
    }

    #[test]
    fn exclusion_after_inclusion() {
        let mut a = square_annotation(&[0], 0, 0, 10);
        // Exclusion listed first must still cut after the inclusion is filled.
        a.contours.insert(0, square_contour(0, 3, 3, 4, false));
        let mask = a.boolean_mask(&a.bbox());
        assert!(!mask.get(5, 5, 0));
        assert!(!mask.get(3, 3, 0), "exclusion vertices are off");
        assert!(mask.get(1, 5, 0));
        // Full square: i 1..=9 × j 1..=10 = 90; the hole (i 4..=6 × j 4..=7 = 12) and its four
        // vertices, all inside the big square, leave 90 − 16 = 74.
        assert_eq!(mask.count(), 74);
    }

    /// The hull-corner diameter is pdist's all-pairs maximum, bit for bit, on random point
    /// sets with repeats and collinear runs.
    #[test]
    fn hull_diameter_equals_the_all_pairs_maximum() {
        let mut rng = ChaCha8Rng::seed_from_u64(0x2545_F491_4F6C_DD1D);
        let mut next = |n: u64| rng.gen_range(0..n) as i64;
        for trial in 0..500 {
            let len = 1 + next(40) as usize;
            let spread = 2 + next(60) as u64;
            let mut points: Vec<[i64; 2]> = (0..len).map(|_| [next(spread), next(spread)]).collect();
            if trial % 5 == 0 {
                points.extend((0..10).map(|t| [t, 2 * t])); // a collinear run
            }
            let ps = 0.5 + next(1000) as f64 / 997.0;
            let mm: Vec<[f64; 2]> = points.iter().map(|p| p.map(|v| v as f64 * ps)).collect();
            let mut all_pairs = 0.0f64;
            for (n, a) in mm.iter().enumerate() {
                for b in &mm[n + 1..] {
                    let (di, dj) = (a[0] - b[0], a[1] - b[1]);
                    all_pairs = all_pairs.max((di * di + dj * dj).sqrt());
                }
            }
            assert_eq!(contour_diameter_mm(&points, ps).to_bits(), all_pairs.to_bits(), "{points:?}");
        }
    }
}
