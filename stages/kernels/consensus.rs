//! Nodule ground truth from radiologist contours, numerically identical to pylidc 0.2.3
//! (SPEC §3 ingest): the consensus mask of a nodule's annotations at `clevel`, the per-nodule
//! numbers (volume, diameters, centroid), and the whole-scan entry point [`scan_truth`].
//!
//! The pylidc rules reproduced by this kernel family, each documented where it is implemented:
//! - `Annotation.boolean_mask`, `.bbox`, `.centroid`, `.diameter`: [`Annotation`].
//! - matplotlib `Path.contains_points`: [`super::polygon`].
//! - `Scan.cluster_annotations()`: [`cluster_annotations`].
//! - `pylidc.utils.consensus(anns, clevel, pad=None)`: [`consensus`].
//!
//! Pure numerics, no I/O. Masks are stored `[k][i][j]` (slice, row, column), the same order as
//! [`crate::volume::Volume`]'s `[slice][row][col]` (which names its fastest axis, the column,
//! "i").

use super::annotation::check_not_empty;
pub use super::annotation::{Annotation, Contour, ScanGeometry};
pub use super::cluster::{cluster_annotations, ClusterParams, Clustering};
pub use super::mask::{BBox, BoxMask, GroundTruthError};
use crate::formats::lidc_xml::ReadMessage;

/// pylidc's default consensus level.
pub const DEFAULT_CLEVEL: f64 = 0.5;

/// The consensus of a set of annotations.
#[derive(Debug, Clone, PartialEq)]
pub struct Consensus {
    /// Union of the annotations' boxes (pylidc's consensus bbox with `pad=None`).
    pub bbox: BBox,
    /// On where the fraction of annotations whose mask is on is `>= clevel`.
    pub mask: BoxMask,
    /// Each annotation's [`Annotation::boolean_mask`] over `bbox`, in input order.
    pub masks: Vec<BoxMask>,
}

/// `pylidc.utils.consensus(anns, clevel, pad=None)`. The fraction is `count / n` in `f64`, as
/// numpy's mean of booleans, so e.g. two annotations at 0.5 give their union.
pub fn consensus(annotations: &[&Annotation], clevel: f64) -> Result<Consensus, GroundTruthError> {
    if !(clevel > 0.0 && clevel <= 1.0) {
        return Err(GroundTruthError::Clevel(clevel));
    }
    let first = annotations.first().ok_or(GroundTruthError::NoAnnotations)?;
    check_not_empty(annotations.iter().copied())?;
    let bbox = annotations.iter().fold(first.bbox(), |b, a| b.union(&a.bbox()));
    let masks: Vec<BoxMask> = annotations.iter().map(|a| a.boolean_mask(&bbox)).collect();
    let mask = threshold_votes(&masks, bbox, clevel);
    Ok(Consensus { bbox, mask, masks })
}

fn threshold_votes(masks: &[BoxMask], bbox: BBox, clevel: f64) -> BoxMask {
    let n = masks.len() as f64;
    let data = (0..bbox.len())
        .map(|v| {
            let votes = masks.iter().filter(|m| m.data[v]).count();
            votes as f64 / n >= clevel
        })
        .collect();
    BoxMask { bbox, data }
}

/// Ground truth for one nodule (one cluster of annotations).
#[derive(Debug, Clone, PartialEq)]
pub struct NoduleTruth {
    /// Indices into the annotation list the clustering ran on.
    pub annotation_indices: Vec<usize>,
    pub clevel: f64,
    /// The consensus box: union of the annotations' boxes; `consensus` and `union_mask` cover it.
    pub bbox: BBox,
    pub consensus: BoxMask,
    /// Voxels inside any of the nodule's annotations (any reader): the nodule's full drawn shape.
    pub union_mask: BoxMask,
    /// Over `bbox`, the fraction of the nodule's annotations whose mask holds each voxel: the
    /// union is where it is above 0, the consensus where it is at least `clevel`.
    pub reader_fraction: Vec<f32>,
    /// Each annotation's mask voxel count, in `annotation_indices` order.
    pub annotation_mask_voxels: Vec<usize>,
    /// Each annotation's own volume, `annotation_mask_voxels` × the consensus's voxel volume:
    /// how far the readers lie from their consensus.
    pub annotation_volumes_mm3: Vec<f64>,
    pub consensus_voxels: usize,
    /// `consensus_voxels × pixel_spacing² × slice_spacing` (median z gap, not SliceThickness).
    pub volume_mm3: f64,
    /// `(6 V / π)^(1/3)`.
    pub equivalent_diameter_mm: f64,
    /// pylidc's `Annotation.diameter` of each annotation, in `annotation_indices` order.
    pub annotation_diameters_mm: Vec<f64>,
    /// Mean of `annotation_diameters_mm`: the paper's "diam" and the guided selection's target.
    pub annotated_diameter_mm: f64,
    /// Mean `(i, j, k)` of the consensus voxels; `None` when the consensus is empty.
    pub centroid_ijk: Option<[f64; 3]>,
    /// The same in mm relative to pixel (0, 0): `x = j·ps`, `y = i·ps`, `z` = slice z at the
    /// fractional `k` (linear between slice positions).
    pub centroid_mm_xyz: Option<[f64; 3]>,
}

impl NoduleTruth {
    pub fn annotation_count(&self) -> usize {
        self.annotation_indices.len()
    }
}

/// Ground truth of the nodule made of `annotations[members]`.
pub fn nodule_truth(
    annotations: &[Annotation],
    members: &[usize],
    geometry: &ScanGeometry,
    clevel: f64,
) -> Result<NoduleTruth, GroundTruthError> {
    let chosen = members
        .iter()
        .map(|&m| annotations.get(m).ok_or(GroundTruthError::AnnotationIndex { index: m, count: annotations.len() }))
        .collect::<Result<Vec<&Annotation>, _>>()?;
    let Consensus { bbox, mask, masks } = consensus(&chosen, clevel)?;
    let reader_fraction = reader_fraction_of(&masks, bbox);
    let consensus_voxels = mask.count();
    let ps = geometry.pixel_spacing_mm;
    let voxel_mm3 = ps * ps * geometry.slice_spacing_mm();
    let volume_mm3 = consensus_voxels as f64 * voxel_mm3;
    let annotation_diameters_mm: Vec<f64> = chosen.iter().map(|a| a.diameter_mm(ps)).collect();
    let annotated_diameter_mm = annotation_diameters_mm.iter().sum::<f64>() / annotation_diameters_mm.len() as f64;
    let centroid_ijk = centroid_of(&mask);
    let centroid_mm_xyz = centroid_ijk.map(|[i, j, k]| [j * ps, i * ps, geometry.z_at_index_mm(k)]);
    Ok(NoduleTruth {
        annotation_indices: members.to_vec(),
        clevel,
        bbox,
        union_mask: BoxMask { bbox, data: reader_fraction.iter().map(|&f| f > 0.0).collect() },
        reader_fraction,
        annotation_mask_voxels: masks.iter().map(BoxMask::count).collect(),
        annotation_volumes_mm3: masks.iter().map(|m| m.count() as f64 * voxel_mm3).collect(),
        consensus: mask,
        consensus_voxels,
        volume_mm3,
        equivalent_diameter_mm: (6.0 * volume_mm3 / std::f64::consts::PI).cbrt(),
        annotation_diameters_mm,
        annotated_diameter_mm,
        centroid_ijk,
        centroid_mm_xyz,
    })
}

fn centroid_of(mask: &BoxMask) -> Option<[f64; 3]> {
    let mut sum = [0f64; 3];
    let mut n = 0usize;
    for v in mask.voxels_on() {
        for a in 0..3 {
            sum[a] += v[a] as f64;
        }
        n += 1;
    }
    (n > 0).then(|| sum.map(|s| s / n as f64))
}

fn reader_fraction_of(masks: &[BoxMask], bbox: BBox) -> Vec<f32> {
    let n = masks.len() as f64;
    (0..bbox.len()).map(|v| (masks.iter().filter(|m| m.data[v]).count() as f64 / n) as f32).collect()
}

/// The `[ingest]` knobs of the ground truth, pylidc's defaults by [`Default`].
#[derive(Debug, Clone, PartialEq)]
pub struct GroundTruthParams {
    pub clevel: f64,
    pub cluster: ClusterParams,
}

impl Default for GroundTruthParams {
    fn default() -> Self {
        Self { clevel: DEFAULT_CLEVEL, cluster: ClusterParams::default() }
    }
}

/// Which read an annotation came from: `sessions[session].reads[read]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadRef {
    pub session: usize,
    pub read: usize,
}

/// Every nodule of a scan.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanTruth {
    /// All kept reads, sessions in document order, reads in document order within each.
    pub annotations: Vec<Annotation>,
    /// Where each annotation came from, parallel to `annotations`.
    pub sources: Vec<ReadRef>,
    pub clustering: Clustering,
    /// One per cluster, in `clustering.clusters` order.
    pub nodules: Vec<NoduleTruth>,
}

impl ScanTruth {
    /// The evaluation target: the nodule with the largest consensus volume (the first on ties).
    pub fn largest(&self) -> Option<&NoduleTruth> {
        self.nodules.iter().reduce(|best, n| if n.consensus_voxels > best.consensus_voxels { n } else { best })
    }
}

/// Most voxels the nodules' bounding boxes may hold together. Each nodule keeps several masks
/// over its box (about 14 bytes a voxel), so this bounds the ground truth's memory and time
/// (about 300 MB at the limit); real LIDC nodules hold under a million.
pub const MAX_NODULE_BOX_VOXELS: usize = 20_000_000;

/// Annotations, clusters and per-nodule ground truth for a parsed message. The default
/// clustering tolerance is `slice_thickness_mm` (DICOM SliceThickness, as pylidc uses).
/// Nodules whose boxes together exceed [`MAX_NODULE_BOX_VOXELS`] are an error.
pub fn scan_truth(
    message: &ReadMessage,
    geometry: &ScanGeometry,
    slice_thickness_mm: f64,
    params: &GroundTruthParams,
) -> Result<ScanTruth, GroundTruthError> {
    let mut annotations = Vec::new();
    let mut sources = Vec::new();
    for (session, s) in message.sessions.iter().enumerate() {
        for (read, r) in s.reads.iter().enumerate() {
            annotations.push(Annotation::from_read(r, geometry)?);
            sources.push(ReadRef { session, read });
        }
    }
    let clustering = cluster_annotations(&annotations, slice_thickness_mm, &params.cluster)?;
    let box_of = |members: &Vec<usize>| members.iter().map(|&m| annotations[m].bbox()).reduce(|a, b| a.union(&b));
    let voxels = clustering.clusters.iter().filter_map(box_of).map(|b| b.len()).fold(0usize, usize::saturating_add);
    if voxels > MAX_NODULE_BOX_VOXELS {
        return Err(GroundTruthError::NodulesTooLarge { voxels, limit: MAX_NODULE_BOX_VOXELS });
    }
    let nodules = clustering
        .clusters
        .iter()
        .map(|members| nodule_truth(&annotations, members, geometry, params.clevel))
        .collect::<Result<_, _>>()?;
    Ok(ScanTruth { annotations, sources, clustering, nodules })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::annotation::tests::{geometry, square_annotation};

    #[test]
    fn consensus_two_annotations_at_half_is_their_union() {
        let a = square_annotation(&[1], 2, 2, 4);
        let b = square_annotation(&[1, 2], 4, 4, 4);
        let c = consensus(&[&a, &b], 0.5).unwrap();
        let union = c.masks[0].data.iter().zip(&c.masks[1].data).filter(|(x, y)| **x || **y).count();
        assert_eq!(c.mask.count(), union);
        let both = consensus(&[&a, &b], 1.0).unwrap();
        assert!(both.mask.count() < union);
        assert_eq!(c.bbox, BBox { min_ijk: [2, 2, 1], max_ijk: [8, 8, 2] });
        assert!(consensus(&[&a], 0.0).is_err());
    }

    #[test]
    fn the_reader_fraction_holds_the_union_and_every_consensus() {
        let g = geometry();
        // Three readers: nested squares on slice 1, the third also on slice 2.
        let anns = vec![
            square_annotation(&[1], 2, 2, 6),
            square_annotation(&[1], 3, 3, 4),
            square_annotation(&[1, 2], 4, 4, 2),
        ];
        let t = nodule_truth(&anns, &[0, 1, 2], &g, 0.5).unwrap();
        assert_eq!(t.reader_fraction.len(), t.bbox.len());
        let union: Vec<bool> = t.reader_fraction.iter().map(|&f| f > 0.0).collect();
        assert_eq!(union, t.union_mask.data);
        for clevel in [0.3, 0.5, 0.7, 1.0] {
            let at = nodule_truth(&anns, &[0, 1, 2], &g, clevel).unwrap();
            let level: Vec<bool> = t.reader_fraction.iter().map(|&f| f64::from(f) >= clevel - 1e-6).collect();
            assert_eq!(level, at.consensus.data, "clevel {clevel}");
        }
        let mut values: Vec<f32> = t.reader_fraction.clone();
        values.sort_by(f32::total_cmp);
        values.dedup();
        assert_eq!(values, [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]);
    }

    #[test]
    fn nodule_truth_numbers_and_paint() {
        let g = geometry();
        let anns = vec![square_annotation(&[1, 2], 2, 2, 4)];
        let t = nodule_truth(&anns, &[0], &g, 0.5).unwrap();
        assert_eq!(t.consensus_voxels, 24);
        assert_eq!(t.volume_mm3, 24.0 * 0.25 * 2.5);
        let diag = 8.0f64.sqrt(); // diagonal of a 4 px × 0.5 mm = 2 mm square
        assert!((t.annotated_diameter_mm - diag).abs() < 1e-12);
        assert_eq!(t.union_mask, t.consensus);
        let [ci, cj, ck] = t.centroid_ijk.unwrap();
        assert!((ck - 1.5).abs() < 1e-12 && ci > 2.0 && cj > 2.0);
        assert_eq!(t.centroid_mm_xyz.unwrap()[2], 3.75);

        let dims = [g.cols, g.rows, g.slices()];
        let mut volume = vec![0u8; dims.iter().product()];
        t.consensus.paint(&mut volume, dims, 7).unwrap();
        assert_eq!(volume.iter().filter(|&&v| v == 7).count(), 24);
        // (i = row 4, j = column 6, k = 1) → index j + cols·(i + rows·k).
        assert_eq!(volume[6 + 32 * (4 + 32)], 7);
        assert!(t.consensus.paint(&mut volume[1..], dims, 1).is_err());
    }
}
