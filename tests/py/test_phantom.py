"""The phantom cohort through independent readers.

`aret-pipe phantom` writes a patient's synthetic CT series; pydicom must read it back as a CT
series with the patient's real geometry and UIDs, and to the same HU our own ingest reads from
the series the pipeline generates into its cache (same seed, same bytes). The ground truth the
pipeline then computes from the XML must be pylidc's (the scan.json `reference` block), and
where ingest says the target lies (`target_site.json`) must be scipy's reading of the same CT.
"""
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from scipy import ndimage as ndi

REPO = Path(__file__).resolve().parents[2]
COHORT = REPO / "tools" / "cohorts" / "paper19"
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
PATIENT = "LIDC-IDRI-0001"


def aret(*args, cwd):
    proc = subprocess.run([BIN, *args], cwd=cwd, capture_output=True, text=True, env={**os.environ, "CI": "true"})
    assert proc.returncode == 0, f"aret-pipe {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """One patient written by `aret-pipe phantom --config`, and that configuration's pipeline run
    on it: another anatomy and nodule extent than the built-in ones, so an export that ignored
    the configuration would differ."""
    tmp = tmp_path_factory.mktemp("phantom")
    (tmp / "pipeline.toml").write_text(
        f'[pipeline]\nname = "phantom-check"\n[dataset]\nkind = "phantom"\ncohort = "{COHORT}"\n'
        '[dataset.phantom]\nseed = 3\nnodule_extent = "union"\n'
    )
    aret("phantom", "--config", "pipeline.toml", "--out", str(tmp / "export"), "--patients", PATIENT, cwd=tmp)
    aret("run", "pipeline.toml", "--until", "ingest", "--patients", PATIENT, cwd=tmp)
    return tmp


def read_series(folder: Path):
    datasets = [pydicom.dcmread(f) for f in sorted(folder.glob("*.dcm"))]
    datasets.sort(key=lambda d: float(d.ImagePositionPatient[2]))
    return datasets


def test_pydicom_reads_a_ct_series_with_the_real_geometry(generated):
    scan = json.loads((COHORT / f"{PATIENT}.scan.json").read_text())
    datasets = read_series(generated / "export" / PATIENT / "series")
    assert len(datasets) == scan["num_slices"] == len(scan["zvals_mm"])
    for d, z, uid in zip(datasets, scan["zvals_mm"], scan["sop_uids"]):
        assert d.SOPClassUID == "1.2.840.10008.5.1.4.1.1.2"  # CT Image Storage
        assert d.Modality == "CT" and d.PhotometricInterpretation == "MONOCHROME2"
        assert (d.Rows, d.Columns) == (scan["rows"], scan["cols"]) == (512, 512)
        assert d.BitsAllocated == 16 and d.PixelRepresentation == 1
        assert d.PatientPosition == "HFS"
        assert float(d.ImagePositionPatient[2]) == pytest.approx(z, abs=1e-6)
        assert [float(v) for v in d.PixelSpacing] == pytest.approx([scan["pixel_spacing_mm"]] * 2)
        assert d.SOPInstanceUID == uid
        assert d.SeriesInstanceUID == scan["series_instance_uid"]
        assert d.StudyInstanceUID == scan["study_instance_uid"]
        assert str(d.PatientID) == PATIENT  # the pseudonymous ID, nothing else
    assert (generated / "export" / PATIENT / f"{PATIENT}.xml").read_bytes() == (COHORT / f"{PATIENT}.xml").read_bytes()


def test_pydicom_hu_equals_the_pipelines_ingest(generated):
    datasets = read_series(generated / "export" / PATIENT / "series")
    hu = np.stack([pydicom.pixels.apply_modality_lut(d.pixel_array, d) for d in datasets])
    ours = sitk.GetArrayFromImage(sitk.ReadImage(str(generated / "out" / PATIENT / "ct_hu.mhd")))
    assert ours.dtype == np.int16 and ours.shape == hu.shape
    np.testing.assert_array_equal(ours, hu.astype(np.int16))
    # A thorax, not noise: air outside, lungs near -850 HU, soft tissue and bone present.
    assert np.median(hu[:, :20, :]) < -900
    assert (hu > 300).mean() > 0.003 and ((hu > -100) & (hu < 100)).mean() > 0.1


def test_ground_truth_from_the_phantom_is_pylidcs(generated):
    scan = json.loads((COHORT / f"{PATIENT}.scan.json").read_text())
    ref = scan["reference"]
    truth = json.loads((generated / "out" / PATIENT / "ground_truth.json").read_text())
    assert len(truth["nodules"]) == len(ref["clusters"])
    for ours, theirs in zip(truth["nodules"], ref["clusters"]):
        assert ours["consensus_voxels"] == theirs["consensus_voxels"]
        assert ours["volume_mm3"] == pytest.approx(theirs["consensus_volume_mm3"], rel=1e-3)
        assert ours["annotated_diameter_mm"] == pytest.approx(theirs["mean_annotated_diameter_mm"], abs=1e-3)
    assert truth["target"] == ref["largest_cluster_index"]
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(generated / "out" / PATIENT / "gt_mask.mhd")))
    assert int(mask.sum()) == ref["clusters"][ref["largest_cluster_index"]]["consensus_voxels"]
    # The nodule is in the CT where the radiologists drew it: solid tissue inside the mask.
    hu = sitk.GetArrayFromImage(sitk.ReadImage(str(generated / "out" / PATIENT / "ct_hu.mhd")))
    assert np.median(hu[mask == 1]) > -300


def test_previews_are_published(generated):
    for name in ("phantom_axial.png", "phantom_coronal.png", "phantom_projection.png"):
        data = (generated / "out" / PATIENT / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"


def filled_lung_field(hu):
    """Per axial slice, air below -400 HU not 4-connected to the border; holes then filled in every
    slice across z, y and x (numpy axes 0, 1, 2)."""
    low = hu < -400
    field = np.zeros_like(low)
    for k, slice_ in enumerate(low):
        labels, _ = ndi.label(slice_)
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        field[k] = slice_ & ~np.isin(labels, border)
    for axis in range(3):
        field = np.moveaxis(np.stack([ndi.binary_fill_holes(s) for s in np.moveaxis(field, axis, 0)]), 0, axis)
    return field


def test_target_site_is_scipys(generated):
    """LIDC-IDRI-0001's nodule lies against the spine: part of it is outside the lung field."""
    site = json.loads((generated / "out" / PATIENT / "target_site.json").read_text())
    hu = sitk.GetArrayFromImage(sitk.ReadImage(str(generated / "out" / PATIENT / "ct_hu.mhd")))
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(generated / "out" / PATIENT / "gt_mask.mhd"))) > 0
    outside = 1.0 - filled_lung_field(hu)[mask].mean()
    assert site["lung_threshold_hu"] == -400
    assert site["outside_lung_fraction"] == pytest.approx(outside, abs=1e-12)
    assert 0.1 < outside < 0.5 and site["attached"] is True
