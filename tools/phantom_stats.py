#!/usr/bin/env python3
"""The phantom's lungs measured as quantitative-CT studies measure real ones, for docs/phantom.md.

    tools/phantom_stats.py out                       # every patient of a run's out dir
    tools/phantom_stats.py out --json stats.json --figures docs/phantom   # figures need matplotlib

Per patient it reads ingest's `ct_hu.mhd` (the CT as read back from the phantom's DICOM
series), `gt_mask.mhd` (the target's consensus) and `ground_truth.json` (its readers' texture
rating), and measures:

- **the lung field**: air below −400 HU that does not touch the scan's edge (the air around
  the body), each axial slice's holes of up to 10 cm² filled, so vessels and nodules inside
  count as lung but the heart and mediastinum the lungs wrap around do not;
- **the parenchyma**: the mean lung density, the 15th percentile, the share of the lung field
  at or below −950 and −910 HU (`%LAA`), and the front-to-back density gradient (HU per cm
  along the patient's y, from a least-squares line through the parenchyma below −500 HU);
- **the vessels**: the lung field's voxels above −500 HU outside the target nodule (dilated
  by 3 voxels), as a share of the lung field, split by the cross-section of each vessel
  profile in the axial slice (the `BV5` convention: below 5 mm², 5–10 mm², above 10 mm²);
- **the target nodule**: its mean HU and standard deviation inside the consensus eroded by one
  voxel in-plane (away from the partial-volume edge), and the share of its consensus at or
  above −300 HU (its solid component, by the threshold part-solid nodules are commonly
  segmented at), beside its readers' mean texture rating.

Prints a table per patient and the cohort's medians; `--json` writes every figure and each
patient's parenchyma histogram.
"""
import argparse
import json
import os
import statistics

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

AIR_HU = -400.0
VESSEL_HU = -500.0
# A nodule's voxels at or above this are its solid component.
SOLID_COMPONENT_HU = -300.0
CROSS_SECTIONS_MM2 = (5.0, 10.0)
# The parenchyma histogram's bin edges, HU (4 HU bins up to the vessel threshold).
HISTOGRAM_HU = np.arange(-1024, VESSEL_HU + 4, 4)
# The largest hole in an axial slice of the lung field that is lung: a 35 mm nodule's section.
HOLE_MM2 = 1000.0


def read(path):
    """A MetaImage as an array [z, y, x] and its spacing (x, y, z) in mm."""
    image = sitk.ReadImage(path)
    return sitk.GetArrayFromImage(image), image.GetSpacing()


def lung_field(hu, spacing):
    """Air below −400 HU that does not touch the volume's sides, with each axial slice's holes of
    up to `HOLE_MM2` filled."""
    air = hu < AIR_HU
    labels, _ = ndimage.label(air)
    outside = np.unique(np.concatenate([labels[:, 0, :].ravel(), labels[:, -1, :].ravel(),
                                        labels[:, :, 0].ravel(), labels[:, :, -1].ravel()]))
    lung = air & ~np.isin(labels, outside[outside > 0])
    largest = HOLE_MM2 / (spacing[0] * spacing[1])
    return np.stack([fill_small_holes(s, largest) for s in lung])


def fill_small_holes(mask, largest_pixels):
    """`mask` with its holes of at most `largest_pixels` filled."""
    holes, count = ndimage.label(ndimage.binary_fill_holes(mask) & ~mask)
    if count == 0:
        return mask
    small = np.bincount(holes.ravel()) <= largest_pixels
    small[0] = False
    return mask | small[holes]


def parenchyma(hu, lung, spacing):
    """Mean lung density, P15, %LAA −950 and −910, and the y gradient of the parenchyma (HU/cm)."""
    values = hu[lung].astype(np.float64)
    tissue = lung & (hu < VESSEL_HU)
    _, y, _ = np.nonzero(tissue)
    slope = np.polyfit(y * spacing[1] / 10.0, hu[tissue].astype(np.float64), 1)[0]
    return {
        "mean_lung_density_hu": float(values.mean()),
        "p15_hu": float(np.percentile(values, 15)),
        "laa950_pct": float(100 * (values <= -950).mean()),
        "laa910_pct": float(100 * (values <= -910).mean()),
        "gradient_hu_per_cm": float(slope),
        "lung_volume_ml": float(lung.sum() * np.prod(spacing) / 1000),
    }


def vessels(hu, lung, nodule, spacing):
    """The vessels' share of the lung field, and of their volume by axial cross-section."""
    near_nodule = ndimage.binary_dilation(nodule, iterations=3)
    vessel = lung & (hu > VESSEL_HU) & ~near_nodule
    pixel_mm2 = spacing[0] * spacing[1]
    by_section = np.zeros(3)
    for s in vessel:
        labels, count = ndimage.label(s)
        if count == 0:
            continue
        areas = np.bincount(labels.ravel())[1:] * pixel_mm2
        band = np.searchsorted(CROSS_SECTIONS_MM2, areas, side="right")
        by_section += np.bincount(band, weights=areas, minlength=3)
    total = by_section.sum()
    return {
        "vessel_volume_ml": float(vessel.sum() * np.prod(spacing) / 1000),
        "vessel_fraction_pct": float(100 * vessel.sum() / max(lung.sum(), 1)),
        "bv5_pct_of_vessels": float(100 * by_section[0] / total) if total else None,
        "bv5_10_pct_of_vessels": float(100 * by_section[1] / total) if total else None,
        "bv10_pct_of_vessels": float(100 * by_section[2] / total) if total else None,
    }


def nodule_stats(hu, nodule):
    """The mean and standard deviation of HU inside the mask eroded by one voxel in-plane (None
    when nothing is left), and the share of the mask at or above SOLID_COMPONENT_HU, %."""
    core = np.stack([ndimage.binary_erosion(s) for s in nodule])
    inside = hu[core] if core.any() else None
    return {
        "nodule_core_hu": None if inside is None else float(inside.mean()),
        "nodule_core_sd_hu": None if inside is None else float(inside.std()),
        "nodule_solid_pct": float(100 * (hu[nodule] >= SOLID_COMPONENT_HU).mean()),
    }


def patient_stats(folder):
    hu, spacing = read(os.path.join(folder, "ct_hu.mhd"))
    nodule = read(os.path.join(folder, "gt_mask.mhd"))[0] > 0
    truth = json.load(open(os.path.join(folder, "ground_truth.json")))
    lung = lung_field(hu, spacing)
    if not lung.any():
        raise SystemExit(f"{folder}/ct_hu.mhd: no air below {AIR_HU:g} HU away from the scan's edge: is it a chest CT?")
    stats = {**parenchyma(hu, lung, spacing), **vessels(hu, lung, nodule, spacing)}
    target = truth.get("target")
    if target is not None and nodule.any():
        stats.update(nodule_stats(hu, nodule))
        stats["nodule_texture_mean"] = truth["nodules"][target].get("texture_mean")
    counts, _ = np.histogram(hu[lung & (hu < VESSEL_HU)], bins=HISTOGRAM_HU)
    stats["parenchyma_histogram"] = counts.tolist()
    return stats


COLUMNS = ("mean_lung_density_hu", "p15_hu", "laa950_pct", "laa910_pct", "gradient_hu_per_cm", "vessel_fraction_pct",
           "bv5_pct_of_vessels", "bv5_10_pct_of_vessels", "bv10_pct_of_vessels", "nodule_core_hu", "nodule_core_sd_hu", "nodule_solid_pct",
           "nodule_texture_mean")


def figures(rows, folder):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(folder, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    centres, width = HISTOGRAM_HU[:-1] + 2, np.diff(HISTOGRAM_HU)
    for s in rows.values():
        counts = np.array(s["parenchyma_histogram"], dtype=float)
        ax.plot(centres, counts / (counts.sum() * width), lw=0.7, alpha=0.6)
    ax.axvline(-950, color="k", ls="--", lw=0.8)
    ax.text(-948, ax.get_ylim()[1] * 0.9, "−950 HU", fontsize=8)
    ax.set_xlabel("HU (lung field below −500 HU)")
    ax.set_ylabel("density")
    ax.set_title("Parenchyma histograms, one line a patient")
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "phantom_parenchyma_histogram.png"), dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    pairs = [(s["nodule_texture_mean"], s["nodule_core_hu"], s["nodule_core_sd_hu"]) for s in rows.values()
             if s.get("nodule_core_hu") is not None and s.get("nodule_texture_mean") is not None]
    ax.errorbar([p[0] for p in pairs], [p[1] for p in pairs], yerr=[p[2] for p in pairs], fmt="o", ms=4,
                capsize=2, label="phantom: each target's core, mean ± SD inside")
    ax.axhspan(-633 - 53, -491 + 155, xmin=0, xmax=0.25, color="tab:orange", alpha=0.2,
               label="ground-glass nodules, mean ± SD range (AJR 2017)")
    ax.set_xlim(0.5, 5.5)
    ax.set_xlabel("readers' mean texture rating (1 ground glass … 5 solid)")
    ax.set_ylabel("mean HU of the nodule's core")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "phantom_nodule_hu.png"), dpi=120)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir")
    parser.add_argument("--json")
    parser.add_argument("--figures", help="draw the histograms here (PNG; needs matplotlib)")
    args = parser.parse_args()
    rows = {}
    for patient in sorted(os.listdir(args.out_dir)):
        folder = os.path.join(args.out_dir, patient)
        if os.path.exists(os.path.join(folder, "ct_hu.mhd")):
            rows[patient] = patient_stats(folder)
    if not rows:
        raise SystemExit(f"{args.out_dir}: no <patient>/ct_hu.mhd (run the pipeline to at least `ingest` first)")
    fmt = lambda v: "–" if v is None else f"{v:.2f}" if abs(v) < 10 else f"{v:.0f}"
    print("| patient | " + " | ".join(COLUMNS) + " |")
    print("|" + " --- |" * (len(COLUMNS) + 1))
    for name, s in rows.items():
        print(f"| {name} | " + " | ".join(fmt(s.get(c)) for c in COLUMNS) + " |")
    medians = {c: statistics.median([s[c] for s in rows.values() if s.get(c) is not None])
               for c in COLUMNS if any(s.get(c) is not None for s in rows.values())}
    print("| median | " + " | ".join(fmt(medians.get(c)) for c in COLUMNS) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"patients": rows, "medians": medians, "histogram_edges_hu": HISTOGRAM_HU.tolist()}, f, indent=2)
    if args.figures:
        figures(rows, args.figures)


if __name__ == "__main__":
    main()
