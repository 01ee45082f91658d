#!/usr/bin/env python3
"""Calibrates the half-maximum sizing on spheres of known size, outside the cohorts it is used on.

    lab/scripts/calibrate_sizing.py                       # lab/presets/calibration_spheres.toml, the ladder below
    lab/scripts/calibrate_sizing.py --fractions 0.4 0.5   # other fractions
    lab/scripts/calibrate_sizing.py --no-run              # re-read the out dirs already written
    lab/scripts/calibrate_sizing.py --preset pipeline.toml --fractions 0.4   # measure a fraction on a cohort

Runs the calibration preset once per `[select.half_max] fraction` on the ladder (`aret-pipe run
PRESET --set select.half_max.fraction=F`, each into the preset's out dir + `-fF`; the phantoms,
views and fits are cached after the first; each further fraction recomputes only select and
metrics), reads every run's results.csv, and prints, per fraction, how the guided rule's hits
size the spheres: the median ratio of measured to true volume, the median APE and the hit count.
The calibrated fraction is the one whose median ratio is nearest 1: the rule sizes a nodule of
known shape without bias. It is chosen here, on spheres, and only then applied to a cohort.
The preset must size at half maximum or by the shadows (`[select] sizing`), which read the
fraction.

`--json FILE` also writes every number (per fraction and per sphere); `--plot FILE.png` draws
each sphere's measured-to-true volume ratio against its diameter at the shipped fraction (0.5)
and the calibrated one (needs matplotlib; everything else needs only the standard library).
"""
import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
from preset_config import load_absolute, toml_value

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LADDER = [round(0.25 + 0.025 * n, 3) for n in range(15)]  # 0.25 … 0.60
# The sizings that cut the half-maximum region (and read [select.half_max]); the built-in one.
HALF_MAX_SIZINGS, DEFAULT_SIZING = ("half_max", "shadows"), "shadows"


def run_at(preset, fraction):
    """The `--set` arguments that run `preset` at `[select.half_max] fraction = fraction` into
    its own out dir (the preset's + `-fF`), and that out dir."""
    cfg = load_absolute(preset)
    sizing = cfg.get("select", {}).get("sizing", DEFAULT_SIZING)
    if sizing not in HALF_MAX_SIZINGS:
        sys.exit(f"{preset}: [select] sizing = {sizing!r} reads no [select.half_max] fraction: "
                 "calibrate a preset with sizing = \"half_max\" or \"shadows\"")
    pipeline = cfg["pipeline"]
    out = pipeline["out_dir"] + f"-f{fraction:.3f}"
    name = f"{pipeline.get('name', 'calibration')} at {fraction:.3f}"
    sets = [f"select.half_max.fraction={fraction!r}", f"pipeline.out_dir={toml_value(out)}",
            f"pipeline.name={toml_value(name)}"]
    return [a for s in sets for a in ("--set", s)], out


def spheres(out):
    """Per sphere: true and measured (guided) volume, hit, Dice, from a run's results.csv."""
    rows = []
    with open(os.path.join(out, "results.csv")) as f:
        for r in csv.DictReader(f):
            pred = float(r["pred_volume_mm3"]) if r["pred_volume_mm3"] else None
            rows.append({
                "patient": r["patient"],
                "gt_volume_mm3": float(r["gt_volume_mm3"]),
                "gt_diameter_mm": float(r["gt_diameter_mm"]),
                "pred_volume_mm3": pred,
                "hit": r["hit"] == "1",
                "dice": float(r["dice"]) if r["dice"] else None,
            })
    return rows


def summarise(rows):
    hits = [r for r in rows if r["hit"] and r["pred_volume_mm3"]]
    ratios = [r["pred_volume_mm3"] / r["gt_volume_mm3"] for r in hits]
    return {
        "hits": len(hits),
        "spheres": len(rows),
        "median_ratio": statistics.median(ratios) if ratios else None,
        "median_ape_pct": statistics.median(abs(q - 1) * 100 for q in ratios) if ratios else None,
        "median_dice": statistics.median(r["dice"] for r in hits) if hits else None,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default=os.path.join(ROOT, "lab", "presets", "calibration_spheres.toml"))
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "aret-pipe"))
    ap.add_argument("--fractions", type=float, nargs="+", default=LADDER)
    ap.add_argument("--no-run", action="store_true", help="only read the out dirs already written")
    ap.add_argument("--json", help="also write every number here")
    ap.add_argument("--plot", help="also draw the ratios against diameter here (PNG; needs matplotlib)")
    args = ap.parse_args()

    results = {}
    preset = os.path.abspath(args.preset)
    for fraction in args.fractions:
        sets, out = run_at(preset, fraction)
        if not args.no_run:
            subprocess.run([args.binary, "run", preset, *sets], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        if not os.path.exists(os.path.join(out, "results.csv")):
            sys.exit(f"{out} has no results.csv: run without --no-run first")
        rows = spheres(out)
        results[fraction] = {"summary": summarise(rows), "spheres": rows}

    print("| [select.half_max] fraction | guided hits | median volume ratio (hits) | median APE (hits) | median Dice |")
    print("| --- | --- | --- | --- | --- |")
    for fraction, r in results.items():
        s = r["summary"]
        fmt = lambda v, f: "–" if v is None else f.format(v)
        print(f"| {fraction:.3f} | {s['hits']}/{s['spheres']} | {fmt(s['median_ratio'], '{:.3f}')} "
              f"| {fmt(s['median_ape_pct'], '{:.1f} %')} | {fmt(s['median_dice'], '{:.2f}')} |")
    scored = [(abs(math.log(r["summary"]["median_ratio"])), f) for f, r in results.items()
              if r["summary"]["median_ratio"]]
    if not scored:
        sys.exit("no fraction hit a sphere: nothing to calibrate")
    best = min(scored)[1]
    # Only on a calibration cohort is this a calibration; on a cohort under study it is a
    # measurement (the value must not be chosen there).
    print(f"\nmedian volume ratio nearest 1 at [select.half_max] fraction {best:.3f} "
          f"({results[best]['summary']['median_ratio']:.3f} over {results[best]['summary']['hits']} hits)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"calibrated": best, "fractions": {f"{k:.3f}": v for k, v in results.items()}}, f, indent=1)
    if args.plot:
        plot(results, sorted({0.5, best} & set(results)), args.plot)


def plot(results, fractions, path):
    """Measured / true volume of every sphere against its diameter, hits filled, misses hollow."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for fraction, marker in zip(fractions, "os^"):
        rows = [r for r in results[fraction]["spheres"] if r["pred_volume_mm3"]]
        for hit in (True, False):
            pts = [(r["gt_diameter_mm"], r["pred_volume_mm3"] / r["gt_volume_mm3"]) for r in rows if r["hit"] == hit]
            if pts:
                ax.scatter(*zip(*pts), marker=marker, s=36, label=f"{fraction:.3f}" + ("" if hit else ", miss (another object)"),
                           facecolors=None if hit else "none", edgecolors=f"C{fractions.index(fraction)}",
                           color=f"C{fractions.index(fraction)}")
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_yscale("log")
    ax.set_ylim(0.3, 4.0)
    ticks = [0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0]
    ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
    ax.minorticks_off()
    ax.set_xlabel("sphere's annotated diameter (mm)")
    ax.set_ylabel("measured / true volume (guided rule)")
    ax.set_title("Half-maximum sizing on the calibration spheres, by [select.half_max] fraction", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":
    main()
