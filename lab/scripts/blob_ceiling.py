#!/usr/bin/env python3
"""How often the select stage's blob search finds the nodule, on the reconstruction and on the
true CT (issue 8: which of the two limits localization).

    lab/scripts/blob_ceiling.py out            # a run's out dir: <patient>/density.mhd, lung_field.mhd,
                                               # ct_unit.mhd, gt_mask.mhd, result.json

For every patient, the true CT (`ct_unit.mhd`, v in [0, 1]) is blurred to the density lattice's
cells (a Gaussian of 0.4 cells) and sampled at its nodes: the best a 64³ reconstruction could
be. Its lung field is the parenchyma band 0.03 < v < 0.3 (after a 1-cell blur), components of at
least 2 % of the box, holes filled slice by slice along each axis. The reconstruction's own field
is the stage's `lung_field.mhd`. On each volume the strongest response more than 8 mm inside the
field is taken, as `select` takes it, for the Laplacian (lab-v1's `blob_filter = "laplacian"`,
since gone from the code) and the Hessian (the stage's only filter now) response, at the scale
matched to the annotated diameter (the guided search) and at the blind search's 6, 9 and 13 mm. A centre is on the nodule when it lies within
half the annotated diameter of the consensus centroid (`gt_mask.mhd`). Counts are over the
patients whose annotated diameter is at least 10 mm. Needs numpy and scipy.
"""
import argparse
import json
import os
import sys

import numpy as np
from scipy import ndimage

from metaimage import read_mhd

INSIDE_MM = 8.0
BLIND_SCALES_MM = (6.0, 9.0, 13.0)


def node_mm(shape, spacing, origin):
    """Patient mm of every node, (z, y, x, 3) with the last axis x, y, z."""
    z, y, x = np.indices(shape)
    return np.stack([origin[0] + x * spacing[0], origin[1] + y * spacing[1], origin[2] + z * spacing[2]], -1)


def true_ct_on_lattice(patient_dir, nodes, lattice_spacing):
    ct, spacing, origin = read_mhd(os.path.join(patient_dir, "ct_unit.mhd"))
    blur = [0.4 * lattice_spacing[a] / spacing[a] for a in (2, 1, 0)]
    smooth = ndimage.gaussian_filter(ct.astype(np.float32), blur)
    index = [(nodes[..., a] - origin[a]) / spacing[a] for a in (2, 1, 0)]
    return ndimage.map_coordinates(smooth, index, order=1, mode="constant")


def true_lung_field(volume):
    band = ndimage.gaussian_filter(volume, 1.0)
    band = (band > 0.03) & (band < 0.3)
    labels, _ = ndimage.label(band)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    field = np.isin(labels, np.nonzero(sizes >= 0.02 * volume.size)[0])
    for axis in range(3):
        slices = [ndimage.binary_fill_holes(s) for s in np.moveaxis(field, axis, 0)]
        field = np.moveaxis(np.stack(slices), 0, axis)
    return field


def hessian_eigenvalues(volume, s_mm, spacing):
    """Eigenvalues (ascending) of the scale-normalised Hessian of Gaussian, mm."""
    spacing_zyx = spacing[::-1]
    sigma = s_mm / spacing_zyx
    hessian = np.empty(volume.shape + (3, 3))
    for a in range(3):
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            h = ndimage.gaussian_filter(volume, sigma, order=order, mode="nearest")
            hessian[..., a, b] = hessian[..., b, a] = h / (spacing_zyx[a] * spacing_zyx[b])
    return np.linalg.eigvalsh(hessian) * s_mm * s_mm


def responses(volume, s_mm, spacing):
    eig = hessian_eigenvalues(volume, s_mm, spacing)
    return {"laplacian": -eig.sum(-1), "hessian": np.maximum(0.0, -eig[..., -1])}


def search_sites(field, spacing):
    """The nodes a blob search may take: > INSIDE_MM inside the lung field and inside the lattice
    (its faces count as edges, as in the stage's `blob_sites`)."""
    padded = np.pad(field, 1, constant_values=False)
    return ndimage.distance_transform_edt(padded, sampling=spacing[::-1])[1:-1, 1:-1, 1:-1] > INSIDE_MM


def strongest(volume, field, spacing, scales_mm):
    """The node of the strongest response per filter, over the scales, at the `search_sites`."""
    sites = search_sites(field, spacing)
    best = {}
    for s in scales_mm:
        for name, r in responses(volume, s, spacing).items():
            r = np.where(sites, r, -np.inf)
            i = np.unravel_index(np.argmax(r), r.shape)
            if name not in best or r[i] > best[name][1]:
                best[name] = (i, r[i])
    return {name: i for name, (i, _) in best.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="a run's out dir")
    ap.add_argument("--min-diameter-mm", type=float, default=10.0)
    args = ap.parse_args()
    patients = sorted(p for p in os.listdir(args.out) if os.path.exists(os.path.join(args.out, p, "result.json")))
    if not patients:
        sys.exit(f"{args.out}: no <patient>/result.json; run the pipeline first")
    counts, n = {}, 0
    for patient in patients:
        d = os.path.join(args.out, patient)
        diameter = json.load(open(os.path.join(d, "result.json")))["annotated_diameter_mm"]
        if diameter is None or diameter < args.min_diameter_mm:
            continue
        n += 1
        density, spacing, origin = read_mhd(os.path.join(d, "density.mhd"))
        field = read_mhd(os.path.join(d, "lung_field.mhd"))[0].astype(bool)
        nodes = node_mm(density.shape, spacing, origin)
        mask, m_spacing, m_origin = read_mhd(os.path.join(d, "gt_mask.mhd"))
        centroid = np.array([m_origin[a] + np.nonzero(mask)[2 - a].mean() * m_spacing[a] for a in range(3)])
        truth = true_ct_on_lattice(d, nodes, spacing)
        line = [f"{patient} d={diameter:4.1f} mm"]
        for source, volume, lungs in (("truth", truth, true_lung_field(truth)),
                                      ("recon", density.astype(np.float64), field)):
            for search, scales in (("guided", [diameter / (2 * np.sqrt(3))]), ("blind", BLIND_SCALES_MM)):
                for name, node in strongest(volume, lungs, spacing, scales).items():
                    on = bool(np.linalg.norm(nodes[node] - centroid) < diameter / 2)
                    key = (source, search, name)
                    counts[key] = counts.get(key, 0) + on
                    line.append(f"{source[0]}{search[0]}{name[0]}:{'+' if on else '.'}")
        print(" ".join(line), flush=True)
    print(f"\ncentres on the nodule, {n} patients ≥ {args.min_diameter_mm:g} mm (laplacian / hessian):")
    for source in ("truth", "recon"):
        for search in ("guided", "blind"):
            lap, hes = counts[(source, search, "laplacian")], counts[(source, search, "hessian")]
            print(f"  {source:5} {search:6}: {lap:2d} / {hes:2d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
