#!/usr/bin/env python3
"""Experiment: how many gradient evaluations does a quasi-Newton solver (scipy's L-BFGS-B, σ ≥ 0)
need to reach the shipped FISTA's energy on the dense fit's own problem?

The shipped solver takes 386-500 FISTA steps at 128³ (each one `A` and one `Aᵀ`) after a 64³
start. A solver that reaches the same minimum in a third of the products would bring a fit near
the 3 s a patient the issue asks for. This runs the objective of `tools/dense_fit_peer.py` (its
`Problem`) from zero and prints the energy against the evaluations.

    python3 lab/scripts/dense_lbfgs.py DIR TARGET_E [--evals 600] [--memory 10]

DIR holds `problem.json` and `rays.f64` as `bench_dense_fit` writes them for its peer (run it
with `--python` pointing at a script that copies them); TARGET_E is the shipped fit's final
energy that `bench_dense_fit` printed.
"""

import argparse
import json
import os
import sys
import time

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tools"))
from dense_fit_peer import Problem, tv_parts  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("target", type=float)
    ap.add_argument("--evals", type=int, default=600)
    ap.add_argument("--memory", type=int, default=10)
    args = ap.parse_args()
    p = Problem(args.dir)
    shape = (p.n,) * 3
    evals = []

    def energy(x):
        s = x.reshape(shape)
        r = np.where(p.seen, p.A @ x - p.tau, 0.0)
        m, g_tv = tv_parts(s, p.eps)
        e = (r**2).sum() / (2 * p.B) + p.mu * m.sum()
        g = (p.A.T @ r) / p.B + p.mu * g_tv.ravel()
        evals.append(e)
        if len(evals) % 25 == 0:
            print(f"eval {len(evals)}: E {e:.9e} ({e / args.target - 1:+.2e} of the target)", flush=True)
        return e, g

    started = time.perf_counter()
    minimize(energy, np.zeros(p.n**3), jac=True, method="L-BFGS-B", bounds=[(0.0, None)] * p.n**3,
             options={"maxfun": args.evals, "maxiter": args.evals, "maxcor": args.memory, "ftol": 0.0, "gtol": 0.0})
    reached = [i + 1 for i, e in enumerate(evals) if e <= args.target * (1 + 1e-4)]
    best = min(evals)
    print(json.dumps({
        "evaluations": len(evals),
        "best_energy": best,
        "best_over_target": best / args.target - 1,
        "evaluations_to_within_1e-4": reached[0] if reached else None,
        "evaluations_to_target": next((i + 1 for i, e in enumerate(evals) if e <= args.target), None),
        "seconds": time.perf_counter() - started,
    }))


if __name__ == "__main__":
    main()
