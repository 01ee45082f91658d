#!/usr/bin/env python3
"""One [select] variant on every set of fits the experiments cached: hits ≥ 10 mm per set.

    lab/scripts/select_study.py line-0.5 'rival_ratio = 0.5'          # run it on the nine sets
    lab/scripts/select_study.py line-0.5 'rival_ratio = 0.5' --sets consensus-1,spheres-2
    lab/scripts/select_study.py shipped ''                             # the shipped select itself
    lab/scripts/select_study.py line-0.5 'rival_ratio = 0.5' --no-run  # summarise what is on disk

Each set is a preset's phantom, views and fit, sized by the shipped select (`pipeline.toml`'s
[select]) with the variant's keys on top. Only select and metrics recompute: with every fit in
cache/ the nine sets take about five minutes on two cores (a set whose fits are not cached
trains first: 15–20 minutes). lab/log.md's select-only tables over "the nine sets"
were measured this way. Two more sets are held out (`--sets views128-consensus,views128-union`:
fits to SPEC §3's 128² views, on which no rule was chosen): run them to check a rule the nine
chose. Out dirs: out-study/NAME/SET/. Only the standard library is needed.

With --perfect-field every set's fit is replaced by the true CT on the same lattice
(`[train] model = "truth"`, a ceiling: lab/log.md, "A perfect field"): what the select
finds when the reconstruction is not the limit, in about 2 minutes a set (no training).
"""
import argparse
import csv
import os
import statistics
import subprocess
import sys
import tomllib

from preset_config import load_absolute, toml_text

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# (set, preset, keys set on top of the preset, as {table: {key: value}})
SETS = [
    ("consensus-1", "pipeline.toml", {}),
    ("consensus-2", "presets/default_seed2.toml", {}),
    ("consensus-3", "presets/default_seed3.toml", {}),
    ("consensus-4", "presets/default_seed4.toml", {}),
    ("union-1", "presets/phantom_union_256.toml", {}),
    ("union-2", "presets/phantom_union_256.toml", {"dataset.phantom": {"seed": 2}}),
    ("readers", "presets/phantom_readers_256.toml", {}),
    ("spheres-1", "presets/calibration_spheres.toml", {}),
    ("spheres-2", "presets/calibration_spheres.toml", {"dataset.phantom": {"seed": 2}}),
]
# Held out: fits no select rule was chosen on (SPEC §3's 128² views, on the consensus and the
# union phantom; the fifth to eighth consensus anatomies, first trained at stop 48, the ninth at
# stop 49). Run only
# when --sets names them, so that they stay held out.
HELD_OUT = [
    ("views128-consensus", "presets/drr128.toml", {}),
    ("views128-union", "presets/phantom_union.toml", {}),
    ("consensus-5", "presets/default_seed5.toml", {}),
    ("consensus-6", "presets/default_seed6.toml", {}),
    ("consensus-7", "presets/default_seed6.toml", {"dataset.phantom": {"seed": 7}}),
    ("consensus-8", "presets/default_seed6.toml", {"dataset.phantom": {"seed": 8}}),
    # Trained at stop 49 (2026-11-28) with nothing looked at but the fit: kept for judging
    # `roundness_opening` (lab/log.md, "A perfect field").
    ("consensus-9", "presets/default_seed6.toml", {"dataset.phantom": {"seed": 9}}),
]


def study_config(preset, overrides, variant, out_dir, perfect_field=False):
    """The preset at `preset` (relative to the repository) with `overrides`, the shipped
    [select] and then `variant` (TOML text of [select] keys) on top, writing to `out_dir`;
    every path absolute. With `perfect_field`, the true CT on the fit's lattice instead of it."""
    config = load_absolute(os.path.join(ROOT, preset))
    if perfect_field:
        overrides = {**overrides, "train": {"model": "truth"}}
    for dotted, keys in overrides.items():
        t = config
        for part in dotted.split("."):
            t = t.setdefault(part, {})
        t.update(keys)
    shipped = load_absolute(os.path.join(ROOT, "pipeline.toml")).get("select", {})
    config["select"] = {**shipped, **tomllib.loads(variant)}
    config["pipeline"]["out_dir"] = out_dir
    return config


def summarise(out):
    with open(os.path.join(out, "results.csv")) as f:
        rows = list(csv.DictReader(f))
    big = [r for r in rows if float(r["gt_diameter_mm"]) >= 10]
    hits = [r for r in big if r["hit"] == "1"]
    ape = statistics.median(float(r["ape_pct"]) for r in hits) if hits else float("nan")
    beat = sum(r["hit"] == "1" and float(r["ape_pct"]) < float(r["sphere_ape_pct"]) for r in rows)
    return {"n": len(big), "guided": len(hits), "blind": sum(r["blind_hit"] == "1" for r in big),
            "ape": ape, "beat": beat, "hits_all": sum(r["hit"] == "1" for r in rows)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", help="the study's name (its out dirs: out-study/NAME/SET)")
    ap.add_argument("variant", help="[select] keys as TOML, ';' between keys: 'rival_ratio = 0.5; …'")
    ap.add_argument("--sets", help="comma-separated sets (default: the nine): "
                    + ", ".join(s for s, *_ in SETS + HELD_OUT))
    ap.add_argument("--no-run", action="store_true", help="summarise the out dirs already written")
    ap.add_argument("--perfect-field", action="store_true",
                    help="the true CT on each fit's lattice instead of the fit (a ceiling, no training)")
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "aret-pipe"))
    args = ap.parse_args()
    wanted = args.sets.split(",") if args.sets else [s for s, *_ in SETS]
    known = SETS + HELD_OUT
    unknown = set(wanted) - {s for s, *_ in known}
    if unknown:
        sys.exit(f"unknown set(s) {', '.join(sorted(unknown))}: choose from {', '.join(s for s, *_ in known)}")
    variant = args.variant.replace(";", "\n")
    total = {"n": 0, "guided": 0, "blind": 0}
    print(f"{'set':<18} {'≥10 mm':>6} {'guided':>6} {'blind':>6} {'APE over guided hits':>21} {'hits beating the sphere':>24}")
    for name, preset, overrides in known:
        if name not in wanted:
            continue
        out = os.path.join(ROOT, "out-study", args.name, name)
        if not args.no_run:
            os.makedirs(out, exist_ok=True)
            path = os.path.join(out, "config.toml")
            with open(path, "w") as f:
                f.write(toml_text(study_config(preset, overrides, variant, out, args.perfect_field)))
            r = subprocess.run([args.binary, "run", path], capture_output=True, text=True,
                               env={**os.environ, "CI": "true"})
            if r.returncode:
                sys.exit(f"{name}: aret-pipe run {path} failed:\n{r.stderr[-2000:]}")
        if not os.path.exists(os.path.join(out, "results.csv")):
            sys.exit(f"{out} has no results.csv: run without --no-run first")
        s = summarise(out)
        for k in total:
            total[k] += s[k]
        print(f"{name:<18} {s['n']:>6} {s['guided']:>6} {s['blind']:>6} {s['ape']:>20.1f}% {s['beat']:>17} of {s['hits_all']}")
    print(f"{'all':<18} {total['n']:>6} {total['guided']:>6} {total['blind']:>6}")


if __name__ == "__main__":
    main()
