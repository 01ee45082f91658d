#!/usr/bin/env python3
"""The dense fit as a Python user would write it: the benchmark's peer (tools/bench_dense_fit).

Reads a problem that `bench_dense_fit` wrote (`problem.json` and `rays.f64`: per ray its origin,
unit direction and measured I/I0, seven float64), builds Joseph's projector of the same rays as a
`scipy.sparse` matrix, and runs the shipped solve on it with numpy: FISTA on
E = 1/(2B) |Aσ − τ|² + λ/N³ Σ √(|∇σ|² + ε²), σ ≥ 0, each node's step from the majoriser's
curvature, restarts, and the relative-change stop (no coarse start). Prints one JSON line:
the seconds to build A and to solve, the steps taken and the final energy.

    python3 tools/dense_fit_peer.py DIR    # DIR holds problem.json and rays.f64
"""

import json
import os
import sys
import time

import numpy as np
import scipy.sparse as sp


def projector(rays, n, lo, hi, scale):
    """A (rays × n³, node index x + n(y + n z)): per ray and plane along its dominant axis,
    the bilinear weights of its crossing times s × the ray's length between planes."""
    cell = (hi - lo) / n
    a = (rays[:, 0:3] - lo) / cell - 0.5
    b = rays[:, 3:6] / cell
    axis = np.argmax(np.abs(b), axis=1)
    rows, cols, vals = [], [], []
    strides = np.array([1, n, n * n])
    others = np.array([[1, 2], [0, 2], [0, 1]])
    for ax in range(3):
        idx = np.nonzero(axis == ax)[0]
        if idx.size == 0:
            continue
        u, v = others[ax]
        ba = b[idx, ax]
        du, dv = b[idx, u] / ba, b[idx, v] / ba
        u0, v0 = a[idx, u] - a[idx, ax] * du, a[idx, v] - a[idx, ax] * dv
        first, last = np.zeros(idx.size), np.full(idx.size, n - 1.0)
        for start, slope in ((u0, du), (v0, dv)):
            with np.errstate(divide="ignore", invalid="ignore"):
                p, q = (-0.5 - start) / slope, (n - 0.5 - start) / slope
            flat = slope == 0
            inside = (start >= -0.5) & (start <= n - 0.5)
            p = np.where(flat, np.where(inside, -np.inf, np.inf), p)
            q = np.where(flat, np.where(inside, np.inf, -np.inf), q)
            first = np.maximum(first, np.minimum(p, q))
            last = np.minimum(last, np.maximum(p, q))
        ahead = a[idx, ax]
        first = np.where(ba > 0, np.maximum(first, ahead), first)
        last = np.where(ba < 0, np.minimum(last, ahead), last)
        first, end = np.ceil(first), np.floor(last) + 1
        weight = scale / np.abs(ba)
        for k in range(n):
            on = (k >= first) & (k < end)
            if not on.any():
                continue
            r = idx[on]
            cu = np.clip(u0[on] + k * du[on], 0, n - 1)
            cv = np.clip(v0[on] + k * dv[on], 0, n - 1)
            iu, iv = np.minimum(cu.astype(int), n - 2), np.minimum(cv.astype(int), n - 2)
            fu, fv = cu - iu, cv - iv
            base = k * strides[ax] + iu * strides[u] + iv * strides[v]
            w = weight[on]
            for off, wt in ((0, (1 - fu) * (1 - fv)), (strides[u], fu * (1 - fv)),
                            (strides[v], (1 - fu) * fv), (strides[u] + strides[v], fu * fv)):
                rows.append(r)
                cols.append(base + off)
                vals.append(w * wt)
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(rays), n ** 3))


def tv_parts(s, eps):
    """Per node m = √(|∇σ|² + ε²) and the gradient of Σ m (σ as [z, y, x])."""
    d = np.zeros((3,) + s.shape)
    d[0, :, :, :-1] = s[:, :, 1:] - s[:, :, :-1]
    d[1, :, :-1, :] = s[:, 1:, :] - s[:, :-1, :]
    d[2, :-1, :, :] = s[1:, :, :] - s[:-1, :, :]
    m = np.sqrt((d * d).sum(0) + eps * eps)
    p = d / m
    g = -p.sum(0)
    g[:, :, 1:] += p[0, :, :, :-1]
    g[:, 1:, :] += p[1, :, :-1, :]
    g[1:, :, :] += p[2, :-1, :, :]
    return m, g


def solve(A, tau, seen, n, lam, eps, steps, tol):
    B = max(seen.sum(), 1)
    mu = lam / n ** 3
    data_curv = (A.T @ (A @ np.ones(n ** 3))).reshape(n, n, n) / B
    sigma = np.zeros((n, n, n))
    ahead, t = sigma.copy(), 1.0
    for step in range(1, steps + 1):
        r = np.where(seen, A @ ahead.ravel() - tau, 0.0)
        m, g_tv = tv_parts(ahead, eps)
        inv = 1.0 / m
        curv = 6.0 * inv
        curv[:, :, 1:] += 2.0 * inv[:, :, :-1]
        curv[:, 1:, :] += 2.0 * inv[:, :-1, :]
        curv[1:, :, :] += 2.0 * inv[:-1, :, :]
        step_size = 1.0 / (data_curv + mu * curv)
        g = (A.T @ r).reshape(n, n, n) / B + mu * g_tv
        nxt = np.maximum(ahead - step_size * g, 0.0)
        change = nxt - sigma
        t_next = (1 + np.sqrt(1 + 4 * t * t)) / 2
        uphill = ((ahead - nxt) * change / step_size).sum() > 0
        ahead = nxt + (t - 1) / t_next * change
        t = t_next
        if uphill:
            t, ahead = 1.0, nxt.copy()
        sigma = nxt
        if np.sqrt((change ** 2).sum() / max((nxt ** 2).sum(), 1e-300)) <= tol:
            break
    r = np.where(seen, A @ sigma.ravel() - tau, 0.0)
    energy = (r ** 2).sum() / (2 * B) + mu * tv_parts(sigma, eps)[0].sum()
    return step, energy


def main():
    folder = sys.argv[1]
    with open(os.path.join(folder, "problem.json")) as f:
        problem = json.load(f)
    rays = np.fromfile(os.path.join(folder, "rays.f64"), dtype="<f8").reshape(-1, 7)
    n = problem["n"]
    lo, hi = np.array(problem["aabb_min"]), np.array(problem["aabb_max"])
    started = time.perf_counter()
    A = projector(rays, n, lo, hi, problem["scale"])
    built = time.perf_counter()
    seen = np.diff(A.indptr) > 0
    tau = -np.log(np.maximum(rays[:, 6], 1e-6))
    steps, energy = solve(A, tau, seen, n, problem["lambda"], problem["epsilon"], problem["iterations"],
                          problem["tolerance"])
    done = time.perf_counter()
    print(json.dumps({"build_s": built - started, "solve_s": done - built, "steps": steps, "energy": energy,
                      "entries": int(A.nnz)}))


if __name__ == "__main__":
    main()
