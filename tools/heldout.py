#!/usr/bin/env python3
"""Choose a setting by leaving one anatomy out, and report only what the held-out anatomies say.

    tools/heldout.py pipeline.toml --seeds 1,2,3,4,5 --choose select.blob.rival_ratio=0.5,0.7,0.9
    tools/heldout.py pipeline.toml --seeds 1-8 --choose select.sizing=half_max,shadows \\
        --choose select.half_max.fraction=0.4,0.5 --out out-heldout
    tools/heldout.py pipeline.toml --seeds 1-8 --choose ... --no-run   # summarise what is on disk

An anatomy is the phantom cohort drawn with one `[dataset.phantom] seed`. Every candidate (one
value of each `--choose` key; several keys make a grid) runs on every anatomy:
`aret-pipe run CONFIG --set dataset.phantom.seed=S --set KEY=VALUE ... --set
pipeline.out_dir=OUT/seedS/CANDIDATE`, sharing CONFIG's cache, so the fits of an anatomy are
computed once and only what a key changes recomputes (a `[select]` key: seconds a cohort).

Then, for each anatomy in turn, the candidate that scores best on the *other* anatomies (the mean
of their scores) is chosen, and the held-out anatomy's figures under that choice are its
held-out figures. A score ranks, in order: the guided rule's centres on the nodule, the guided
hits, the blind rule's centres on the nodule, then the lower median APE over guided hits, each
over `--group` (`ge10mm` by default, `summary.json`'s groups). The figures reported are the
held-out ones, their mean, standard deviation and range over the anatomies, beside what the
candidate best on all anatomies scores on those same anatomies (in sample): the gap is the
choice's optimism. OUT/heldout.json holds every figure.
"""
import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BIN = os.environ.get("ARET_PIPE_BIN", os.path.join(ROOT, "target", "release", "aret-pipe"))
# (name in heldout.json, heading, how a summary group holds it)
FIGURES = (
    ("guided_centre", "guided centre on", lambda g: g["localization"]["centre_rate_guided"]),
    ("guided_hit", "guided hit", lambda g: g["localization"]["hit_rate_ours"]),
    ("blind_centre", "blind centre on", lambda g: g["localization"]["centre_rate_blind"]),
    ("blind_hit", "blind hit", lambda g: g["localization"]["hit_rate_blind"]),
    ("median_dice", "median Dice", lambda g: g["localization"]["median_dice_ours"]),
    ("median_ape_over_guided_hits_pct", "median APE over guided hits", lambda g: stat(g["ours"]["over_hits"]["median_ape_pct"])),
)
PERCENT = {"guided_centre", "guided_hit", "blind_centre", "blind_hit"}


def stat(s):
    """A summary statistic's value, or None where the summary says why it is undefined."""
    value = s.get("value") if isinstance(s, dict) else None
    return value.get("value") if isinstance(value, dict) else value


def seeds(text):
    """`1,2,5-8` as [1, 2, 5, 6, 7, 8]."""
    out = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        out.extend(range(int(low), int(high or low) + 1))
    if len(set(out)) < 2:
        raise SystemExit("--seeds: leaving one anatomy out needs two anatomies or more")
    return sorted(set(out))


def choice(text):
    """`section.key=v1,v2` as (key, [v1, v2]), each value TOML as `--set` reads it."""
    key, eq, values = text.partition("=")
    if not eq or "." not in key or not values:
        raise SystemExit(f"--choose {text!r}: write SECTION.KEY=VALUE1,VALUE2 (e.g. select.blob.rival_ratio=0.5,0.7)")
    return key.strip(), [v.strip() for v in values.split(",")]


def candidates(choices):
    """Every combination of one value per key: [(name, [(key, value), ...])]."""
    keys = [k for k, _ in choices]
    combos = itertools.product(*[values for _, values in choices])
    return [(",".join(f"{k}={v}" for k, v in zip(keys, combo)), list(zip(keys, combo))) for combo in combos]


def out_dir(out, seed, name):
    safe = "".join(c if c.isalnum() or c in "._=-," else "_" for c in name)
    return os.path.join(out, f"seed{seed}", safe)


def run(config, seed, settings, out, patients):
    command = [BIN, "run", config, "--set", f"dataset.phantom.seed={seed}", "--set", f"pipeline.out_dir={json.dumps(out)}"]
    for key, value in settings:
        command += ["--set", f"{key}={value}"]
    if patients:
        command += ["--patients", patients]
    print("$", " ".join(command), flush=True)
    done = subprocess.run(command, env={**os.environ, "CI": os.environ.get("CI", "true")})
    if done.returncode != 0:
        raise SystemExit(f"aret-pipe run failed for seed {seed} ({out}); its output is above")


def figures(out, group):
    """The figures of `group` in OUT's summary.json."""
    path = os.path.join(out, "summary.json")
    if not os.path.exists(path):
        raise SystemExit(f"{path} is missing: run without --no-run first")
    groups = json.load(open(path))["groups"]
    if group not in groups:
        raise SystemExit(f"{path} has no group {group!r}; it has {', '.join(sorted(groups))}")
    return {name: read(groups[group]) for name, _, read in FIGURES}


def score(f):
    """What a choice maximises, in order (a figure that is undefined counts as the worst)."""
    worst = lambda v, sign=1: sign * v if v is not None else -float("inf")
    return (worst(f["guided_centre"]), worst(f["guided_hit"]), worst(f["blind_centre"]),
            worst(f["median_ape_over_guided_hits_pct"], -1))


def mean_score(rows):
    """The mean of each part of the scores of `rows` (figures of several anatomies)."""
    return tuple(statistics.fmean(parts) for parts in zip(*(score(r) for r in rows)))


def best(table, names, anatomies):
    """The candidate with the best mean score over `anatomies` (ties to the first as listed)."""
    return max(names, key=lambda n: (mean_score([table[(a, n)] for a in anatomies]), -names.index(n)))


def leave_one_out(table, names, anatomies):
    """Per held-out anatomy: the candidate best on the others."""
    return {held: best(table, names, [a for a in anatomies if a != held]) for held in anatomies}


def spread(values):
    """Mean, standard deviation and range of the defined values (None where none is)."""
    values = [v for v in values if v is not None]
    if not values:
        return None
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return {"mean": statistics.fmean(values), "sd": sd, "min": min(values), "max": max(values), "n": len(values)}


def show(name, value):
    if value is None:
        return "–"
    return f"{100 * value:.0f} %" if name in PERCENT else f"{value:.2f}" if name == "median_dice" else f"{value:.1f} %"


def print_spread(label, spreads):
    """A table row of each figure's mean ± sd (range)."""
    def cell(f):
        s = spreads[f]
        return "–" if s is None else f"{show(f, s['mean'])} ± {show(f, s['sd'])} ({show(f, s['min'])}–{show(f, s['max'])})"
    print(f"| {label} | | " + " | ".join(cell(f) for f, _, _ in FIGURES) + " |")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config")
    parser.add_argument("--seeds", type=seeds, required=True, help="the anatomies: 1,2,3 or 1-8")
    parser.add_argument("--choose", type=choice, action="append", required=True, metavar="SECTION.KEY=V1,V2",
                        help="a key and the values to choose among (repeat for a grid)")
    parser.add_argument("--group", default="ge10mm", help="summary.json's group the choice and figures are over")
    parser.add_argument("--out", default="out-heldout")
    parser.add_argument("--patients", help="only these patients (as aret-pipe run --patients)")
    parser.add_argument("--no-run", action="store_true", help="summarise the out dirs already on disk")
    args = parser.parse_args()
    grid = candidates(args.choose)
    names = [n for n, _ in grid]
    table = {}
    for seed in args.seeds:
        for name, settings in grid:
            out = out_dir(args.out, seed, name)
            if not args.no_run:
                run(args.config, seed, settings, out, args.patients)
            table[(seed, name)] = figures(out, args.group)
    chosen = leave_one_out(table, names, args.seeds)
    held_out = {seed: table[(seed, chosen[seed])] for seed in args.seeds}
    in_sample = best(table, names, args.seeds)
    report = {
        "config": args.config,
        "group": args.group,
        "candidates": names,
        "anatomies": {str(s): {"chosen": chosen[s], "held_out": held_out[s]} for s in args.seeds},
        "held_out": {f: spread([held_out[s][f] for s in args.seeds]) for f, _, _ in FIGURES},
        "in_sample": {"chosen": in_sample,
                      "figures": {f: spread([table[(s, in_sample)][f] for s in args.seeds]) for f, _, _ in FIGURES}},
        "every_run": {f"seed{s}": {n: table[(s, n)] for n in names} for s in args.seeds},
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "heldout.json"), "w") as f:
        json.dump(report, f, indent=2)
    heads = [h for _, h, _ in FIGURES]
    values = {name: ", ".join(v for _, v in settings) for name, settings in grid}
    print(f"\n{args.group}, each anatomy under the candidate chosen on the others "
          f"(chosen: {', '.join(k for k, _ in args.choose)}):")
    print("| anatomy | chosen | " + " | ".join(heads) + " |")
    print("|" + " --- |" * (len(heads) + 2))
    for s in args.seeds:
        print(f"| {s} | {values[chosen[s]]} | " + " | ".join(show(f, held_out[s][f]) for f, _, _ in FIGURES) + " |")
    print_spread("held out: mean ± sd (range)", report["held_out"])
    print_spread(f"in sample ({values[in_sample]})", report["in_sample"]["figures"])
    print(f"\n{os.path.join(args.out, 'heldout.json')} holds every figure.")


if __name__ == "__main__":
    sys.exit(main())
