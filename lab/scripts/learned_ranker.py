#!/usr/bin/env python3
"""Could a learned ranking of the searches' blobs find more nodules? Judged leaving one anatomy out.

    lab/scripts/learned_ranker.py OUT_HELDOUT --candidate NAME [--search guided|blind] [--pool blind]
    lab/scripts/learned_ranker.py OUT --candidate NAME --test-seeds 9-12   # trained once on the rest

Reads the `result.json` files `tools/heldout.py` left under OUT_HELDOUT/seedS/NAME/PATIENT/ (one
candidate's runs, on several anatomies): every blob each search accepted among its strongest
(`centres.guided_accepted`, `centres.blind_accepted`), with the features the select stage
measured (response, scale, rank, the half-maximum region's roundness, diameter and peak local
contrast, depth in the lung field) and, diagnostic only, whether its centre lies on the nodule.

For every nodule ≥ 10 mm the question is which accepted blob to take. A conditional logit (a
softmax over the case's blobs, L2-penalised: `tools/train_blob_ranker.py`'s fit) learns weights on
the features from the other anatomies, and takes the held-out anatomy's highest-scored blob.
Beside it: the shipped rule's centre (`centres.guided` / `centres.blind`, the fallbacks
included), the strongest blob, and the oracle (some accepted blob is on the nodule). With
`--pool blind` the guided search ranks the blind search's blobs (found over its three scales)
instead of its own, still told the annotated diameter. With `--test-seeds`, the weights are
fitted once on every other anatomy and judged on those alone, which nothing was chosen on. Counts are
centres on the nodule, per anatomy and in all. A lab instrument: it reads the ground truth only
to label and to count.
"""
import argparse
import json
import os
import sys

import numpy as np

import blob_ranker

sys.path.insert(0, os.path.join(blob_ranker.ROOT, "tools"))
import train_blob_ranker  # noqa: E402  (the product's features)

FEATURES = train_blob_ranker.FEATURES


def blob_features(blob, region, strongest, reference_mm):
    """The product's features of an accepted blob, its region measured against reference_mm."""
    row = {"response": blob["blob"]["response"], "peak_score": region["peak_score"], "roundness": region["roundness"],
           "diameter_mm": region["diameter_mm"], "depth_mm": blob.get("depth_mm", 0.0), "rank": blob["rank"]}
    return train_blob_ranker.features(row, strongest, reference_mm)


def cases(out, candidate, search, pool=None):
    """{seed: [(patient, features [n, f], on_nodule [n], shipped_on)]} for nodules ≥ 10 mm, for
    every anatomy OUT/seedS/CANDIDATE whose runs kept their result.json files."""
    found = {}
    for entry in sorted(os.listdir(out)):
        records = blob_ranker.nodules(os.path.join(out, entry, candidate)) if entry.startswith("seed") else []
        if not records or not all(os.path.exists(path) for _, path in records):
            continue
        per_seed = []
        for row, path in records:
            centres = json.load(open(path)).get("centres", {})
            blobs = centres.get(f"{pool or search}_accepted") or []
            shipped_on = bool((centres.get(search) or {}).get("on_nodule"))
            if not blobs:
                per_seed.append((row["patient"], np.zeros((0, len(FEATURES))), np.zeros(0, bool), shipped_on))
                continue
            strongest = max(b["blob"]["response"] for b in blobs)
            # The blind search is not told the annotated diameter.
            annotated = float(row["gt_diameter_mm"]) if search == "guided" else train_blob_ranker.REFERENCE_DIAMETER_MM
            x = np.array([blob_features(b, blob_ranker.scored_region(b, path, pool or search), strongest, annotated)
                          for b in blobs])
            y = np.array([bool(b.get("on_nodule")) for b in blobs])
            per_seed.append((row["patient"], x, y, shipped_on))
        found[int(entry[4:])] = per_seed
    return found


def fit(train, penalty):
    """Weights of the conditional logit (the product's fit) on the cases where some blob is on the nodule."""
    w, mean, sd, _ = train_blob_ranker.fit([(0, patient, x.tolist(), list(y)) for patient, x, y, _ in train if len(y)],
                                           penalty)
    return np.array(w), np.array(mean), np.array(sd)


def pick(case, model):
    _, x, y, _ = case
    if len(y) == 0:
        return False
    w, mean, sd = model
    return bool(y[int(np.argmax(((x - mean) / sd) @ w))])


def seeds(text):
    """"1-4,9" → [1, 2, 3, 4, 9]."""
    found = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        found += list(range(int(lo), int(hi or lo) + 1))
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out")
    parser.add_argument("--candidate", required=True)
    parser.add_argument("--search", choices=("guided", "blind"), default="guided")
    parser.add_argument("--pool", choices=("guided", "blind"), help="whose accepted blobs are ranked (default: the search's own)")
    parser.add_argument("--penalty", type=float, default=1.0)
    parser.add_argument("--test-seeds", help="judge only these anatomies (e.g. 9-12), with weights fitted on the rest")
    args = parser.parse_args()
    data = cases(args.out, args.candidate, args.search, args.pool)
    if len(data) < 2:
        raise SystemExit(f"{args.out}: result.json files for {args.candidate} on fewer than two anatomies")
    print(f"{args.search} search ranking the {args.pool or args.search} search's blobs, nodules ≥ 10 mm, centres on the"
          " nodule (learned: held-out anatomy)")
    print("| anatomy | cases | shipped rule | strongest blob | learned | oracle |")
    print("| --- | --- | --- | --- | --- | --- |")
    tested = seeds(args.test_seeds) if args.test_seeds else sorted(data)
    if not set(tested) <= set(data) or (args.test_seeds and set(data) <= set(tested)):
        raise SystemExit(f"{args.out}: --test-seeds {args.test_seeds} needs those anatomies and at least one other")
    totals = np.zeros(5, int)
    for seed in tested:
        held = data[seed]
        train = [s for s in data if s != seed and s not in (tested if args.test_seeds else ())]
        model = fit([c for s in train for c in data[s]], args.penalty)
        row = np.array([len(held), sum(c[3] for c in held), sum(bool(len(c[2]) and c[2][0]) for c in held),
                        sum(pick(c, model) for c in held), sum(bool(c[2].any()) for c in held)])
        totals += row
        print(f"| {seed} | " + " | ".join(str(v) for v in row) + " |")
    print("| all | " + " | ".join(str(v) for v in totals) + " |")
    w, _, _ = fit([c for cs in data.values() for c in cs], args.penalty)
    print("weights on all anatomies (standardised features):")
    for name, v in zip(FEATURES, w):
        print(f"  {name:34s} {v:+.2f}")


if __name__ == "__main__":
    main()
