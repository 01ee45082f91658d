#!/usr/bin/env python3
"""The dense fit as a Python user would write it: the benchmark's peer (tools/bench_dense_fit).

Reads a problem that `bench_dense_fit` wrote (`problem.json` and `rays.f64`: per ray its origin,
unit direction and measured I/I0, seven float64), builds Joseph's projector of the same rays as a
`scipy.sparse` matrix, and runs the shipped solve on it with numpy: FISTA on
E = 1/(2B) |Aσ − τ|² + λ/N³ Σ √(|∇σ|² + ε²), σ ≥ 0, each node's step from the majoriser's
curvature, restarts, and the relative-change stop of a step that carries momentum (no coarse
start). Prints one JSON line: the seconds to build A and to solve, the steps taken and the final
energy. `lab/scripts/dense_*.py` build their experiments on its `Problem` and `Fista`.

    python3 tools/dense_fit_peer.py DIR    # DIR holds problem.json and rays.f64
"""

import functools
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


def gradient(s):
    """∇σ on the lattice: forward differences along x, y, z (σ as [z, y, x]), zero at each
    axis' last node."""
    d = np.zeros((3,) + s.shape)
    d[0, :, :, :-1] = s[:, :, 1:] - s[:, :, :-1]
    d[1, :, :-1, :] = s[:, 1:, :] - s[:, :-1, :]
    d[2, :-1, :, :] = s[1:, :, :] - s[:-1, :, :]
    return d


def gradient_adjoint(p):
    """∇ᵀp, for p zero wherever ∇ has no row (each axis' last node)."""
    g = -p.sum(0)
    g[:, :, 1:] += p[0, :, :, :-1]
    g[:, 1:, :] += p[1, :, :-1, :]
    g[1:, :, :] += p[2, :-1, :, :]
    return g


def tv_parts(s, eps):
    """Per node m = √(|∇σ|² + ε²) and the gradient of Σ m (σ as [z, y, x])."""
    d = gradient(s)
    m = np.sqrt((d * d).sum(0) + eps * eps)
    return m, gradient_adjoint(d / m)


class Problem:
    """E's parts for the rays of a DIR that `bench_dense_fit` wrote (`problem.json`, `rays.f64`):
    A, which rays meet the box, the measured depths τ, B, λ/N³, ε and (AᵀA·1)/B."""

    def __init__(self, folder):
        with open(os.path.join(folder, "problem.json")) as f:
            self.params = json.load(f)
        rays = np.fromfile(os.path.join(folder, "rays.f64"), dtype="<f8").reshape(-1, 7)
        self.n = n = self.params["n"]
        lo, hi = np.array(self.params["aabb_min"]), np.array(self.params["aabb_max"])
        started = time.perf_counter()
        self.A = projector(rays, n, lo, hi, self.params["scale"])
        self.build_s = time.perf_counter() - started
        self.seen = np.diff(self.A.indptr) > 0
        self.tau = -np.log(np.maximum(rays[:, 6], 1e-6))
        self.B = max(self.seen.sum(), 1)
        self.mu = self.params["lambda"] / n**3
        self.eps = self.params["epsilon"]

    @functools.cached_property
    def data_curvature(self):
        """(AᵀA·1)/B: each node's bound on the data term's curvature."""
        return self.curvature_of(self.rows())

    def rows(self, which=None):
        """A, which rays meet the box and τ for the rays `which` (a slice; all by default)."""
        if which is None:
            return self.A, self.seen, self.tau
        return self.A[which], self.seen[which], self.tau[which]

    def curvature_of(self, rows, scale=1.0):
        """`scale` × (AᵀA·1)/B of `rows` (as [`rows`] gives them)."""
        A = rows[0]
        return scale * (A.T @ (A @ np.ones(self.n**3))).reshape((self.n,) * 3) / self.B

    def data_gradient(self, s, rows=None, scale=1.0):
        """`scale` × Aᵀ(Aσ − τ)/B at σ over `rows` (all rays by default)."""
        A, seen, tau = rows or self.rows()
        r = np.where(seen, A @ s.ravel() - tau, 0.0)
        return scale * (A.T @ r).reshape(s.shape) / self.B

    def energy(self, s, eps=None):
        r = np.where(self.seen, self.A @ s.ravel() - self.tau, 0.0)
        return (r**2).sum() / (2 * self.B) + self.mu * tv_parts(s, self.eps if eps is None else eps)[0].sum()


class Fista:
    """The shipped solve's state (σ, the look-ahead point, t) and its step: the majoriser's
    per-node step from the look-ahead point, Nesterov's momentum restarted when it points uphill."""

    def __init__(self, sigma):
        self.sigma, self.ahead, self.t = sigma, sigma.copy(), 1.0
        self.coasting = False  # whether the look-ahead point carries momentum

    def step(self, gradient, data_curvature, mu, eps):
        """One step, `gradient(ahead)` the data term's gradient. Returns σ's change and whether
        this step's look-ahead carried momentum (only such a step may end a solve)."""
        m, g_tv = tv_parts(self.ahead, eps)
        inv = 1.0 / m
        curv = 6.0 * inv
        curv[:, :, 1:] += 2.0 * inv[:, :, :-1]
        curv[:, 1:, :] += 2.0 * inv[:, :-1, :]
        curv[1:, :, :] += 2.0 * inv[:-1, :, :]
        step_size = 1.0 / (data_curvature + mu * curv)
        g = gradient(self.ahead) + mu * g_tv
        nxt = np.maximum(self.ahead - step_size * g, 0.0)
        change = nxt - self.sigma
        t_next = (1 + np.sqrt(1 + 4 * self.t * self.t)) / 2
        uphill = ((self.ahead - nxt) * change / step_size).sum() > 0
        momentum = (self.t - 1) / t_next
        coasted, self.coasting = self.coasting, momentum > 0
        self.ahead = nxt + momentum * change
        self.t = t_next
        if uphill:
            self.t, self.ahead, self.coasting = 1.0, nxt.copy(), False
        self.sigma = nxt
        return change, coasted


def relative_change(change, sigma):
    return np.sqrt((change**2).sum() / max((sigma**2).sum(), 1e-300))


def solve(problem, steps, tol, sigma=None, eps=None, on_step=None):
    """The shipped solve from `sigma` (zero by default) at `eps` (the problem's by default):
    at most `steps` steps, stopping once a coasting step changes σ by at most `tol`;
    `on_step(k, σ)` after each."""
    eps = problem.eps if eps is None else eps
    fista = Fista(np.zeros((problem.n,) * 3) if sigma is None else sigma)
    for step in range(1, steps + 1):
        change, coasted = fista.step(problem.data_gradient, problem.data_curvature, problem.mu, eps)
        if on_step:
            on_step(step, fista.sigma)
        if coasted and relative_change(change, fista.sigma) <= tol:
            break
    return fista.sigma, step


def main():
    problem = Problem(sys.argv[1])
    started = time.perf_counter()
    sigma, steps = solve(problem, problem.params["iterations"], problem.params["tolerance"])
    energy = problem.energy(sigma)
    solved = time.perf_counter() - started
    print(json.dumps({"build_s": problem.build_s, "solve_s": solved, "steps": steps, "energy": energy,
                      "entries": int(problem.A.nnz)}))


if __name__ == "__main__":
    main()
