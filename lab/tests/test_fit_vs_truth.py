"""lab/scripts/fit_vs_truth.py tells a fit that loses the nodule's contrast from one that makes
decoys."""
import sys
from pathlib import Path

import numpy as np

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
sys.path.insert(0, str(SCRIPTS))  # the scripts import their shared metaimage and blob_ceiling
import fit_vs_truth  # noqa: E402

SPACING = np.array([1.5, 1.5, 1.5])
SHAPE = (40, 40, 40)


def ball(centre_mm, radius_mm):
    z, y, x = np.indices(SHAPE)
    nodes = np.stack([x, y, z], -1) * SPACING - SPACING * 20
    return np.linalg.norm(nodes - np.array(centre_mm), axis=-1) <= radius_mm


NODULE, JUNCTION, STREAK = ([-11.0, 0.0, 0.0], 5.0), ([11.0, 0.0, 0.0], 5.0), ([0.0, 11.0, 0.0], 5.0)


def field(nodule_value, junction_value, streak_value=0.0):
    """Lung at 0.1 with a nodule, a vessel junction and an optional blob at three places."""
    v = np.full(SHAPE, 0.1)
    for (centre, radius), value in ((NODULE, nodule_value), (JUNCTION, junction_value), (STREAK, streak_value)):
        if value:
            v[ball(centre, radius)] = value
    return v


def test_a_fit_that_halves_the_nodule_keeps_half_its_contrast_and_loses_it_to_real_anatomy():
    truth, fit = field(0.6, 0.5), field(0.35, 0.5)
    lungs = np.ones(SHAPE, bool)
    r = fit_vs_truth.compare(fit, truth, ball(*NODULE), lungs, SPACING)
    assert abs(r["fit_contrast"] - 0.25) < 1e-9 and abs(r["truth_contrast"] - 0.5) < 1e-9
    assert abs(r["kept"] - 0.5) < 1e-9
    assert r["truth_margin"] > 1, "on the truth the nodule answers the most"
    assert r["fit_margin"] < 1, "on the fit the junction does"
    assert 0 < r["response_kept"] < 1
    assert r["decoy_kind"] == "anatomy" and r["reachable"]


def test_a_blob_the_truth_lacks_is_an_artefact_and_a_nodule_outside_the_field_is_out_of_reach():
    truth, fit = field(0.6, 0.0), field(0.6, 0.0, streak_value=0.9)
    lungs = ~ball(*NODULE)  # the field holes where the nodule is, as at the chest wall
    lungs[ball(NODULE[0], 7.0)] = False
    r = fit_vs_truth.compare(fit, truth, ball(*NODULE), lungs, SPACING)
    assert r["decoy_kind"] == "artefact"
    assert r["truth_at_fit_decoy"] < 0.5 * r["fit_decoy"]
    assert not r["reachable"]
    assert abs(r["kept"] - 1.0) < 1e-9
