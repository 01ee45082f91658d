#!/usr/bin/env python3
"""Experiment: continuation in the TV's ε for the dense fit. The shipped ε (1e-3) makes the
majoriser's steps tiny wherever σ is flat; a fit at a larger ε is fast and lies near, so each
stage starts the next, and the last runs at the shipped ε to the shipped stop, so the minimiser
is the same. Prints, per stage, its steps and energy (at the shipped ε), and the total steps to
come within 1e-4 of the shipped fit's energy.

    python3 lab/scripts/dense_continuation.py DIR TARGET_E [--epsilons 1e-2,3e-3,1e-3]
        [--stage-tolerance 1e-3] [--steps 500]

DIR and TARGET_E as for `lab/scripts/dense_lbfgs.py`. Every stage is `tools/dense_fit_peer.py`'s
solve (the shipped FISTA), from zero for the first.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tools"))
from dense_fit_peer import Problem, solve  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("target", type=float)
    ap.add_argument("--epsilons", default="1e-2,3e-3,1e-3")
    ap.add_argument("--stage-tolerance", type=float, default=1e-3)
    ap.add_argument("--steps", type=int, default=500)
    args = ap.parse_args()
    p = Problem(args.dir)
    started = time.perf_counter()
    epsilons = [float(e) for e in args.epsilons.split(",")]
    sigma, total, reached = None, 0, None
    for i, eps in enumerate(epsilons):
        last = i == len(epsilons) - 1

        def watch(k, s):
            nonlocal reached
            if last and reached is None and k % 5 == 0 and p.energy(s) <= args.target * (1 + 1e-4):
                reached = total + k

        tol = p.params["tolerance"] if last else args.stage_tolerance
        sigma, steps = solve(p, args.steps, tol, sigma=sigma, eps=eps, on_step=watch)
        total += steps
        e = p.energy(sigma)
        print(json.dumps({"epsilon": eps, "steps": steps, "energy_at_shipped_epsilon": e,
                          "over_target": e / args.target - 1}), flush=True)
    print(json.dumps({"total_steps": total, "steps_to_within_1e-4": reached, "seconds": time.perf_counter() - started}))


if __name__ == "__main__":
    main()
