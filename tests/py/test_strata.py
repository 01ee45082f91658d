"""tools/strata.py sorts a target into solid and free, solid and touching the lung's wall, or
subsolid, from its texture rating and the true CT alone."""
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))  # the tools import their shared metaimage and blob_ceiling
import strata  # noqa: E402

SHAPE = (40, 40, 40)


def chest_with_nodule(centre):
    """Soft tissue (0.7) around one lung (0.1, nodes 8–31 on each axis), with a solid ball of
    radius 4 nodes at `centre` (z, y, x)."""
    ct = np.full(SHAPE, 0.7)
    ct[8:32, 8:32, 8:32] = 0.1
    z, y, x = np.indices(SHAPE)
    nodule = (z - centre[0]) ** 2 + (y - centre[1]) ** 2 + (x - centre[2]) ** 2 <= 16
    ct[nodule] = 0.7
    return ct, nodule


def test_a_nodule_the_lung_encloses_is_free_and_one_against_its_wall_is_attached():
    assert strata.kind(4.5, *chest_with_nodule((20, 20, 20))) == "free"
    assert strata.kind(4.5, *chest_with_nodule((20, 20, 10))) == "attached"


def test_a_ground_glass_rating_is_subsolid_wherever_the_nodule_lies():
    assert strata.kind(1.5, *chest_with_nodule((20, 20, 20))) == "subsolid"
    assert strata.kind(3.25, *chest_with_nodule((20, 20, 10))) == "subsolid"
    assert strata.kind(3.5, *chest_with_nodule((20, 20, 20))) == "free", "3.5 is solid, as summary.json splits"
