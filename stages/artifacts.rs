//! The name of every artifact one stage writes and another reads or a user opens: one constant
//! each, so that the writer and its readers name the same file, and a misspelling does not
//! compile. The stage is the one that writes it.

/// One file a stage writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Artifact {
    pub stage: &'static str,
    pub file: &'static str,
}

/// A MetaImage volume a stage writes: its header `<name>.mhd` and its data `<name>.raw`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VolumeArtifact {
    pub stage: &'static str,
    pub name: &'static str,
    pub header: &'static str,
    pub raw: &'static str,
}

impl VolumeArtifact {
    /// Whether `file` is the header or the data.
    pub fn holds(self, file: &str) -> bool {
        file == self.header || file == self.raw
    }
}

macro_rules! artifact {
    ($stage:literal, $file:literal) => {
        Artifact { stage: $stage, file: $file }
    };
}

macro_rules! volume {
    ($stage:literal, $name:literal) => {
        VolumeArtifact { stage: $stage, name: $name, header: concat!($name, ".mhd"), raw: concat!($name, ".raw") }
    };
}

/// The CT in HU (int16), as read from the series.
pub const CT_HU: VolumeArtifact = volume!("ingest", "ct_hu");
/// What the series was and what was skipped (no patient attributes).
pub const CT_SERIES: Artifact = artifact!("ingest", "ct_series.json");
/// Every nodule's consensus and numbers, and which one is the target.
pub const GROUND_TRUTH: Artifact = artifact!("ingest", "ground_truth.json");
/// The target's consensus mask (uint8), on the CT's grid.
pub const GT_MASK: VolumeArtifact = volume!("ingest", "gt_mask");
/// Whether the target lies against the lung's wall.
pub const TARGET_SITE: Artifact = artifact!("ingest", "target_site.json");

/// The CT windowed to [0, 1].
pub const CT_UNIT: VolumeArtifact = volume!("hu", "ct_unit");

/// The cameras that rendered the views, and the scene frame.
pub const CAMERAS: Artifact = artifact!("drr", "cameras.json");

/// The DRR of one view (`coronal`, `sagittal`, `axial`), I/I0 per pixel, as OpenEXR.
pub fn drr_image(view: &str) -> String {
    format!("drr_{view}.exr")
}

/// Whether `file` is a view's DRR ([`drr_image`]).
pub fn is_drr_image(file: &str) -> bool {
    file.starts_with("drr_") && file.ends_with(".exr")
}

/// Its 8-bit preview.
pub fn drr_preview(view: &str) -> String {
    format!("drr_{view}.png")
}

/// The coronal view's preview, shown in the report.
pub const DRR_CORONAL_PREVIEW: Artifact = artifact!("drr", "drr_coronal.png");

/// The fitted field and its metadata.
pub const MODEL: Artifact = artifact!("train", "model.safetensors");
/// The fit's log, a row per logged step.
pub const TRAIN_LOG: Artifact = artifact!("train", "train_log.csv");
/// The fit's loss curves.
pub const LOSS_PLOT: Artifact = artifact!("train", "loss.svg");

/// σ in patient mm.
pub const DENSITY: VolumeArtifact = volume!("grid", "density");
/// |∇σ| scaled to [0, 1].
pub const UNCERTAINTY: VolumeArtifact = volume!("grid", "uncertainty");
/// Density and uncertainty as OpenVDB grids.
pub const DENSITY_VDB: Artifact = artifact!("grid", "density.vdb");

/// The sweep's candidates as a table.
pub const SWEEP_CSV: Artifact = artifact!("sweep", "sweep.csv");
/// The sweep's candidates and the parameters that made them.
pub const SWEEP: Artifact = artifact!("sweep", "sweep.json");
/// The lung field found in σ (uint8), where the sweep looked.
pub const LUNG_FIELD: VolumeArtifact = volume!("sweep", "lung_field");

/// The bright blobs of σ each blob search chooses among.
pub const BLOBS: Artifact = artifact!("blobs", "blobs.json");

/// Every rule's selection, its localization and the verdict.
pub const RESULT: Artifact = artifact!("select", "result.json");
/// The primary selection's mask (uint8).
pub const NODULE_MASK: VolumeArtifact = volume!("select", "nodule_mask");
/// The primary selection's surface.
pub const NODULE_MESH: Artifact = artifact!("select", "nodule.obj");
/// Slices through the selection, the nodule and a rival.
pub const NODULE_PREVIEW: Artifact = artifact!("select", "nodule.png");
/// The fitted ellipsoid over its shadows (`sizing = "shadows"`).
pub const SHADOWS_PREVIEW: Artifact = artifact!("select", "shadows.png");

/// One row per patient.
pub const RESULTS_CSV: Artifact = artifact!("metrics", "results.csv");
/// The cohort's statistics.
pub const SUMMARY: Artifact = artifact!("metrics", "summary.json");
/// Predicted against true volume.
pub const SCATTER_PLOT: Artifact = artifact!("metrics", "scatter.svg");
/// The Bland–Altman plot.
pub const BLAND_ALTMAN_PLOT: Artifact = artifact!("metrics", "bland_altman.svg");
/// The cohort's report.
pub const REPORT: Artifact = artifact!("metrics", "report.html");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_artifact_belongs_to_a_stage() {
        let files = [CT_SERIES, GROUND_TRUTH, TARGET_SITE, CAMERAS, MODEL, BLOBS, RESULT, SUMMARY, REPORT];
        let volumes = [CT_HU, GT_MASK, CT_UNIT, DENSITY, UNCERTAINTY, LUNG_FIELD, NODULE_MASK];
        let stages = files.iter().map(|a| a.stage).chain(volumes.iter().map(|v| v.stage));
        for stage in stages {
            assert!(crate::stage::STAGE_NAMES.contains(&stage), "{stage}");
        }
        assert_eq!((CT_HU.header, CT_HU.raw), ("ct_hu.mhd", "ct_hu.raw"));
        assert!(DENSITY.holds("density.raw") && !DENSITY.holds("density.vdb"));
        assert_eq!(DRR_CORONAL_PREVIEW.file, drr_preview("coronal"));
        assert!(is_drr_image(&drr_image("axial")) && !is_drr_image(&drr_preview("axial")));
    }
}
