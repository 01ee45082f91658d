#!/usr/bin/env python3
"""Experiment: ordered subsets for the dense fit. Each step uses one view's rays (a third of the
products), its data term scaled by the number of views, with the shipped majoriser's per-node
step (OS-SQS, Erdogan and Fessler 1999) and Nesterov's momentum with the gradient restart
(Kim, Ramani and Fessler 2015). After `--epochs` passes over the views it continues with full
steps, the shipped solve, so the minimiser is the same. Prints the full energy after each epoch
and how many view-products it took to come within 1e-4 of the shipped fit's energy.

    python3 lab/scripts/dense_os.py DIR TARGET_E [--epochs 60] [--full 300]

DIR and TARGET_E as for `lab/scripts/dense_lbfgs.py`; the solve is `tools/dense_fit_peer.py`'s.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tools"))
from dense_fit_peer import Fista, Problem, solve  # noqa: E402

VIEWS = 3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("target", type=float)
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--full", type=int, default=300)
    args = ap.parse_args()
    p = Problem(args.dir)
    per_view = len(p.tau) // VIEWS
    subsets = [p.rows(slice(v * per_view, (v + 1) * per_view)) for v in range(VIEWS)]
    curvatures = [p.curvature_of(rows, VIEWS) for rows in subsets]
    started = time.perf_counter()
    fista = Fista(np.zeros((p.n,) * 3))
    products, trace = 0, []  # view-products: one view's A and Aᵀ
    for epoch in range(1, args.epochs + 1):
        for rows, curvature in zip(subsets, curvatures):
            fista.step(lambda s, rows=rows: p.data_gradient(s, rows, VIEWS), curvature, p.mu, p.eps)
            products += 1
        e = p.energy(fista.sigma)
        trace.append((products, e))
        print(f"epoch {epoch}: {products} view-products, E {e:.9e} ({e / args.target - 1:+.2e})", flush=True)

    def after_full(k, sigma):
        if k % 10 == 0:
            e = p.energy(sigma)
            trace.append((products + VIEWS * k, e))
            print(f"full step {k}: {products + VIEWS * k} view-products, E {e:.9e} ({e / args.target - 1:+.2e})",
                  flush=True)

    solve(p, args.full, 0.0, sigma=fista.sigma, on_step=after_full)
    within = next((n for n, e in trace if e <= args.target * (1 + 1e-4)), None)
    print(json.dumps({
        "epochs": args.epochs,
        "view_products_to_within_1e-4": within,
        "full_step_equivalents": within / VIEWS if within else None,
        "final_over_target": trace[-1][1] / args.target - 1,
        "seconds": time.perf_counter() - started,
    }))


if __name__ == "__main__":
    main()
