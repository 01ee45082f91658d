//! `ingest`: a patient's DICOM CT series to an int16 HU volume in patient space (SPEC §3 ingest).
//!
//! Input: the patient's files (any nesting; files that are not CT DICOM are skipped and counted),
//! optionally with its LIDC XML. Outputs: `ct_hu.mhd` + `ct_hu.raw` (int16 HU, MetaImage with
//! spacing, origin and direction), `ct_series.json` (geometry and provenance), and from the
//! annotations `ground_truth.json` + `gt_mask.mhd`/`.raw` (see [`truth`]) and `target_site.json`,
//! whether the target lies against the lung's wall (see [`site`]). No patient-identifying
//! tag reaches any of them, and no file name other than the annotation file's: the patient is
//! named only by the ID the dataset gives it, and skipped files only by how many there are (a
//! file name can carry a patient's name).

pub mod site;
pub mod truth;

use crate::artifacts::{CT_HU, CT_SERIES, GROUND_TRUTH, GT_MASK, TARGET_SITE};
use crate::engine::{Context, Output, Stage};
use crate::formats::dicom;
use anyhow::bail;
use serde::{Deserialize, Serialize};

/// 2: `ground_truth.json` gives each annotation's own volume.
/// 3: `target_site.json`: whether the target lies against the lung's wall.
/// 4: `ct_series.json` counts skipped files instead of naming them; stricter DICOM checks.
pub const VERSION: u32 = 4;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Largest allowed deviation of any slice gap from the median gap, as a fraction of it.
    pub slice_gap_tolerance: f64,
    /// Consensus level: a voxel is in a nodule's ground truth when at least this fraction of
    /// its annotations contain it (pylidc `consensus(clevel)`).
    pub clevel: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { slice_gap_tolerance: dicom::DEFAULT_GAP_TOLERANCE, clevel: 0.5 }
    }
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        if !(self.slice_gap_tolerance.is_finite() && (0.0..0.5).contains(&self.slice_gap_tolerance)) {
            bail!("[ingest] slice_gap_tolerance must be in [0, 0.5) (got {})", self.slice_gap_tolerance);
        }
        if !(self.clevel > 0.0 && self.clevel <= 1.0) {
            bail!("[ingest] clevel must be in (0, 1] (got {})", self.clevel);
        }
        Ok(())
    }
}

/// What `ct_series.json` records.
#[derive(Debug, Serialize, Deserialize)]
pub struct SeriesInfo {
    pub patient: String,
    pub geometry: crate::volume::Geometry,
    pub slice_positions_mm: Vec<f64>,
    pub slice_gap_mm: f64,
    pub slice_thickness_mm: Option<f64>,
    pub transfer_syntax: String,
    pub hu_rounding_max_abs: f64,
    pub hu_min: i16,
    pub hu_max: i16,
    /// How many files of the patient's folder are not part of the CT series. Never their names.
    pub skipped_files: SkippedFiles,
}

/// Files of the patient's folder left out of the CT series, counted by kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkippedFiles {
    /// Files that are clearly not DICOM (no `DICM` marker, not named or sized like a slice).
    pub not_dicom: usize,
    /// DICOM files that are not CT images (a scout, a structured report, …).
    pub dicom_not_ct: usize,
}

pub struct Ingest {
    pub params: Params,
    /// Where the patient's files come from: `[SOURCE]` (a DICOM dataset), or a generator stage.
    pub input: &'static [&'static str],
}

impl Stage for Ingest {
    fn name(&self) -> &'static str {
        "ingest"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        self.input
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let files = ctx.input_files(self.input[0])?;
        let paths: Vec<_> = files.iter().map(|f| f.path.clone()).collect();
        let series = dicom::read_ct_series(&paths, self.params.slice_gap_tolerance)?;
        let info = SeriesInfo {
            patient: ctx.patient().to_string(),
            geometry: series.hu.geometry.clone(),
            slice_positions_mm: series.slice_positions_mm.clone(),
            slice_gap_mm: series.slice_gap_mm,
            slice_thickness_mm: series.slice_thickness_mm,
            transfer_syntax: series.transfer_syntax.clone(),
            hu_rounding_max_abs: series.hu_rounding_max_abs,
            hu_min: series.hu.data.iter().copied().min().unwrap_or(0),
            hu_max: series.hu.data.iter().copied().max().unwrap_or(0),
            skipped_files: SkippedFiles {
                not_dicom: series.skipped_not_dicom(),
                dicom_not_ct: series.skipped.len() - series.skipped_not_dicom(),
            },
        };
        let annotations = truth::find_annotations(&files)?;
        let (ground_truth, gt_mask) = truth::ground_truth(ctx.patient(), &series, annotations, self.params.clevel)?;
        let site = site::target_site(&series.hu, gt_mask.as_ref())?;
        let mut outputs = Vec::from(super::volume_outputs(CT_HU, &series.hu));
        outputs.extend([
            Output::new(CT_SERIES.file, serde_json::to_vec_pretty(&info)?),
            Output::new(GROUND_TRUTH.file, serde_json::to_vec_pretty(&ground_truth)?),
            Output::new(TARGET_SITE.file, serde_json::to_vec_pretty(&site)?),
        ]);
        if let Some(mask) = gt_mask {
            outputs.extend(super::volume_outputs(GT_MASK, &mask));
        }
        Ok(outputs)
    }
}
