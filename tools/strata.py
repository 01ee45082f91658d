#!/usr/bin/env python3
"""Hit rates by kind of nodule: solid and free in the lung, solid and touching its wall, subsolid.

    tools/strata.py out out-default-seed2 ...      # run out dirs: <patient>/result.json,
                                                   # ground_truth.json, gt_mask.mhd, ct_unit.mhd

A miss rate says little until it says which nodules it misses. For every patient whose target is
at least `--min-diameter-mm` (10 by default) this sorts the target into one of three strata, from
the annotations and the CT only (never from a result):

- **subsolid**: its readers' mean texture rating is below 3.5 (`ground_truth.json`; LIDC's 1
  ground glass … 5 solid; the phantom draws ratings 1–3 at −650 to −250 HU), as `summary.json`'s
  `solid` / `subsolid` groups split them;
- **attached**: solid, and touching the lung's wall: some node of its consensus mask
  (`gt_mask.mhd` on the density lattice) lies outside the lung field of the true CT
  (`ct_unit.mhd` on the same lattice, the band and hole filling of `tools/blob_ceiling.py`), so
  the field does not enclose it (juxtapleural or paravertebral);
- **free**: solid, enclosed by the lung.

It prints, per out dir and stratum, the guided and the blind rule's hits (`result.json`'s
`localization.hit`) and which patients each missed. Needs numpy and scipy.
"""
import argparse
import json
import os

import numpy as np

from blob_ceiling import node_mm, true_ct_on_lattice, true_lung_field
from fit_vs_truth import mask_on_lattice
from metaimage import read_mhd

SOLID_RATING = 3.5  # summary.json's `solid`: the readers' mean texture rating from 3.5 up
STRATA = ("free", "attached", "subsolid")


def kind(texture_mean, ct, on_nodule):
    """The stratum of a target rated `texture_mean` whose nodes `on_nodule` lie in the true CT
    `ct` (v in [0, 1], both on the density lattice)."""
    if texture_mean < SOLID_RATING:
        return "subsolid"
    outside_lungs = ~true_lung_field(ct.astype(np.float32))
    return "attached" if (on_nodule & outside_lungs).any() else "free"


def stratum(patient_dir):
    """The target's stratum and annotated diameter (mm), or None without a target."""
    truth = json.load(open(os.path.join(patient_dir, "ground_truth.json")))
    if truth.get("target") is None:
        return None
    nodule = truth["nodules"][truth["target"]]
    density, spacing, origin = read_mhd(os.path.join(patient_dir, "density.mhd"))
    nodes = node_mm(density.shape, spacing, origin)
    ct = true_ct_on_lattice(patient_dir, nodes, spacing)
    mask, m_spacing, m_origin = read_mhd(os.path.join(patient_dir, "gt_mask.mhd"))
    on_nodule = mask_on_lattice(mask, m_spacing, m_origin, nodes)
    return kind(nodule["texture_mean"], ct, on_nodule), nodule["annotated_diameter_mm"]


def hits(patient_dir):
    """Whether the guided and the blind rule's selections hit."""
    result = json.load(open(os.path.join(patient_dir, "result.json")))
    hit = lambda rule: bool(result.get(rule) and (result[rule].get("localization") or {}).get("hit"))
    return hit("guided"), hit(result.get("blind_rule", "blind_persistent"))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dirs", nargs="+")
    parser.add_argument("--min-diameter-mm", type=float, default=10.0)
    args = parser.parse_args()
    for out in args.out_dirs:
        table = {s: [] for s in STRATA}
        for patient in sorted(os.listdir(out)):
            patient_dir = os.path.join(out, patient)
            if not os.path.exists(os.path.join(patient_dir, "result.json")):
                continue
            found = stratum(patient_dir)
            if found is None or found[1] < args.min_diameter_mm:
                continue
            table[found[0]].append((patient, *hits(patient_dir)))
        print(f"{out} (targets ≥ {args.min_diameter_mm:g} mm)")
        for s in STRATA:
            rows = table[s]
            guided, blind = sum(r[1] for r in rows), sum(r[2] for r in rows)
            missed = lambda i: " ".join(r[0].removeprefix("LIDC-IDRI-") for r in rows if not r[i]) or "-"
            print(f"  {s:9s} n={len(rows):2d}  guided {guided:2d}  blind {blind:2d}"
                  f"   guided misses: {missed(1)}; blind misses: {missed(2)}")


if __name__ == "__main__":
    main()
