//! Ground truth from the radiologists' LIDC XML: nodules by pylidc's clustering, each with its
//! consensus mask at `clevel`, volume and diameters; the target is the largest nodule by
//! consensus volume (SPEC §3 ingest, Annotations). Written as `ground_truth.json` and
//! `gt_mask.mhd` + `.raw` (uint8, 1 inside the target's consensus, on the CT's own grid).

use crate::engine::InputFile;
use crate::formats::dicom::CtSeries;
use crate::formats::lidc_xml::{self, LidcError};
use crate::kernels::consensus::{scan_truth, ClusterParams, GroundTruthParams, NoduleTruth, ScanGeometry};
use crate::volume::{Geometry, Volume};
use anyhow::{anyhow, bail, Context as _};
use serde::{Deserialize, Serialize};

/// What `ground_truth.json` holds.
#[derive(Debug, Serialize, Deserialize)]
pub struct GroundTruth {
    pub patient: String,
    /// The annotation file read (its name among the patient's files); `None`: no annotations.
    pub annotations_file: Option<String>,
    pub clevel: f64,
    pub reading_sessions: usize,
    /// Reads used for volumetry, and those read but left out (as pylidc leaves them out).
    pub reads_used: usize,
    pub small_nodule_reads: usize,
    pub unrated_reads: usize,
    pub non_nodule_marks: usize,
    pub nodules: Vec<Nodule>,
    /// Index into `nodules` of the evaluation target: the largest by consensus volume.
    pub target: Option<usize>,
}

/// One nodule (a cluster of reads by different radiologists).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Nodule {
    pub annotation_count: usize,
    /// Reader (reading session, 1-based) and `noduleID` of each annotation.
    pub reads: Vec<(usize, String)>,
    pub consensus_voxels: usize,
    pub volume_mm3: f64,
    pub equivalent_diameter_mm: f64,
    /// Mean over the annotations of pylidc's `Annotation.diameter` (the guided rule's target).
    pub annotated_diameter_mm: f64,
    pub annotation_diameters_mm: Vec<f64>,
    /// Each annotation's own volume (its mask's voxels × the voxel volume), in `reads` order.
    pub annotation_volumes_mm3: Vec<f64>,
    /// Inclusive voxel box `[[col min, row min, slice min], [col max, row max, slice max]]`.
    pub bbox_voxels: [[usize; 3]; 2],
    /// Consensus centroid in patient LPS mm (`None` if the consensus is empty).
    pub centroid_mm: Option<[f64; 3]>,
    /// Mean of the readers' texture ratings (1 ground-glass … 5 solid).
    pub texture_mean: f64,
}

/// The patient's LIDC XML among `files`, if any: files whose root is `LidcReadMessage`.
/// Other XML (e.g. the chest-radiograph reads TCIA ships beside a CR series) is ignored.
pub fn find_annotations(files: &[InputFile]) -> anyhow::Result<Option<(String, lidc_xml::ReadMessage)>> {
    let mut found = Vec::new();
    for f in files.iter().filter(|f| f.name.to_ascii_lowercase().ends_with(".xml")) {
        match lidc_xml::read(&f.path) {
            Ok(message) => found.push((f.name.clone(), message)),
            Err(LidcError::WrongRoot { .. }) => continue,
            Err(e) => bail!("{}: {e}", f.name),
        }
    }
    match found.len() {
        0 | 1 => Ok(found.pop()),
        _ => {
            let names: Vec<&str> = found.iter().map(|(n, _)| n.as_str()).collect();
            bail!("more than one LIDC annotation file ({}): keep one per patient folder", names.join(", "))
        }
    }
}

/// Ground truth of `series` from `annotations` (name, parsed XML), and the target's mask.
pub fn ground_truth(
    patient: &str,
    series: &CtSeries,
    annotations: Option<(String, lidc_xml::ReadMessage)>,
    clevel: f64,
) -> anyhow::Result<(GroundTruth, Option<Volume<u8>>)> {
    let mut truth = GroundTruth {
        patient: patient.to_string(),
        annotations_file: None,
        clevel,
        reading_sessions: 0,
        reads_used: 0,
        small_nodule_reads: 0,
        unrated_reads: 0,
        non_nodule_marks: 0,
        nodules: vec![],
        target: None,
    };
    let Some((name, message)) = annotations else {
        return Ok((truth, None));
    };
    let g = &series.hu.geometry;
    let scan = scan_geometry(g).with_context(|| format!("{name}: the CT series cannot carry LIDC annotations"))?;
    let slice_thickness = series.slice_thickness_mm.unwrap_or(series.slice_gap_mm);
    let params = GroundTruthParams { clevel, cluster: ClusterParams::default() };
    let computed = scan_truth(&message, &scan, slice_thickness, &params).map_err(|e| anyhow!("{name}: {e}"))?;
    truth.annotations_file = Some(name);
    truth.reading_sessions = message.sessions.len();
    for s in &message.sessions {
        truth.reads_used += s.reads.len();
        truth.small_nodule_reads += s.small_nodules;
        truth.unrated_reads += s.unrated_reads;
        truth.non_nodule_marks += s.non_nodules;
    }
    for n in &computed.nodules {
        let reads: Vec<(usize, String)> = n
            .annotation_indices
            .iter()
            .map(|&a| {
                let r = &computed.sources[a];
                (r.session + 1, message.sessions[r.session].reads[r.read].nodule_id.clone())
            })
            .collect();
        let textures: Vec<f64> = n
            .annotation_indices
            .iter()
            .map(|&a| {
                let r = &computed.sources[a];
                f64::from(message.sessions[r.session].reads[r.read].characteristics.texture)
            })
            .collect();
        truth.nodules.push(nodule(n, g, reads, textures.iter().sum::<f64>() / textures.len() as f64));
    }
    let target = computed.largest();
    truth.target = target.and_then(|t| computed.nodules.iter().position(|n| std::ptr::eq(n, t)));
    let mask = match target {
        None => None,
        Some(t) => {
            let mut data = vec![0u8; g.len()];
            t.consensus.paint(&mut data, g.dims, 1)?;
            Some(Volume { geometry: g.clone(), data })
        }
    };
    Ok((truth, mask))
}

/// pylidc's view of the scan: ascending slice z, one in-plane spacing, rows × cols.
fn scan_geometry(g: &Geometry) -> anyhow::Result<ScanGeometry> {
    let axial = g.direction[0][0] > 0.9999 && g.direction[1][1] > 0.9999 && g.direction[2][2] > 0.9999;
    if !axial {
        bail!("LIDC annotations address axial slices by z; this series is oriented {:?}", g.direction);
    }
    if (g.spacing_mm[0] - g.spacing_mm[1]).abs() > 1e-6 * g.spacing_mm[0] {
        bail!("LIDC annotations assume square pixels; PixelSpacing is {} × {} mm", g.spacing_mm[1], g.spacing_mm[0]);
    }
    let z: Vec<f64> = (0..g.dims[2]).map(|k| g.voxel_to_patient_mm([0.0, 0.0, k as f64])[2]).collect();
    Ok(ScanGeometry::new(z, g.spacing_mm[0], g.dims[1], g.dims[0])?)
}

fn nodule(n: &NoduleTruth, g: &Geometry, reads: Vec<(usize, String)>, texture_mean: f64) -> Nodule {
    let [i0, j0, k0] = n.bbox.min_ijk;
    let [i1, j1, k1] = n.bbox.max_ijk;
    Nodule {
        annotation_count: n.annotation_indices.len(),
        reads,
        consensus_voxels: n.consensus_voxels,
        volume_mm3: n.volume_mm3,
        equivalent_diameter_mm: n.equivalent_diameter_mm,
        annotated_diameter_mm: n.annotated_diameter_mm,
        annotation_diameters_mm: n.annotation_diameters_mm.clone(),
        annotation_volumes_mm3: n.annotation_volumes_mm3.clone(),
        bbox_voxels: [[j0, i0, k0], [j1, i1, k1]],
        centroid_mm: n.centroid_ijk.map(|[i, j, k]| g.voxel_to_patient_mm([j, i, k])),
        texture_mean,
    }
}
