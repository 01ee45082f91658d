//! Reads one patient of a committed cohort folder (`<id>.scan.json` + `<id>.xml`, the layout of
//! `tools/cohorts/`) through the real LIDC XML reader and consensus kernels.
#![allow(dead_code)] // shared by several test crates; each uses a subset

use aret_pipe::formats::lidc_xml;
use aret_pipe::kernels::consensus::{scan_truth, GroundTruthParams, ScanGeometry, ScanTruth};
use serde_json::Value;
use std::path::Path;

/// A cohort patient: its scan description as written, its geometry and its ground truth.
pub struct CohortPatient {
    pub scan: Value,
    pub geometry: ScanGeometry,
    pub truth: ScanTruth,
}

pub fn load_patient(dir: &Path, id: &str) -> CohortPatient {
    let xml = std::fs::read_to_string(dir.join(format!("{id}.xml"))).unwrap();
    let scan: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{id}.scan.json"))).unwrap()).unwrap();
    let message = lidc_xml::parse(&xml).unwrap_or_else(|e| panic!("{id}: {e}"));
    let geometry = ScanGeometry::new(
        scan["zvals_mm"].as_array().unwrap().iter().map(|z| z.as_f64().unwrap()).collect(),
        scan["pixel_spacing_mm"].as_f64().unwrap(),
        scan["rows"].as_u64().unwrap() as usize,
        scan["cols"].as_u64().unwrap() as usize,
    )
    .unwrap();
    let thickness = scan["slice_thickness_mm"].as_f64().unwrap();
    let truth = scan_truth(&message, &geometry, thickness, &GroundTruthParams::default())
        .unwrap_or_else(|e| panic!("{id}: {e}"));
    CohortPatient { scan, geometry, truth }
}
