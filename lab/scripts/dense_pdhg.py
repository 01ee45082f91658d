#!/usr/bin/env python3
"""Experiment: does a primal–dual solver reach the dense fit's minimum in fewer products than FISTA?

FISTA's steps on E = 1/(2B) |Aσ − τ|² + λ/N³ Σ √(|∇σ|² + ε²), σ ≥ 0, are bounded by the smoothed
TV's curvature, up to 12 λ/(N³ ε) where the field is flat. Chambolle and Pock's primal–dual
method (diagonally preconditioned, Pock and Chambolle 2011) handles the TV through its dual,
whose prox is exact at any ε, so its steps do not shrink with ε. Each step costs one `A` and
one `Aᵀ`, as FISTA's. This runs it on the peer's problem (`tools/dense_fit_peer.py`'s `Problem`)
from zero and prints E against the steps, and the steps to within 1e-4 of TARGET_E.

On LIDC-IDRI-0001's problem the best pair found (c = 1e-4, γ = 3000, of c in 1e-7…1e-3 and γ in
0.1…1e4) is within 1e-4 after ≈ 500 steps, FISTA from zero after 425: the dual does not help.

K = [A/√B; c ∇]; primal steps γ/Σ_i |K_ij|, dual steps 1/(γ Σ_j |K_ij|): `--balance c` weighs
the TV's rows against the rays', `--gamma` the primal steps against the dual ones. `--fista`
runs the peer's FISTA from zero instead, for the reference curve.

    python3 lab/scripts/dense_pdhg.py DIR TARGET_E [--steps 600] [--balance 1e-4] [--gamma 1]
"""

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tools"))
from dense_fit_peer import Problem, gradient, gradient_adjoint, solve  # noqa: E402


def rows_of_gradient(n):
    """Where ∇ has a row (1) or none (0), per component."""
    on = np.zeros((3, n, n, n))
    on[0, :, :, :-1] = 1
    on[1, :, :-1, :] = 1
    on[2, :-1, :, :] = 1
    return on


def dual_tv_prox(p, kappa, radius):
    """prox of s F*, F(g) = μ √(|g/c|² + ε²) per node, at p: p's direction, its length R q with
    q − q' + κ q/√(1 − q²) = 0 (q' = |p|/R, κ = s ε c²/μ), solved in t = q/√(1 − q²) by Newton
    from t = 0 (g(t) = t/√(1 + t²) + κ t − q' is concave and increasing, so it never overshoots)."""
    length = np.sqrt((p * p).sum(0))
    q0 = length / radius
    t = np.zeros_like(q0)
    for _ in range(12):
        root = np.sqrt(1 + t * t)
        g = t / root + kappa * t - q0
        t = t - g / (1 / root**3 + kappa)
    q = t / np.sqrt(1 + t * t)
    scale = np.where(length > 0, radius * q / np.maximum(length, 1e-300), 0.0)
    return p * scale


def pdhg(p, steps, balance, gamma, on_step=None):
    """The preconditioned primal–dual solve of `p` (a `Problem`) from zero: `steps` steps,
    `on_step(k, σ)` after each. Returns σ."""
    n, shape, c = p.n, (p.n,) * 3, balance
    A, seen, tau, B, mu, eps = p.A, p.seen, p.tau, p.B, p.mu, p.eps
    on = rows_of_gradient(n)
    # Σ_i |K_ij| for node j: its column of A/√B, and c for each gradient row it enters (up to 6).
    touches = on.sum(0).copy()
    touches[:, :, 1:] += on[0, :, :, :-1]
    touches[:, 1:, :] += on[1, :, :-1, :]
    touches[1:, :, :] += on[2, :-1, :, :]
    # The rays' rows are A/√B, so that F₁(z) = ½ |z − τ/√B|².
    a = 1 / np.sqrt(B)
    column_sums = a * np.asarray(abs(A).sum(0)).reshape(shape) + c * touches
    primal_step = gamma / np.maximum(column_sums, 1e-300)
    ray_step = np.where(seen, 1.0 / (gamma * np.maximum(a * np.asarray(abs(A).sum(1)).ravel(), 1e-300)), 0.0)
    tv_step = 1.0 / (gamma * 2 * c)
    kappa = tv_step * eps * c * c / mu
    radius = mu / c
    x = np.zeros(shape)
    x_bar = x.copy()
    y = np.zeros(len(tau))
    q = np.zeros((3,) + shape)
    for step in range(1, steps + 1):
        y = y + ray_step * a * (A @ x_bar.ravel())
        y = np.where(seen, (y - ray_step * a * tau) / (1 + ray_step), 0.0)
        q = dual_tv_prox((q + tv_step * c * gradient(x_bar)) * on, kappa, radius) * on
        x_new = np.maximum(x - primal_step * (a * (A.T @ y).reshape(shape) + c * gradient_adjoint(q)), 0.0)
        x_bar = 2 * x_new - x
        x = x_new
        if on_step:
            on_step(step, x)
    return x


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("target", type=float)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--balance", type=float, default=1e-4)
    ap.add_argument("--gamma", type=float, default=1.0)
    ap.add_argument("--fista", action="store_true")
    ap.add_argument("--every", type=int, default=25)
    args = ap.parse_args()
    p = Problem(args.dir)
    energies = []

    def on_step(k, s):
        if k % args.every == 0:
            energies.append((k, p.energy(s)))
            print(f"step {k}: E {energies[-1][1]:.9e} ({energies[-1][1] / args.target - 1:+.2e} of the target)", flush=True)

    started = time.perf_counter()
    if args.fista:
        solve(p, args.steps, 0.0, on_step=on_step)
    else:
        pdhg(p, args.steps, args.balance, args.gamma, on_step)
    within = next((k for k, e in energies if e <= args.target * (1 + 1e-4)), None)
    print(json.dumps({"solver": "fista" if args.fista else "pdhg", "balance": args.balance, "gamma": args.gamma,
                      "steps": args.steps, "final_over_target": energies[-1][1] / args.target - 1,
                      "steps_to_within_1e-4": within, "seconds": time.perf_counter() - started}))


if __name__ == "__main__":
    main()
