#!/usr/bin/env python3
"""How well `tie_break = "score"` ranks a search's blobs, and its weight chosen without peeking.

    lab/scripts/select_study.py shipped ''          # first: the nine sets' result.json files
    lab/scripts/blob_ranker.py shipped              # then: the blind search's blobs, judged
    lab/scripts/blob_ranker.py shipped --search guided

Every result.json records the blobs each search accepted (`centres.blind_accepted`,
`centres.guided_accepted`: response, region roundness and peak score, whether the centre lies
on the nodule), whatever rule then took one. This reads them for every nodule ≥ 10 mm of a
select study (out-study/NAME/SET/) and counts the cases whose best scored blob among the
`top` strongest, by ln(response / peak score) + w × roundness, lies on the nodule:

- in-sample, for each w of a grid and each `top`;
- leave-one-patient-out: for each patient, w is chosen on every other patient's cases (the
  same LIDC patient's nodule in other anatomies is held out with it; the calibration spheres
  are each their own group), then judged on the held-out ones.

"On the nodule" is the centre's ground-truth coverage, which is close to a hit (the select
stage's own hit also asks its region to overlap). Only the standard library is needed.
"""
import argparse
import csv
import json
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WEIGHTS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0)
TOPS = (1, 2, 3, 4, 5, 6, 8, 16)


def nodules(folder, min_diameter_mm=10.0):
    """[(results.csv row, its result.json path)] for every nodule ≥ min_diameter_mm of one run's
    out dir; none where the dir has no results.csv."""
    results = os.path.join(folder, "results.csv")
    if not os.path.exists(results):
        return []
    with open(results) as f:
        rows = [row for row in csv.DictReader(f) if float(row["gt_diameter_mm"]) >= min_diameter_mm]
    return [(row, os.path.join(folder, row["patient"], "result.json")) for row in rows]


def scored_region(blob, path, search):
    """An accepted blob's half-maximum region, or exit saying the run sized none."""
    region = blob.get("region")
    if region is None or region["peak_score"] <= 0:
        sys.exit(f"{path}: a {search} blob has no region to score: run the study with sizing = "
                 "\"half_max\" or \"shadows\"")
    return region


def cases(study_dir, search, min_diameter_mm=10.0):
    """[(set, patient, [(score_terms, on_nodule), ...])] for every nodule ≥ min_diameter_mm:
    each accepted blob as (ln(response / peak score), roundness) with whether it is on the nodule."""
    found = []
    for set_name in sorted(os.listdir(study_dir)):
        for row, path in nodules(os.path.join(study_dir, set_name), min_diameter_mm):
            with open(path) as f:
                centres = json.load(f).get("centres", {})
            blobs = []
            for c in centres.get(f"{search}_accepted", []):
                region = scored_region(c, path, search)
                blobs.append(((math.log(c["blob"]["response"] / region["peak_score"]), region["roundness"]),
                              bool(c.get("on_nodule"))))
            found.append((set_name, row["patient"], blobs))
    return found


def takes_nodule(blobs, weight, top):
    """Whether the best scored of the `top` strongest blobs lies on the nodule (the stronger of two alike)."""
    best = None
    for (log_ratio, roundness), on in blobs[:top]:
        score = log_ratio + weight * roundness
        if best is None or score > best[0]:
            best = (score, on)
    return best is not None and best[1]


def group_of(set_name, patient):
    """A phantom patient's nodule recurs in every anatomy: hold them out together."""
    return set_name + "/" + patient if set_name.startswith("spheres") else patient


def leave_one_patient_out(found, top):
    """How many held-out cases the in-fold best weight takes the nodule in, and the weights chosen."""
    groups = sorted({group_of(s, p) for s, p, _ in found})
    taken, chosen = 0, []
    for group in groups:
        train = [b for s, p, b in found if group_of(s, p) != group]
        # The first of the best: ties go to the smaller weight.
        weight = max(WEIGHTS, key=lambda w: (sum(takes_nodule(b, w, top) for b in train), -w))
        chosen.append(weight)
        taken += sum(takes_nodule(b, weight, top) for s, p, b in found if group_of(s, p) == group)
    return taken, chosen


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", help="a select study's name (out-study/NAME) or its directory")
    ap.add_argument("--search", choices=("blind", "guided"), default="blind")
    args = ap.parse_args()
    study_dir = args.study if os.path.isdir(args.study) else os.path.join(ROOT, "out-study", args.study)
    if not os.path.isdir(study_dir):
        sys.exit(f"no study at {study_dir}: run lab/scripts/select_study.py {args.study} '' first")
    found = cases(study_dir, args.search)
    if not found:
        sys.exit(f"{study_dir} holds no results.csv with nodules ≥ 10 mm")
    n = len(found)
    strongest = sum(bool(b) and b[0][1] for _, _, b in found)
    anywhere = sum(any(on for _, on in b) for _, _, b in found)
    print(f"{args.search} search, {n} nodules ≥ 10 mm: the strongest blob is on the nodule in {strongest}; "
          f"some accepted blob in {anywhere}")
    print("top  " + " ".join(f"w={w:<4}" for w in WEIGHTS) + "  leave-one-patient-out (weights chosen)")
    for top in TOPS:
        in_sample = [sum(takes_nodule(b, w, top) for _, _, b in found) for w in WEIGHTS]
        held_out, chosen = leave_one_patient_out(found, top)
        spread = sorted(set(chosen))
        print(f"{top:>3}  " + " ".join(f"{c:>6}" for c in in_sample) + f"  {held_out:>4} ({', '.join(map(str, spread))})")


if __name__ == "__main__":
    main()
