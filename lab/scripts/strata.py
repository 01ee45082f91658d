#!/usr/bin/env python3
"""Hit rates by kind of nodule (solid and enclosed by the lung, solid and against its wall,
subsolid) and by diameter band (10–15, 15–20, ≥ 20 mm).

    lab/scripts/strata.py out out-default-seed2 ...      # run out dirs: <patient>/result.json,
                                                         # ground_truth.json, target_site.json

A miss rate says little until it says which nodules it misses. For every patient whose target is
at least `--min-diameter-mm` (10 by default) this sorts the target into one of three strata, from
what ingest read in the annotations and the CT (never from a result), as `summary.json`'s groups
`ge10mm_solid_enclosed`, `ge10mm_solid_attached` and `ge10mm_subsolid` split them:

- **subsolid**: its readers' mean texture rating is below 3.5 (`ground_truth.json`; LIDC's 1
  ground glass … 5 solid; the phantom draws ratings 1–3 at −650 to −250 HU);
- **attached**: solid, and against the lung's wall (`target_site.json`: some of its consensus
  lies outside the CT's lung field, juxtapleural or on the mediastinum or the spine);
- **free**: solid, enclosed by the lung.

It then sorts the same targets by their annotated diameter into the bands of `summary.json`'s
groups `ge10mm_lt15mm`, `ge15mm_lt20mm` and `ge20mm` (each band holds its lower edge).

It prints, per out dir and stratum, the guided and the blind rule's hits (`result.json`'s
`localization.hit`) and which patients each missed: the names behind the summary's rates.
"""
import argparse
import json
import os

SOLID_RATING = 3.5  # summary.json's `solid`: the readers' mean texture rating from 3.5 up
STRATA = ("free", "attached", "subsolid")
# (name, lowest diameter, diameter it stops below), mm.
BANDS = (("10-15 mm", 10.0, 15.0), ("15-20 mm", 15.0, 20.0), (">=20 mm", 20.0, float("inf")))


def kind(texture_mean, attached):
    """The stratum of a target rated `texture_mean` that lies against the lung's wall or not."""
    if texture_mean < SOLID_RATING:
        return "subsolid"
    return "attached" if attached else "free"


def stratum(patient_dir):
    """The target's stratum and annotated diameter (mm), or None without a target."""
    truth = json.load(open(os.path.join(patient_dir, "ground_truth.json")))
    if truth.get("target") is None:
        return None
    site_path = os.path.join(patient_dir, "target_site.json")
    if not os.path.exists(site_path):
        raise SystemExit(f"{site_path} is missing: it comes from ingest version 3 on; run the "
                         "pipeline again (only ingest and metrics recompute)")
    site = json.load(open(site_path))
    nodule = truth["nodules"][truth["target"]]
    return kind(nodule["texture_mean"], site["attached"]), nodule["annotated_diameter_mm"]


def hits(patient_dir):
    """Whether the guided and the blind rule's selections hit."""
    result = json.load(open(os.path.join(patient_dir, "result.json")))
    hit = lambda rule: bool(result.get(rule) and (result[rule].get("localization") or {}).get("hit"))
    return hit("guided"), hit(result.get("blind_rule", "blind_persistent"))


def band(diameter_mm):
    """The band of a target `diameter_mm` across, or None below 10 mm."""
    return next((name for name, low, high in BANDS if low <= diameter_mm < high), None)


def print_rows(name, rows):
    """One stratum's line: its count, hits, and the patients each rule missed."""
    guided, blind = sum(r[1] for r in rows), sum(r[2] for r in rows)
    missed = lambda i: " ".join(r[0].removeprefix("LIDC-IDRI-") for r in rows if not r[i]) or "-"
    print(f"  {name:9s} n={len(rows):2d}  guided {guided:2d}  blind {blind:2d}"
          f"   guided misses: {missed(1)}; blind misses: {missed(2)}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dirs", nargs="+")
    parser.add_argument("--min-diameter-mm", type=float, default=10.0)
    args = parser.parse_args()
    for out in args.out_dirs:
        table = {s: [] for s in STRATA}
        bands = {name: [] for name, _, _ in BANDS}
        for patient in sorted(os.listdir(out)):
            patient_dir = os.path.join(out, patient)
            if not os.path.exists(os.path.join(patient_dir, "result.json")):
                continue
            found = stratum(patient_dir)
            if found is None or found[1] < args.min_diameter_mm:
                continue
            row = (patient, *hits(patient_dir))
            table[found[0]].append(row)
            if band(found[1]):
                bands[band(found[1])].append(row)
        print(f"{out} (targets ≥ {args.min_diameter_mm:g} mm)")
        for s in STRATA:
            print_rows(s, table[s])
        for name, rows in bands.items():
            print_rows(name, rows)


if __name__ == "__main__":
    main()
