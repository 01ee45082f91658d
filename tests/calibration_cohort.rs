//! The sizing calibration's cohort (`tools/cohorts/spheres16/`, written by
//! `lab/scripts/sphere_cohort.py`): every patient's annotations, read through the real LIDC XML and
//! consensus path, are the one sphere its scan description says was drawn — four identical
//! reads, a consensus equal to their union, the stated diameter and centre — so a volume
//! measured on it is scored against a sphere of known size.

mod support;

use std::path::PathBuf;
use support::cohort::{load_patient, CohortPatient};

fn cohort_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tools/cohorts/spheres16")
}

#[test]
fn each_calibration_patient_holds_the_sphere_it_states() {
    let mut checked = 0;
    for entry in std::fs::read_dir(cohort_dir()).unwrap() {
        let path = entry.unwrap().path();
        let Some(id) = path.file_name().unwrap().to_str().unwrap().strip_suffix(".scan.json") else {
            continue;
        };
        let CohortPatient { scan, truth, .. } = load_patient(&cohort_dir(), id);
        let ps = scan["pixel_spacing_mm"].as_f64().unwrap();
        let cols = scan["cols"].as_u64().unwrap() as usize;
        let thickness = scan["slice_thickness_mm"].as_f64().unwrap();

        assert_eq!(truth.nodules.len(), 1, "{id}: one nodule");
        let nodule = &truth.nodules[0];
        assert_eq!(nodule.annotation_count(), 4, "{id}: four reads");
        assert_eq!(nodule.consensus_voxels, nodule.union_mask.count(), "{id}: identical reads");

        let stated = scan["sphere"]["diameter_mm"].as_f64().unwrap();
        // A voxelised sphere's volume is the sphere's to within its surface's partial voxels.
        let tolerance_mm = 0.5 * thickness.max(ps);
        assert!(
            (nodule.equivalent_diameter_mm - stated).abs() <= tolerance_mm,
            "{id}: equivalent diameter {:.2} mm, stated {stated} mm",
            nodule.equivalent_diameter_mm
        );
        let centre = scan["sphere"]["centre_mm"].as_array().unwrap();
        let found = nodule.centroid_mm_xyz.unwrap();
        // pylidc's mm are measured from pixel (0, 0); the phantom's scanner axis is the image centre.
        let half_fov = cols as f64 / 2.0 * ps;
        let found = [found[0] - half_fov, found[1] - half_fov, found[2]];
        for axis in 0..3 {
            let stated = centre[axis].as_f64().unwrap();
            assert!(
                (found[axis] - stated).abs() <= thickness.max(ps),
                "{id}: centroid {found:?} mm, stated {centre:?}"
            );
        }
        checked += 1;
    }
    assert_eq!(checked, 16);
}
