#!/usr/bin/env python3
"""Issue 8's experiment table: one row per configuration, re-run from the shared cache.

    lab/scripts/experiments.py                 # run every configuration, then write lab/log.md
    lab/scripts/experiments.py --only tv3d     # run the named rows only (the table keeps the others)
    lab/scripts/experiments.py --no-run        # rebuild the table from the results already in out dirs

A row whose out dir is not on this machine keeps its line from the table as it stands.

Every configuration is a preset in presets/ (or pipeline.toml itself) run with
`aret-pipe run`; presets share cache/, so a row that changes only a downstream stage recomputes
only that stage. The numbers are read back from each run's summary.json and results.csv.
Only the standard library is needed.

The rows are the lab's experiments as of tag lab-v1, and they re-run there: most of their
presets (default_seed2, phantom_union_256, drr128, …) and the keys they set are gone from this
checkout, and a preset that kept its name may now hold another configuration. A row whose
preset is missing here is not run: the script says so and keeps the row's line. To re-run it:
`git checkout lab-v1`, then `tools/experiments.py --only NAME` (the script's place there).
"""
import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import time

from preset_config import load_absolute

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# (name, config, assistance level of the primary rule, assistance of the blind rule, what it is)
ROWS = [
    ("paper", "presets/paper.toml", "B", "C*",
     "the paper as written: f = 1280, global percentile sweep, closest-diameter rule"),
    ("faithful", "presets/faithful.toml", "B", "C*",
     "the previous default: the paper's method with the fitted focal length"),
    ("tv3d", "presets/tv3d.toml", "B", "C*",
     "+ 3-D TV (λ = 1e-4) on the composed field during training"),
    ("lungs-contrast", "presets/lungs_contrast.toml", "B", "C*",
     "+ sweep of the local contrast inside the lung field found in σ"),
    ("find-then-size", "presets/tensorf.toml", "B", "C*",
     "+ blob centre (the Hessian's) inside the lung field first, then the candidates holding it, on TensoRF's VM"
     " field (the default until 2026-11-26)"),
    ("find-then-size-A", "presets/origin.toml", "A", "A",
     "the same, centred on the scene origin (= the nodule with roi_center = \"nodule\")"),
    ("blind", "presets/blind.toml", "C", "C",
     "the default method, scene centred on the lungs (roi_center = \"lungs\"), blind rule primary"),
    ("blind-chest", "presets/blind_chest.toml", "C", "C",
     "the same, with a box that holds the whole chest (380 × 280 × 400 mm) instead of the paper's"),
    ("tv3d-strong", "presets/tv3d_strong.toml", "B", "C*",
     "the default with ten times the 3-D TV (λ = 1e-3)"),
    ("log-loss", "presets/log_loss.toml", "B", "C*",
     "the default with the photometric loss on optical depths (−ln Î against −ln I)"),
    ("rank-32", "presets/rank32.toml", "B", "C*",
     "the default with rank 32 per plane/line pair instead of 16"),
    ("l1-strong", "presets/l1_strong.toml", "B", "C*",
     "the default with ten times the L1 weight on the factors (λ1 = 1e-3)"),
    ("iters-6000", "presets/iters6000.toml", "B", "C*",
     "the default trained for 6000 iterations instead of 3000"),
    ("lr-high", "presets/lr_high.toml", "B", "C*",
     "the default with twice the learning rate (0.04, same decay)"),
    ("grid-128", "presets/grid128.toml", "B", "C*",
     "the default on a 128³ lattice instead of 64³ (same box and views)"),
    ("blob-laplacian", "presets/blob_laplacian.toml", "B", "C*",
     "the default with the blob search on the Laplacian of Gaussian instead of the Hessian (the default until 2026-11-26)"),
    ("dense-tv", "presets/dense_tv.toml", "B", "C*",
     "the default with σ fitted as a dense 64³ lattice under a smoothed 3-D TV (FISTA on the optical depths)"
     " instead of TensoRF's VM factors"),
    ("dense-tv-128", "presets/dense_tv_128.toml", "B", "C*",
     "the dense model on a 128³ lattice (same box, views and λ), sized by the paper's rules among the"
     " sweep's candidates"),
    ("half-max", "presets/half_max.toml", "B", "C*",
     "the same field fitted to views of 256 × 256 pixels instead of 128 × 128, each rule sizing its centre at"
     " half maximum (sizing = \"half_max\"), on the phantom whose nodules are their 50 % consensus: the default"
     " until late on 2026-11-26"),
    ("strongest-blob", "presets/strongest_blob.toml", "B", "C*",
     "the same, each rule's half-maximum region then sized by the ellipsoid that best explains its shadows in"
     " the three views (sizing = \"shadows\"): the default from late on 2026-11-26 until 2026-11-27"),
    ("blind-roundness", "presets/blind_roundness.toml", "B", "C*",
     "the same, each search taking, among the blobs that answer alike (at 0.7 of the strongest or more), the one"
     " whose half-maximum region is roundest (tie_break = \"roundness\"): the default until 2026-11-27 (stop 42)"),
    ("default", "pipeline.toml", "B", "C*",
     "the same, the blind search ranking its five strongest blobs by ln(response / peak score) + 3 × roundness"
     " (blind_tie_break = \"score\"): the default"),
    ("default-A", "presets/default_origin.toml", "A", "A",
     "the default centred on the scene origin (= the nodule with roi_center = \"nodule\")"),
    ("perfect-field", "presets/perfect_field.toml", "B", "C*",
     "a ceiling, not a method: the default with its fit replaced by the true CT averaged over each cell of"
     " the same lattice ([train] model = \"truth\"), the field a perfect fit would reach"),
    ("default-seed2", "presets/default_seed2.toml", "B", "C*",
     "the default on a second anatomy of the same patients (phantom seed 2)"),
    ("default-seed3", "presets/default_seed3.toml", "B", "C*",
     "the default on a third anatomy (phantom seed 3), first trained after the roundness tie-break was fixed"),
    ("default-seed4", "presets/default_seed4.toml", "B", "C*",
     "the default on a fourth anatomy (phantom seed 4), first trained after the roundness tie-break was fixed"),
    ("default-seed5", "presets/default_seed5.toml", "B", "C*",
     "the default on a fifth anatomy (phantom seed 5), first trained after every rule of the shipped select was fixed; it led guided_faint_ratio from 0.5 to 0.2"),
    ("default-seed6", "presets/default_seed6.toml", "B", "C*",
     "the default on a sixth anatomy (phantom seed 6), first trained after that: held out from every choice"),
    ("bregman", "presets/bregman.toml", "B", "C*",
     "the default with one Bregman step on its dense fit (dense_tv_bregman_steps = 1): a second solve from the"
     " first σ, fitting the depths plus the views' residual"),
    ("reweighted-l1", "presets/reweighted_l1.toml", "B", "C*",
     "the default with one reweighted-L1 solve on its dense fit (dense_tv_reweight_steps = 1, dense_tv_sparsity ="
     " 3e-2): a second solve from the first σ with μ/N³ Σ η/(σ + η) σ added, drawing ambiguous mass into dense objects"),
    ("default-blind-chest", "presets/default_blind_chest.toml", "C", "C",
     "the default fully blind: the whole-chest box of blind-chest around the lungs' centroid"),
    ("tiles", "presets/tiles.toml", "C", "C",
     "the default fully blind by tiling: the paper's box at 2 × 3 × 3 points over the lungs, each its own fit;"
     " each rule keeps the box whose centre scores most (response × depth in the lung field)"),
    ("tiles-gpu", "presets/tiles_gpu.toml", "C", "C",
     "tiles with its views and fits on a GPU (backend = \"gpu\"), eight patients at a time"),
    ("tiles-seed2", "presets/tiles_seed2.toml", "C", "C",
     "tiles on the second phantom anatomy (seed 2), a cohort the tiling's rule was not chosen on"),
    ("default-blind-chest-256", "presets/default_blind_chest_256.toml", "C", "C",
     "default-blind-chest on a 256³ lattice: cells of 1.5 × 1.1 × 1.6 mm, near the default's in the paper's box"),
    ("drr-128", "presets/drr128.toml", "B", "C*",
     "the default fitted to SPEC §3's views of 128 × 128 pixels (the default's views until the evening of 2026-11-26)"),
    ("phantom-readers", "presets/phantom_readers.toml", "B", "C*",
     "half-max's method at 128² views on a phantom whose nodules hold tissue in the fraction of readers"
     " who drew each voxel (the default phantom draws their 50 % consensus)"),
    ("phantom-readers-256", "presets/phantom_readers_256.toml", "B", "C*",
     "the same phantom with the default's views of 256 × 256 pixels"),
    ("phantom-union", "presets/phantom_union.toml", "B", "C*",
     "half-max's method at 128² views on the phantom as first built, whose nodules are the union of their"
     " readers' contours (most rows above the default were measured on it)"),
    ("phantom-union-256", "presets/phantom_union_256.toml", "B", "C*",
     "the same phantom with the default's views of 256 × 256 pixels (the default until the night of 2026-11-26)"),
    ("guided-scales", "presets/guided_scales.toml", "B", "C*",
     "half-max with the guided blob search at the matched scale and at 1/√2 of it"
     " (guided_scale_ratios = [0.71, 1.0])"),
    ("fine-box-A", "presets/fine_box.toml", "A", "A",
     "the fine half of coarse-to-fine, given the location: a 64 mm box (1 mm cells) centred on the nodule,"
     " rules through the origin"),
]
MEASURED = "experiment.json"
# Columns of the table, the row's name included.
COLUMNS = 14
# The column added last (0-based, after the row name's empty lead cell): rows kept from the doc
# that predate it get – there.
UNAMBIGUOUS_COLUMN = 7
# The phantom's nodule where a config does not name one (`[dataset.phantom] nodule_extent`):
# the built-in default. Rows the log kept from before it say "consensus", the default then;
# at lab-v1 it was "union".
DEFAULT_EXTENT = "readers"
# Where the rows re-run.
LAB_V1 = ("the experiment rows re-run at tag lab-v1, where every preset they name exists: "
          "`git checkout lab-v1`, then `tools/experiments.py --only NAME`")
START, END = "<!-- table: written by lab/scripts/experiments.py -->", "<!-- end of table -->"
LEVELS = {
    "A": "location and diameter known",
    "B": "diameter known (the guided rule)",
    "C": "blind: no annotation anywhere (roi_center = \"lungs\" or \"tiles\", blind rule)",
    "C*": "blind rule, but the box is still centred on the nodule (roi_center = \"nodule\")",
}


# Rows whose preset name lives on in the product with another configuration: they too re-run
# only at lab-v1, or a run here would write new numbers under the old description.
RENAMED_SINCE = {"presets/origin.toml", "presets/phantom_readers.toml"}


def missing(config):
    """Whether the row's config (relative to the repository) is not the one the row measured in
    this checkout: absent, or a product preset that kept the name with another configuration."""
    return config in RENAMED_SINCE or not os.path.exists(os.path.join(ROOT, config))


def out_dir(config_path):
    """The config's out dir, absolute (through the files it extends)."""
    return load_absolute(config_path)["pipeline"]["out_dir"]


def nodule_extent(config_path):
    """How the config's phantom draws each nodule: "union", "readers" or "consensus"."""
    return load_absolute(config_path)["dataset"].get("phantom", {}).get("nodule_extent", DEFAULT_EXTENT)


def run(binary, config_path):
    started = time.time()
    subprocess.run([binary, "run", config_path], check=True, cwd=ROOT)
    return time.time() - started


def train_seconds(out):
    """Each scored run's training seconds a patient (its boxes' together), from the run's own
    record: no published file holds a wall time."""
    report = json.load(open(os.path.join(out, "run_report.json")))
    per_patient = {}
    for r in report["records"]:
        if r["stage"] == "train" and "seconds" in r:
            patient = r["unit"].split("/")[0]
            per_patient[patient] = per_patient.get(patient, 0.0) + r["seconds"]
    return list(per_patient.values())


def commit():
    """The checkout's commit, marked `+changes` when a tracked file other than the table's own
    document differs from it."""
    git = lambda *a: subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!lab/log.md")
    return head + ("+changes" if changed else "")


def record_run(out, at):
    """Notes in the row's out dir which commit produced its numbers (the table's last column)."""
    with open(os.path.join(out, MEASURED), "w") as f:
        json.dump({"commit": at, "date": time.strftime("%Y-%m-%d")}, f)


def pct(x):
    return "–" if x is None else f"{100 * x:.0f}%"


def of(unambiguous):
    """The hits among the selections not flagged ambiguous, as "hits of n"."""
    return "–" if unambiguous is None else f"{unambiguous['hits']} of {unambiguous['n']}"


def count(rate, n):
    """A rate of n patients as "k/n"."""
    return "–" if rate is None else f"{round(rate * n)}/{n}"


def num(x, fmt="{:.1f}"):
    return "–" if x is None else fmt.format(x)


def value(stat):
    return stat.get("value") if isinstance(stat, dict) else None


def row_numbers(out):
    summary = json.load(open(os.path.join(out, "summary.json")))
    with open(os.path.join(out, "results.csv")) as f:
        rows = list(csv.DictReader(f))
    groups = summary["groups"]

    def group(name):
        g = groups[name]
        loc = g["localization"]
        return dict(
            n=g["n"],
            hit=loc["hit_rate_ours"],
            blind=loc["hit_rate_blind"],
            oracle=loc["hit_rate_oracle"],
            dice=loc["median_dice_ours"],
            # Absent from summaries written before metrics v4.
            centre_guided=loc.get("centre_rate_guided"),
            centre_blind=loc.get("centre_rate_blind"),
            # Absent from summaries written before metrics v8 (select v15).
            unambiguous=loc.get("unambiguous_ours"),
            ape_all=value(g["ours"]["all"]["median_ape_pct"]),
            ape_hits=value(g["ours"]["over_hits"]["median_ape_pct"]),
            blind_ape_hits=value(g["blind"]["over_hits"]["median_ape_pct"]),
        )

    hits = [r for r in rows if r["hit"] == "1"]
    beats = sum(float(r["ape_pct"]) < float(r["sphere_ape_pct"]) for r in hits)
    seconds = train_seconds(out)
    measured = os.path.join(out, MEASURED)
    at = json.load(open(measured))["commit"] if os.path.exists(measured) else None
    return dict(
        at=at,
        ge10=group("ge10mm"),
        all=group("all"),
        hits_beating_sphere=f"{beats}/{len(hits)}",
        train_s=statistics.median(seconds) if seconds else None,
    )


def rows_in(doc):
    """The table's current line per row name, kept for rows whose results are not on disk (their
    out dir was never run on this machine, or was cleaned) instead of blanking them."""
    kept = {}
    for line in doc.split(START, 1)[-1].split(END, 1)[0].splitlines():
        cells = [c.strip() for c in line.split("|")]
        if len(cells) > 2 and any(cells[1] == name for name, *_ in ROWS):
            if len(cells) == COLUMNS + 1:  # written before the unambiguous column
                cells.insert(UNAMBIGUOUS_COLUMN, "–")
                line = " | ".join(cells).strip()
            kept[cells[1]] = line
    return kept


def table(results, kept):
    lines = [
        "| row | config | phantom nodule | level (primary / blind) | ≥10 mm hit: primary / blind / oracle"
        " | ≥10 mm centre on the nodule: guided / blind | ≥10 mm primary hits of those not ambiguous | ≥10 mm median Dice"
        " | median APE: all / ≥10 mm / ≥10 mm over hits | blind APE over hits (≥10 mm) | all 19: hit / blind"
        " | hits beating the sphere | train s (median) | measured at |",
        "|" + " --- |" * COLUMNS,
    ]
    for name, config, level, blind_level, _ in ROWS:
        r = results.get(name)
        # A config missing here (its row re-runs at lab-v1) names no phantom.
        extent = "–" if missing(config) else nodule_extent(os.path.join(ROOT, config))
        if r is None:
            status = "only at lab-v1" if missing(config) else "not run"
            lines.append(kept.get(name, f"| {name} | `{config}` | {extent} | {level} / {blind_level} | {status} |" + " |" * (COLUMNS - 5)))
            continue
        g, a = r["ge10"], r["all"]
        lines.append(
            f"| {name} | `{config}` | {extent} | {level} / {blind_level} | {pct(g['hit'])} / {pct(g['blind'])} / {pct(g['oracle'])}"
            f" | {count(g['centre_guided'], g['n'])} / {count(g['centre_blind'], g['n'])} | {of(g['unambiguous'])} | {num(g['dice'], '{:.2f}')} | {num(a['ape_all'])}% / {num(g['ape_all'])}% / {num(g['ape_hits'])}%"
            f" | {num(g['blind_ape_hits'])}% | {pct(a['hit'])} / {pct(a['blind'])} | {r['hits_beating_sphere']}"
            f" | {num(r['train_s'])} | {r['at'] or '–'} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", help="row names to (re)run")
    ap.add_argument("--no-run", action="store_true", help="only rebuild the table")
    ap.add_argument("--bin", default=os.path.join(ROOT, "target", "release", "aret-pipe"))
    ap.add_argument("--doc", default=os.path.join(ROOT, "lab", "log.md"))
    args = ap.parse_args(argv)
    names = [name for name, *_ in ROWS]
    unknown = [name for name in args.only or [] if name not in names]
    if unknown:
        sys.exit(f"no row {', '.join(unknown)}: the rows are {', '.join(names)}")
    absent = [(name, config) for name, config, *_ in ROWS if missing(config)]
    if not args.no_run:
        asked = [(name, config) for name, config in absent if not args.only or name in args.only]
        listed = ", ".join(f"{name} ({config})" for name, config in asked)
        if args.only and asked:
            # Before running anything: the rows asked for cannot all run here.
            sys.exit(f"{listed}: not in this checkout; {LAB_V1}")
        if asked:
            print(f"not run, their presets are not in this checkout: {listed};\n{LAB_V1}", file=sys.stderr,
                  flush=True)
    results = {}
    for name, config, *_ in ROWS:
        path = os.path.join(ROOT, config)
        if (name, config) in absent:
            continue  # the table keeps its line
        if not args.no_run and (not args.only or name in args.only):
            print(f"== {name}: aret-pipe run {config}", flush=True)
            at = commit()  # the code that runs, even if the checkout moves on meanwhile
            print(f"   {run(args.bin, path):.0f} s", flush=True)
            record_run(out_dir(path), at)
        out = out_dir(path)
        if os.path.exists(os.path.join(out, "summary.json")):
            results[name] = row_numbers(out)
    doc = open(args.doc).read()
    if START not in doc or END not in doc:
        sys.exit(f"{args.doc} has no {START} … {END} block to fill")
    text = table(results, rows_in(doc))
    legend = "\n".join(f"- **{k}**: {v}" for k, v in LEVELS.items())
    rows = "\n".join(f"- **{name}**: {what}" for name, _, _, _, what in ROWS)
    block = f"{START}\n{text}\n\nRows:\n{rows}\n\nAssistance levels:\n{legend}\n{END}"

    head, rest = doc.split(START, 1)
    with open(args.doc, "w") as f:
        f.write(head + block + rest.split(END, 1)[1])
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
