"""tools/phantom_stats.py on a volume whose answers are known by construction: a body at −50 HU
in air, two lungs whose parenchyma rises 3 HU a cm towards the back, some voxels at −960 HU,
two straight vessels of 4 and 9 mm² cross-section, a nodule at +30 HU, and a "heart" the lungs
wrap around that is not lung."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

REPO = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("phantom_stats", REPO / "tools" / "phantom_stats.py")
phantom_stats = importlib.util.module_from_spec(spec)
spec.loader.exec_module(phantom_stats)


def write(path, array, spacing):
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    sitk.WriteImage(image, str(path))


@pytest.fixture()
def patient(tmp_path):
    hu = np.full((20, 100, 100), -1000, dtype=np.int16)  # [z, y, x], 1 mm voxels
    hu[:, 5:95, 5:95] = -50  # the body
    y = np.arange(100)[None, :, None]
    parenchyma = np.broadcast_to(-850 + 0.3 * (y - 50), hu.shape)  # 3 HU a cm along y
    lungs = np.zeros(hu.shape, bool)
    lungs[:, 10:90, 10:90] = True
    lungs[:, 30:70, 35:65] = False  # the heart, 1200 mm², which the lungs wrap around
    hu[lungs] = np.rint(parenchyma[lungs])
    hu[:, 50, 15] = -960  # 20 voxels at or below −950, mid-lung (no pull on the gradient)
    hu[:, 20:22, 15:17] = 40  # a vessel of 4 mm²
    hu[:, 40:43, 20:23] = 40  # a vessel of 9 mm²
    nodule = np.zeros(hu.shape, np.uint8)
    nodule[8:12, 75:81, 70:76] = 1
    hu[nodule > 0] = 30
    write(tmp_path / "ct_hu.mhd", hu, (1.0, 1.0, 1.0))
    write(tmp_path / "gt_mask.mhd", nodule, (1.0, 1.0, 1.0))
    truth = {"target": 0, "nodules": [{"texture_mean": 4.75}]}
    (tmp_path / "ground_truth.json").write_text(json.dumps(truth))
    return tmp_path, lungs.sum()


def test_each_figure_is_the_one_built_in(patient):
    folder, lung_voxels = patient
    s = phantom_stats.patient_stats(str(folder))
    assert s["lung_volume_ml"] == pytest.approx(lung_voxels / 1000), "vessels and the nodule count, the heart not"
    assert s["laa950_pct"] == pytest.approx(100 * 20 / lung_voxels)
    assert s["gradient_hu_per_cm"] == pytest.approx(3.0, abs=0.05)
    assert s["vessel_fraction_pct"] == pytest.approx(100 * 20 * 13 / lung_voxels)
    assert s["bv5_pct_of_vessels"] == pytest.approx(100 * 4 / 13)
    assert s["bv5_10_pct_of_vessels"] == pytest.approx(100 * 9 / 13)
    assert s["bv10_pct_of_vessels"] == 0
    assert s["nodule_core_hu"] == 30 and s["nodule_texture_mean"] == 4.75
    assert s["nodule_core_sd_hu"] == 0 and s["nodule_solid_pct"] == 100


def test_a_part_solid_nodule_shows_its_core_and_its_spread(patient):
    folder, _ = patient
    hu, spacing = phantom_stats.read(str(folder / "ct_hu.mhd"))
    hu[8:12, 75:81, 70:73] = -650  # half the nodule ground glass
    write(folder / "ct_hu.mhd", hu.astype(np.int16), spacing)
    s = phantom_stats.patient_stats(str(folder))
    assert s["nodule_solid_pct"] == 50
    # The eroded core is 2 × 4 × 4 voxels, half at each level.
    assert s["nodule_core_hu"] == pytest.approx((30 - 650) / 2) and s["nodule_core_sd_hu"] == pytest.approx(340)


def test_a_volume_without_lungs_says_so(tmp_path):
    write(tmp_path / "ct_hu.mhd", np.full((4, 10, 10), -50, np.int16), (1.0, 1.0, 1.0))
    write(tmp_path / "gt_mask.mhd", np.zeros((4, 10, 10), np.uint8), (1.0, 1.0, 1.0))
    (tmp_path / "ground_truth.json").write_text(json.dumps({"target": None, "nodules": []}))
    with pytest.raises(SystemExit, match="is it a chest CT"):
        phantom_stats.patient_stats(str(tmp_path))
