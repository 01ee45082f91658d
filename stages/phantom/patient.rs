//! One cohort patient's phantom: the real scan geometry (`<patient>.scan.json`), a synthetic
//! thorax, and the real nodules drawn where the radiologists drew them — graded by their
//! readers, or their union or consensus (pylidc-exact masks), with partial-volume edges and the
//! solid core and ground-glass halo of their texture rating — written as a CT DICOM series to be
//! read back through the real ingest path beside the original LIDC XML. The ground truth is
//! *not* taken from here: ingest recomputes it from the XML, exactly as for a real LIDC scan.

use super::{noise, phantom_ct, textured_nodule, BoxGrid, NoduleExtent, NoduleInsert, PhantomParams};
use crate::formats::dicom_writer::{write_ct_series, SeriesMeta};
use crate::formats::lidc_xml::{self, ReadMessage};
use crate::formats::png;
use crate::kernels::consensus::{scan_truth, GroundTruthParams, NoduleTruth, ScanGeometry};
use crate::kernels::mask::BoxMask;
use crate::kernels::stats::median_gap;
use crate::volume::{Geometry, Volume};
use anyhow::{anyhow, bail, Context as _};
use serde::Deserialize;
use std::path::Path;

/// What the generator reads of a `*.scan.json`: the scan's real geometry and UIDs.
#[derive(Debug, Clone, Deserialize)]
pub struct ScanInfo {
    pub patient_id: String,
    pub study_instance_uid: String,
    pub series_instance_uid: String,
    pub pixel_spacing_mm: f64,
    pub slice_thickness_mm: f64,
    pub rows: usize,
    pub cols: usize,
    /// Slice z positions, ascending.
    pub zvals_mm: Vec<f64>,
    /// SOPInstanceUID of each slice, in `zvals_mm` order.
    #[serde(default)]
    pub sop_uids: Vec<String>,
}

impl ScanInfo {
    pub fn parse(text: &str, name: &str) -> anyhow::Result<ScanInfo> {
        let scan: ScanInfo = serde_json::from_str(text).with_context(|| format!("{name} is not a scan description"))?;
        if scan.zvals_mm.len() < 2 || scan.zvals_mm.windows(2).any(|w| w[1] <= w[0]) {
            bail!("{name}: zvals_mm must hold at least two ascending slice positions");
        }
        if !scan.sop_uids.is_empty() && scan.sop_uids.len() != scan.zvals_mm.len() {
            bail!("{name}: {} sop_uids for {} slices", scan.sop_uids.len(), scan.zvals_mm.len());
        }
        Ok(scan)
    }

    /// The CT grid: `rows × cols` pixels centred on the scanner axis (LIDC scans put
    /// ImagePositionPatient x, y near −FOV/2; the database has no exact origin), axial slices at
    /// the real z positions, slice spacing their median gap.
    pub fn geometry(&self) -> Geometry {
        let ps = self.pixel_spacing_mm;
        Geometry {
            dims: [self.cols, self.rows, self.zvals_mm.len()],
            spacing_mm: [ps, ps, median_gap(&self.zvals_mm)],
            origin_mm: [-(self.cols as f64) / 2.0 * ps, -(self.rows as f64) / 2.0 * ps, self.zvals_mm[0]],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }
}

/// A generated patient: the HU volume, its DICOM files, the annotations, and PNG previews.
pub struct PatientPhantom {
    pub ct: Volume<f32>,
    /// `(file name, bytes)` per slice.
    pub series: Vec<(String, Vec<u8>)>,
    /// `(file name, text)` of the LIDC XML the nodules come from, to travel with the series.
    pub annotations: (String, String),
    /// `(file name, PNG bytes)`: axial and coronal slices through the largest nodule, and a
    /// coronal projection.
    pub previews: Vec<(String, Vec<u8>)>,
}

/// Builds the phantom of the patient described by `scan_path` (`<id>.scan.json`) and
/// `xml_path` (its LIDC XML).
pub fn generate_from_files(
    scan_path: &Path,
    xml_path: &Path,
    params: &PhantomParams,
) -> anyhow::Result<PatientPhantom> {
    let name = |p: &Path| p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    let scan_text = std::fs::read_to_string(scan_path).with_context(|| format!("reading {}", scan_path.display()))?;
    let scan = ScanInfo::parse(&scan_text, &name(scan_path))?;
    let annotations = lidc_xml::read(xml_path).map_err(|e| anyhow!("{}: {e}", xml_path.display()))?;
    let xml = std::fs::read_to_string(xml_path).with_context(|| format!("reading {}", xml_path.display()))?;
    generate(&scan, &annotations, (name(xml_path), xml), params)
}

/// Builds the phantom of one patient. `params.seed` is combined with the patient ID, so every
/// patient of a cohort gets its own anatomy while the whole cohort stays reproducible.
pub fn generate(
    scan: &ScanInfo,
    annotations: &ReadMessage,
    xml: (String, String),
    params: &PhantomParams,
) -> anyhow::Result<PatientPhantom> {
    if scan.zvals_mm.windows(2).any(|w| ((w[1] - w[0]) - (scan.zvals_mm[1] - scan.zvals_mm[0])).abs() > 1e-3) {
        bail!("{}: the phantom needs evenly spaced slices", scan.patient_id);
    }
    let geometry = scan.geometry();
    let params = PhantomParams { seed: patient_seed(params.seed, &scan.patient_id), ..params.clone() };
    let lidc = ScanGeometry::new(scan.zvals_mm.clone(), scan.pixel_spacing_mm, scan.rows, scan.cols)?;
    let truth = scan_truth(annotations, &lidc, scan.slice_thickness_mm, &GroundTruthParams::default())
        .map_err(|e| anyhow!("{}: {e}", scan.patient_id))?;
    let inserts: Vec<NoduleInsert> = truth
        .nodules
        .iter()
        .enumerate()
        .map(|(index, n)| {
            let textures = n.annotation_indices.iter().map(|&a| {
                let r = &truth.sources[a];
                annotations.sessions[r.session].reads[r.read].characteristics.texture
            });
            let seed = noise::stream_seed(params.seed, "nodule", index as u64);
            nodule_insert(n, median_rating(textures.collect()), params.nodule_extent, &geometry, seed)
        })
        .collect();
    let ct = phantom_ct(&geometry, &params, &inserts);
    let meta = SeriesMeta {
        patient_id: scan.patient_id.clone(),
        study_instance_uid: scan.study_instance_uid.clone(),
        series_instance_uid: scan.series_instance_uid.clone(),
        sop_instance_uids: scan.sop_uids.clone(),
        slice_thickness_mm: Some(scan.slice_thickness_mm),
        series_description: "aret-pipe synthetic thorax around real LIDC-IDRI annotations".into(),
    };
    let series = write_ct_series(&ct, &meta)?;
    let centre = truth.largest().and_then(|n| n.centroid_ijk);
    let previews = previews(&ct, centre);
    Ok(PatientPhantom { ct, series, annotations: xml, previews })
}

/// The drawn shape of a nodule with the tissue of its texture rating: the union of all its
/// readers' masks, each voxel at the fraction of readers who drew it, or their 50 % consensus
/// (`extent`); its internal texture is drawn from `seed`.
fn nodule_insert(
    nodule: &NoduleTruth,
    texture: Option<u8>,
    extent: NoduleExtent,
    geometry: &Geometry,
    seed: u64,
) -> NoduleInsert {
    // Every mask of a nodule covers its consensus box, so one origin serves them all.
    let [i0, j0, k0] = nodule.bbox.min_ijk;
    let [i1, j1, k1] = nodule.bbox.max_ijk;
    // BoxMask is [k][i][j] (slice, row, column), as BoxGrid: only the axis names differ.
    let origin = [j0 as i64, i0 as i64, k0 as i64];
    let dims = [j1 - j0 + 1, i1 - i0 + 1, k1 - k0 + 1];
    let binary = |mask: &BoxMask| {
        debug_assert_eq!(mask.bbox, nodule.bbox);
        BoxGrid { origin, dims, data: mask.data.clone() }.as_fraction()
    };
    let fraction = match extent {
        NoduleExtent::Union => binary(&nodule.union_mask),
        NoduleExtent::Consensus => binary(&nodule.consensus),
        NoduleExtent::Readers => BoxGrid { origin, dims, data: nodule.reader_fraction.clone() },
    };
    textured_nodule(&fraction, texture, geometry.spacing_mm, seed)
}

/// The median of the readers' ratings (the lower middle one for an even count).
fn median_rating(mut ratings: Vec<u8>) -> Option<u8> {
    ratings.sort_unstable();
    ratings.get(ratings.len().saturating_sub(1) / 2).copied()
}

fn patient_seed(seed: u64, patient: &str) -> u64 {
    let hash = blake3::hash(format!("{seed}/{patient}").as_bytes());
    u64::from_le_bytes(hash.as_bytes()[..8].try_into().expect("8 bytes"))
}

/// Axial (lung window) and coronal slices through `centre_ijk` (row, column, slice), or the
/// volume's middle, and the coronal projection.
fn previews(ct: &Volume<f32>, centre_ijk: Option<[f64; 3]>) -> Vec<(String, Vec<u8>)> {
    let [cols, rows, slices] = ct.geometry.dims;
    let [row, _col, k] = centre_ijk.unwrap_or([rows as f64 / 2.0, cols as f64 / 2.0, slices as f64 / 2.0]);
    let axial = png::axial_slice(ct, (k.round() as usize).min(slices - 1));
    let coronal = png::coronal_slice(ct, (row.round() as usize).min(rows - 1));
    let projection = png::coronal_projection(ct);
    vec![
        ("phantom_axial.png".into(), png::image_png(&axial, png::LUNG_WINDOW)),
        ("phantom_coronal.png".into(), png::image_png(&coronal, png::LUNG_WINDOW)),
        ("phantom_projection.png".into(), png::image_png(&projection, png::Window::spanning(&projection))),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::annotation::tests::{geometry, square_annotation};
    use crate::kernels::consensus::nodule_truth;

    #[test]
    fn each_extent_draws_the_tissue_it_names() {
        // Three nested readers; only the smallest also drew the next slice.
        let anns = vec![
            square_annotation(&[1], 2, 2, 6),
            square_annotation(&[1], 3, 3, 4),
            square_annotation(&[1, 2], 4, 4, 2),
        ];
        let truth = nodule_truth(&anns, &[0, 1, 2], &geometry(), 0.5).unwrap();
        let ct = Geometry {
            dims: [32, 32, 5],
            spacing_mm: [0.5, 0.5, 2.5],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let tissue = |extent| {
            nodule_insert(&truth, Some(5), extent, &ct, 7).occupancy.data.iter().map(|&v| f64::from(v)).sum::<f64>()
        };
        // The blur keeps the sum, so each extent's tissue is its own shape's voxel count.
        let union = truth.union_mask.count() as f64;
        let consensus = truth.consensus.count() as f64;
        let readers: f64 = truth.reader_fraction.iter().map(|&f| f64::from(f)).sum();
        assert!(consensus < readers && readers < union, "{consensus} {readers} {union}");
        for (extent, voxels) in
            [(NoduleExtent::Union, union), (NoduleExtent::Consensus, consensus), (NoduleExtent::Readers, readers)]
        {
            assert!((tissue(extent) - voxels).abs() < 1e-3 * voxels, "{extent:?}: {} against {voxels}", tissue(extent));
        }
    }
}
