#!/usr/bin/env python3
"""Train the blind blob search's learned ranking (`[select.blob] blind_tie_break = "learned"`).

    tools/train_blob_ranker.py cases 1=RUN1 2=RUN2 ... --out models/blob_ranker_cases.csv
    tools/train_blob_ranker.py fit models/blob_ranker_cases.csv --out models/blob_ranker.json

`cases` reads `aret-pipe run` out dirs of phantom anatomies (ANATOMY=DIR: the
`[dataset.phantom] seed` the run drew, and its out_dir). For every nodule of at least
`--min-diameter-mm` it writes one row per blob the blind search accepted
(`result.json`: `centres.blind_accepted`): what the select stage measured of the blob and its
half-maximum region, and whether its centre lies on the nodule, which labels it.

`fit` learns a conditional logit: for each nodule, a softmax over its accepted blobs of
w · (standardised features), fitted to put the mass on the blobs on the nodule (cases where none
is carry no information and are left out), with an L2 penalty on w. The select stage then takes
the blob of highest w · z. Pure Python floats and a damped Newton method: the same cases give the
same weights, written to 9 significant digits, on any machine.

The features are defined once here and once in `stages/stage/select/find/learned.rs`, which
refuses a model whose feature names differ from its own.
"""
import argparse
import csv
import json
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# What the blind search's region diameters are measured against, mm: it is not told the
# annotated one.
REFERENCE_DIAMETER_MM = 20.0
# Depth in the lung field counts up to this, mm: deeper is as deep.
DEPTH_CAP_MM = 60.0
FEATURES = (
    "ln response",
    "ln response / strongest accepted",
    "ln peak contrast",
    "ln response / peak contrast",
    "roundness",
    "ln region diameter / reference",
    "|ln region diameter / reference|",
    "depth in the lung field / 10 mm",
    "rank / 16",
)
COLUMNS = ("anatomy", "patient", "gt_diameter_mm", "rank", "response", "peak_score", "roundness", "diameter_mm",
           "depth_mm", "on_nodule")


def features(blob, strongest_response, reference_diameter_mm=REFERENCE_DIAMETER_MM):
    """A blob's features (FEATURES' order) from its row: response, peak_score, roundness,
    diameter_mm, depth_mm, rank. The lab's guided ranking passes the annotated diameter as the
    reference."""
    response, peak = float(blob["response"]), float(blob["peak_score"])
    diameter_ratio = math.log(max(float(blob["diameter_mm"]), 1e-3) / reference_diameter_mm)
    return [math.log(response), math.log(response / strongest_response), math.log(peak), math.log(response / peak),
            float(blob["roundness"]), diameter_ratio, abs(diameter_ratio),
            min(float(blob["depth_mm"]), DEPTH_CAP_MM) / 10.0, int(blob["rank"]) / 16.0]


def blob_row(anatomy, patient, diameter_mm, blob, path):
    region = blob.get("region")
    if region is None or not region["peak_score"] > 0 or not blob["blob"]["response"] > 0:
        sys.exit(f"{path}: a blind blob has no half-maximum region to rank by: run with "
                 "[select] sizing = \"half_max\" or \"shadows\"")
    return {"anatomy": anatomy, "patient": patient, "gt_diameter_mm": diameter_mm, "rank": blob["rank"],
            "response": repr(float(blob["blob"]["response"])), "peak_score": repr(float(region["peak_score"])),
            "roundness": repr(float(region["roundness"])), "diameter_mm": repr(float(region["diameter_mm"])),
            "depth_mm": repr(float(blob.get("depth_mm", 0.0))), "on_nodule": int(bool(blob.get("on_nodule")))}


def read_run(anatomy, folder, min_diameter_mm):
    """The rows of one anatomy's out dir."""
    results = os.path.join(folder, "results.csv")
    if not os.path.exists(results):
        sys.exit(f"{results}: no such file: ANATOMY=DIR names an `aret-pipe run` out_dir")
    rows = []
    with open(results, newline="") as f:
        nodules = [r for r in csv.DictReader(f) if float(r["gt_diameter_mm"]) >= min_diameter_mm]
    for nodule in sorted(nodules, key=lambda r: r["patient"]):
        path = os.path.join(folder, nodule["patient"], "result.json")
        if not os.path.exists(path):
            sys.exit(f"{path}: no such file: the run's out_dir must keep every patient's result.json")
        with open(path) as f:
            accepted = json.load(f).get("centres", {}).get("blind_accepted") or []
        rows += [blob_row(anatomy, nodule["patient"], nodule["gt_diameter_mm"], b, path) for b in accepted]
    return rows


def read_cases(path):
    """[(anatomy, patient, [[feature, ...] per blob], [on_nodule per blob])] in the file's order."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or tuple(rows[0]) != COLUMNS:
        sys.exit(f"{path}: expected the columns {', '.join(COLUMNS)} (written by `cases`)")
    grouped = {}
    for row in rows:
        grouped.setdefault((int(row["anatomy"]), row["patient"]), []).append(row)
    found = []
    for (anatomy, patient), blobs in grouped.items():
        strongest = max(float(b["response"]) for b in blobs)
        found.append((anatomy, patient, [features(b, strongest) for b in blobs], [b["on_nodule"] == "1" for b in blobs]))
    return found


def standardisation(cases):
    """Each feature's mean and standard deviation over every blob of the cases ([(features, on)])."""
    x = [row for xs, _ in cases for row in xs]
    n = len(x)
    mean = [sum(r[j] for r in x) / n for j in range(len(FEATURES))]
    sd = [math.sqrt(sum((r[j] - mean[j]) ** 2 for r in x) / n) + 1e-9 for j in range(len(FEATURES))]
    return mean, sd


def dot(a, b):
    return sum(p * q for p, q in zip(a, b))


def loss_gradient_hessian(w, cases, penalty):
    """−Σ ln P(a blob on the nodule) + penalty·|w|², its gradient and Hessian (z standardised)."""
    k = len(w)
    loss, grad, hess = penalty * dot(w, w), [2 * penalty * v for v in w], [[0.0] * k for _ in range(k)]
    for j in range(k):
        hess[j][j] = 2 * penalty
    for z, on in cases:
        s = [dot(row, w) for row in z]
        top = max(s)
        e = [math.exp(v - top) for v in s]
        total, on_total = sum(e), sum(v for v, y in zip(e, on) if y)
        p, q = [v / total for v in e], [v / on_total if y else 0.0 for v, y in zip(e, on)]
        loss -= math.log(on_total / total)
        mean_p = [dot(p, [row[j] for row in z]) for j in range(k)]
        mean_q = [dot(q, [row[j] for row in z]) for j in range(k)]
        for j in range(k):
            grad[j] += mean_p[j] - mean_q[j]
            for m in range(k):
                cov_p = dot(p, [row[j] * row[m] for row in z]) - mean_p[j] * mean_p[m]
                cov_q = dot(q, [row[j] * row[m] for row in z]) - mean_q[j] * mean_q[m]
                hess[j][m] += cov_p - cov_q
    return loss, grad, hess


def solve(a, b):
    """x with a·x = b for a symmetric positive definite a (Cholesky), or None if it is not."""
    k = len(b)
    chol = [[0.0] * k for _ in range(k)]
    for i in range(k):
        for j in range(i + 1):
            s = a[i][j] - sum(chol[i][m] * chol[j][m] for m in range(j))
            if i == j:
                if s <= 0:
                    return None
                chol[i][i] = math.sqrt(s)
            else:
                chol[i][j] = s / chol[j][j]
    y = [0.0] * k
    for i in range(k):
        y[i] = (b[i] - sum(chol[i][m] * y[m] for m in range(i))) / chol[i][i]
    x = [0.0] * k
    for i in reversed(range(k)):
        x[i] = (y[i] - sum(chol[m][i] * x[m] for m in range(i + 1, k))) / chol[i][i]
    return x


def fit(cases, penalty, iterations=100, tolerance=1e-10):
    """The weights on standardised features, with (mean, sd) and how many cases they learned from."""
    usable = [(xs, on) for _, _, xs, on in cases if any(on)]
    if not usable:
        sys.exit("no case has a blob on the nodule: nothing to learn from")
    mean, sd = standardisation(usable)
    standardised = [([[(v - m) / s for v, m, s in zip(row, mean, sd)] for row in xs], on) for xs, on in usable]
    w = [0.0] * len(FEATURES)
    loss, grad, hess = loss_gradient_hessian(w, standardised, penalty)
    for _ in range(iterations):
        if max(abs(g) for g in grad) < tolerance:
            break
        # Damped Newton: the Hessian is not positive definite where a case has several blobs
        # on the nodule, so add to its diagonal until it is, then halve the step until the
        # loss falls.
        damping, step = 0.0, None
        while step is None:
            step = solve([[h + (damping if i == j else 0.0) for j, h in enumerate(r)] for i, r in enumerate(hess)],
                         [-g for g in grad])
            damping = max(2 * damping, 1e-6)
        for _ in range(60):
            trial = [v + s for v, s in zip(w, step)]
            trial_loss, trial_grad, trial_hess = loss_gradient_hessian(trial, standardised, penalty)
            if trial_loss <= loss:
                break
            step = [s / 2 for s in step]
        else:
            break
        w, loss, grad, hess = trial, trial_loss, trial_grad, trial_hess
    return w, mean, sd, len(usable)


def cases_name(path):
    """The cases' path from the repository's root if they lie in it, else their file name."""
    inside = os.path.relpath(os.path.abspath(path), ROOT)
    return os.path.basename(path) if inside.startswith("..") else inside


def significant(v):
    """A float at 9 significant digits: ties of the last bit between machines do not show."""
    return float(f"{v:.9g}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    cases_cmd = commands.add_parser("cases", help="write the blind search's accepted blobs of some runs as rows")
    cases_cmd.add_argument("runs", nargs="+", metavar="ANATOMY=DIR")
    cases_cmd.add_argument("--min-diameter-mm", type=float, default=10.0)
    cases_cmd.add_argument("--out", required=True)
    fit_cmd = commands.add_parser("fit", help="learn the ranking's weights from the rows")
    fit_cmd.add_argument("cases")
    fit_cmd.add_argument("--penalty", type=float, default=1.0, help="the L2 penalty on the standardised weights")
    fit_cmd.add_argument("--out", required=True)
    args = parser.parse_args()
    if args.command == "cases":
        rows = []
        for run in args.runs:
            anatomy, eq, folder = run.partition("=")
            if not eq or not anatomy.isdigit():
                sys.exit(f"{run!r}: write ANATOMY=DIR, the phantom seed the run drew and its out_dir (e.g. 3=out-seed3)")
            rows += read_run(int(anatomy), folder, args.min_diameter_mm)
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
        print(f"{args.out}: {len(rows)} blobs of {len({(r['anatomy'], r['patient']) for r in rows})} nodules")
        return
    cases = read_cases(args.cases)
    w, mean, sd, used = fit(cases, args.penalty)
    model = {
        "what": "The blind blob search's ranking (select.blob.blind_tie_break = \"learned\"): the accepted blob "
                "of highest Σ weights · (feature − mean) / sd is taken.",
        "trained_by": f"tools/train_blob_ranker.py fit {cases_name(args.cases)} --penalty {args.penalty}",
        "anatomies": sorted({a for a, _, _, _ in cases}),
        "nodules": len(cases),
        "nodules_with_a_blob_on_them": used,
        "blobs": sum(len(on) for _, _, _, on in cases),
        "penalty": args.penalty,
        "reference_diameter_mm": REFERENCE_DIAMETER_MM,
        "depth_cap_mm": DEPTH_CAP_MM,
        "features": list(FEATURES),
        "mean": [significant(v) for v in mean],
        "sd": [significant(v) for v in sd],
        "weights": [significant(v) for v in w],
    }
    with open(args.out, "w") as f:
        f.write(json.dumps(model, indent=2, ensure_ascii=False) + "\n")
    print(f"{args.out}: weights from {used} of {len(cases)} nodules on anatomies {model['anatomies']}")
    for name, v in zip(FEATURES, model["weights"]):
        print(f"  {name:36s} {v:+.3f}")


if __name__ == "__main__":
    main()
