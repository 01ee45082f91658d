#!/usr/bin/env python3
"""Where a fit loses the nodule, against the perfect field of the same patients (issue 8).

    lab/scripts/fit_vs_truth.py out out-perfect-field      # a run's out dir, then the same patients'
                                                           # run with [train] model = "truth"

The perfect field (`lab/presets/perfect_field.toml`, docs/train.md "A perfect field") is the true CT
on the fit's own lattice, in its units, so the two `density.mhd` compare node for node: for a
run of another configuration, run that configuration again with `--set train.model=truth` and
`--set pipeline.out_dir=…` (e.g. `aret-pipe run pipeline.toml --set dataset.phantom.seed=2
--set train.model=truth --set pipeline.out_dir=out-perfect-field-seed2`). For
every patient whose annotated diameter is at least `--min-diameter-mm`, on both fields:

- **contrast**: the mean σ over the consensus mask (`gt_mask.mhd`, sampled at the lattice's
  nodes) above the median σ of the shell 4–10 mm outside it; `kept` is the fit's over the truth's;
- **nodule / decoy**: the strongest Hessian blob response (s²·max(0, −λ₁), the stage's blob
  filter, the maximum over the blind search's 6, 9 and 13 mm) on the nodule's
  nodes, and the strongest more than 8 mm inside the fit's lung field (`lung_field.mhd`) and
  more than 3 mm from the nodule. Above 1, a plain strongest-blob search takes the nodule, if
  it can reach it: `reach` says whether any of the nodule's nodes lies in that search region;
- **the fit's decoy**: what the truth holds within 3 nodes of the fit's strongest decoy, as a
  fraction of that decoy's response. At 0.5 or more it is `anatomy` (a vessel junction, the
  hilum: present in the CT, and a better fit keeps it); below, an `artefact` of the fit
  (`none`: no blob answers anywhere in the search region).

So a reader can tell a fit that loses the nodule's contrast from one that makes decoys, on a
continuous scale instead of hit counts. `--figure PNG` also draws, for the patients named in
`--patients` (which alone restricts the table), the axial, coronal and sagittal slices through the nodule's centre on the fit and
on the truth, the consensus outline in green (needs matplotlib). Needs numpy and scipy.
"""
import argparse
import json
import os
import sys

import numpy as np
from scipy import ndimage

from blob_ceiling import BLIND_SCALES_MM, node_mm, responses, search_sites
from metaimage import read_mhd

SHELL_MM = (4.0, 10.0)
DECOY_CLEARANCE_MM = 3.0
DECOY_WINDOW_NODES = 3
ANATOMY_FRACTION = 0.5


def blob_response(volume, spacing):
    """The scale-normalised Hessian bright-blob response, the maximum over the blind scales."""
    return np.max([responses(volume, s, spacing)["hessian"] for s in BLIND_SCALES_MM], 0)


def mask_on_lattice(mask, mask_spacing, mask_origin, nodes):
    """The consensus mask at every lattice node (its nearest CT voxel; outside the CT: no)."""
    index = np.round((nodes - mask_origin) / mask_spacing).astype(int)
    inside = np.all((index >= 0) & (index < np.array(mask.shape[::-1])), -1)
    out = np.zeros(nodes.shape[:-1], bool)
    i = index[inside]
    out[inside] = mask[i[:, 2], i[:, 1], i[:, 0]] > 0
    return out


def ratio(a, b):
    """a / b, NaN where b is not positive (a truth with no contrast or no blob there)."""
    return a / b if b > 0 else float("nan")


def compare(fit, truth, nodule, lung_field, spacing):
    """The measures above, for one patient: a dict of floats and the decoy's kind."""
    sampling = spacing[::-1]
    outside = ndimage.distance_transform_edt(~nodule, sampling=sampling)
    shell = (outside > SHELL_MM[0]) & (outside < SHELL_MM[1])
    sites = search_sites(lung_field, spacing)
    elsewhere = sites & (outside > DECOY_CLEARANCE_MM)
    row, fields_response = {}, {}
    for name, field in (("fit", fit), ("truth", truth)):
        response = fields_response[name] = blob_response(field.astype(np.float64), spacing)
        row[f"{name}_contrast"] = float(field[nodule].mean() - np.median(field[shell]))
        row[f"{name}_nodule"] = float(response[nodule].max()) if nodule.any() else 0.0
        row[f"{name}_decoy"] = float(response[elsewhere].max()) if elsewhere.any() else 0.0
        row[f"{name}_margin"] = ratio(row[f"{name}_nodule"], row[f"{name}_decoy"])
    row["reachable"] = bool((nodule & sites).any())
    row["kept"] = ratio(row["fit_contrast"], row["truth_contrast"])
    row["response_kept"] = ratio(row["fit_nodule"], row["truth_nodule"])
    if row["fit_decoy"] > 0:
        decoy = np.unravel_index(np.argmax(np.where(elsewhere, fields_response["fit"], -np.inf)), fit.shape)
        window = tuple(slice(max(0, i - DECOY_WINDOW_NODES), i + DECOY_WINDOW_NODES + 1) for i in decoy)
        row["truth_at_fit_decoy"] = float(fields_response["truth"][window].max())
        row["decoy_truth_ratio"] = row["truth_at_fit_decoy"] / row["fit_decoy"]
        row["decoy_kind"] = "anatomy" if row["decoy_truth_ratio"] >= ANATOMY_FRACTION else "artefact"
    else:  # no blob anywhere in the search region
        row["truth_at_fit_decoy"], row["decoy_truth_ratio"], row["decoy_kind"] = 0.0, float("nan"), "none"
    return row


def load(fit_out, truth_out, patient):
    """The fit, the truth on its lattice, the nodule's nodes and the lattice's spacing."""
    fit_dir, truth_dir = (os.path.join(d, patient) for d in (fit_out, truth_out))
    truth_mhd = os.path.join(truth_dir, "density.mhd")
    if not os.path.exists(truth_mhd):
        sys.exit(f"{truth_mhd}: missing; run lab/presets/perfect_field.toml (or the fit's configuration with "
                 f"--set train.model=truth) into {truth_out} first")
    fit, spacing, origin = read_mhd(os.path.join(fit_dir, "density.mhd"))
    truth, truth_spacing, truth_origin = read_mhd(truth_mhd)
    if truth.shape != fit.shape or not np.allclose(truth_spacing, spacing) or not np.allclose(truth_origin, origin):
        sys.exit(f"{truth_mhd}: not on the fit's lattice ({fit.shape}, spacing {spacing}); "
                 "the perfect field must use the fit's box, roi and grid")
    mask, m_spacing, m_origin = read_mhd(os.path.join(fit_dir, "gt_mask.mhd"))
    nodule = mask_on_lattice(mask, m_spacing, m_origin, node_mm(fit.shape, spacing, origin))
    return fit, truth, nodule, spacing


def figure(fit_out, truth_out, patients, path):
    """Slices through each named patient's nodule: fit (left three), truth (right three)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(patients), 6, figsize=(15, 2.6 * len(patients)), squeeze=False)
    for row, patient in zip(axes, patients):
        fit, truth, nodule, spacing = load(fit_out, truth_out, patient)
        if not nodule.any():
            sys.exit(f"{patient}: its consensus mask holds no node of the lattice; nothing to draw")
        z, y, x = (int(round(i.mean())) for i in np.nonzero(nodule))
        # Each cut of the (z, y, x) arrays, with the array axes of its rows and columns.
        cuts = (("axial", np.s_[z, :, :], 1, 2), ("coronal", np.s_[:, y, :], 0, 2),
                ("sagittal", np.s_[:, :, x], 0, 1))
        for half, (name, volume) in enumerate((("fit", fit), ("truth", truth))):
            for col, (view, cut, rows_axis, cols_axis) in enumerate(cuts):
                ax = row[3 * half + col]
                extent = [0, volume.shape[cols_axis] * spacing[2 - cols_axis],
                          0, volume.shape[rows_axis] * spacing[2 - rows_axis]]
                ax.imshow(volume[cut], cmap="gray", vmin=0.0, vmax=0.8, origin="lower", extent=extent)
                ax.contour(nodule[cut].astype(float), [0.5], colors="lime", linewidths=0.7, extent=extent)
                ax.set_title(f"{patient[-4:]} {name}, {view}", fontsize=8)
                ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("fit_out", help="a run's out dir")
    ap.add_argument("truth_out", help="the same patients' out dir with [train] model = \"truth\"")
    ap.add_argument("--min-diameter-mm", type=float, default=10.0)
    ap.add_argument("--figure", metavar="PNG", help="draw slices through the nodules of --patients")
    ap.add_argument("--patients", default="", help="comma-separated: only these (with --figure: the ones drawn)")
    args = ap.parse_args()
    if args.figure:
        if not args.patients:
            sys.exit("--figure needs --patients, e.g. --patients LIDC-IDRI-0012,LIDC-IDRI-0014")
        figure(args.fit_out, args.truth_out, args.patients.split(","), args.figure)
        return 0
    patients = sorted(p for p in os.listdir(args.fit_out)
                      if os.path.exists(os.path.join(args.fit_out, p, "result.json")))
    if args.patients:
        wanted = args.patients.split(",")
        missing = [p for p in wanted if p not in patients]
        if missing:
            sys.exit(f"{args.fit_out}: no result.json for {', '.join(missing)}")
        patients = wanted
    if not patients:
        sys.exit(f"{args.fit_out}: no <patient>/result.json; run the pipeline first")
    print("patient         d mm  contrast fit / truth  kept | response kept | nodule/decoy fit  truth  reach"
          " | the fit's strongest decoy")
    rows = []
    for patient in patients:
        fit_dir = os.path.join(args.fit_out, patient)
        diameter = json.load(open(os.path.join(fit_dir, "result.json")))["annotated_diameter_mm"]
        if diameter is None or diameter < args.min_diameter_mm:
            continue
        fit, truth, nodule, spacing = load(args.fit_out, args.truth_out, patient)
        lungs = read_mhd(os.path.join(fit_dir, "lung_field.mhd"))[0].astype(bool)
        r = compare(fit, truth, nodule, lungs, spacing)
        rows.append(r)
        print(f"{patient}  {diameter:4.1f}   {r['fit_contrast']:.3f} / {r['truth_contrast']:.3f}     {r['kept']:.2f} |"
              f"          {r['response_kept']:.2f} |       {r['fit_margin']:5.2f}  {r['truth_margin']:5.2f}"
              f"  {'yes' if r['reachable'] else 'no ':5} | {r['decoy_kind']}"
              f" (the truth answers {r['decoy_truth_ratio']:.2f} × as much there)", flush=True)
    if not rows:
        sys.exit(f"{args.fit_out}: no patient with an annotated diameter ≥ {args.min_diameter_mm:g} mm")
    anatomy = [r for r in rows if r["decoy_kind"] == "anatomy"]
    reachable = [r for r in rows if r["reachable"]]
    print(f"\n{len(rows)} patients ≥ {args.min_diameter_mm:g} mm:"
          f" median contrast kept {np.nanmedian([r['kept'] for r in rows]):.2f},"
          f" median nodule response kept {np.nanmedian([r['response_kept'] for r in rows]):.2f};"
          f" of the {len(reachable)} in the search's reach, the nodule out-answers every decoy"
          f" on the fit in {sum(r['fit_margin'] > 1 for r in reachable)},"
          f" on the truth in {sum(r['truth_margin'] > 1 for r in reachable)};"
          f" the fit's strongest decoy is anatomy in {len(anatomy)}"
          + (f" (median response kept {np.median([1 / r['decoy_truth_ratio'] for r in anatomy]):.2f})"
             if anatomy else "")
          + f", an artefact in {sum(r['decoy_kind'] == 'artefact' for r in rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
