#!/usr/bin/env python3
"""Where the boxes of a tiled run lay, and which one each patient's blind rule kept.

    lab/scripts/tiles_figure.py out-tiles LIDC-IDRI-0002 LIDC-IDRI-0006 -o lab/figures/tiles.png

For each patient of a `roi_center = "tiles"` run (`presets/tiles.toml`): the CT's coronal mean
projection (`ct_hu.mhd`, −1000…400 HU), every box's x–z extent from its `tileNN/cameras.json`
(blue; boxes at the three depths overlap in this view), the box the blind rule kept (orange,
from `result.json`), the boxes whose blind centre lay on the nodule (green dashed: the
diagnostic `blind_on_nodule`, never used to choose), the blind centre (×) and the consensus
centroid (○, from `gt_mask.mhd`). Needs numpy and matplotlib.
"""
import argparse
import json
import os

import numpy as np

from metaimage import read_mhd


def box_extent_mm(cameras):
    """A box's corners in patient mm, from its cameras.json."""
    frame = cameras["frame"]
    centre, mm = np.array(frame["roi_center_mm"]), frame["mm_per_unit"]
    return centre + np.array(cameras["aabb"]["min"]) * mm, centre + np.array(cameras["aabb"]["max"]) * mm


def draw_patient(ax, patient_dir, name):
    from matplotlib.patches import Rectangle

    ct, spacing, origin = read_mhd(os.path.join(patient_dir, "ct_hu.mhd"))
    projection = np.clip(ct, -1000, 400).mean(axis=1)  # [z, x]
    extent = [origin[0], origin[0] + spacing[0] * ct.shape[2], origin[2], origin[2] + spacing[2] * ct.shape[0]]
    ax.imshow(projection, cmap="gray", origin="lower", extent=extent, aspect="equal")
    result = json.load(open(os.path.join(patient_dir, "result.json")))
    chosen = (result.get("blind_persistent") or {}).get("tile")
    span = list(extent)
    for tile in result["tiles"]:
        lo, hi = box_extent_mm(json.load(open(os.path.join(patient_dir, tile["tile"], "cameras.json"))))
        style = dict(fill=False, lw=0.6, ec="#6af", alpha=0.6)
        if tile.get("blind_on_nodule"):
            style.update(ls="--", lw=1.2, ec="#4d4", alpha=1.0)
        if tile["tile"] == chosen:
            style.update(ls="-", lw=2.5, ec="#f80", alpha=1.0)
        ax.add_patch(Rectangle((lo[0], lo[2]), hi[0] - lo[0], hi[2] - lo[2], **style))
        span = [min(span[0], lo[0]), max(span[1], hi[0]), min(span[2], lo[2]), max(span[3], hi[2])]
    mask, mask_spacing, mask_origin = read_mhd(os.path.join(patient_dir, "gt_mask.mhd"))
    if mask.any():
        centroid = np.argwhere(mask > 0).mean(axis=0)[::-1] * mask_spacing + mask_origin
        ax.plot(centroid[0], centroid[2], "o", mfc="none", mec="#4d4", ms=12, mew=2, label="nodule (consensus)")
    blind = (result.get("centres") or {}).get("blind")
    if blind:
        ax.plot(blind["position_mm"][0], blind["position_mm"][2], "x", color="#f80", ms=10, mew=2, label="blind centre")
    hit = (((result.get("blind_persistent") or {}).get("localization")) or {}).get("hit")
    ax.set_title(f"{name}: blind {'hit' if hit else 'miss'} in {chosen}", fontsize=10)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_xlim(span[0] - 5, span[1] + 5)
    ax.set_ylim(span[2] - 5, span[3] + 5)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir", help="the tiled run's out dir")
    ap.add_argument("patients", nargs="+")
    ap.add_argument("-o", "--output", help="the PNG to write (default: OUT_DIR/tiles_overview.png)")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(args.patients), figsize=(4.6 * len(args.patients), 5.6), squeeze=False)
    for ax, patient in zip(axes[0], args.patients):
        draw_patient(ax, os.path.join(args.out_dir, patient), patient)
    axes[0][0].legend(loc="lower left", fontsize=7)
    fig.suptitle(
        "The boxes in coronal view (blue; the three depths overlap), the one the blind rule kept (orange),"
        " those whose blind centre lies on the nodule (green dashed)",
        fontsize=9,
    )
    fig.tight_layout()
    output = args.output or os.path.join(args.out_dir, "tiles_overview.png")
    fig.savefig(output, dpi=90)
    print(output)


if __name__ == "__main__":
    main()
