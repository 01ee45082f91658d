"""lab/scripts/dense_pdhg.py: its ∇ᵀ is ∇'s adjoint, its dual prox is the prox, and on a small
problem it reaches the minimum the peer's FISTA reaches, so its step counts compare like for like."""
import json

import numpy as np
from scipy.optimize import minimize

from lab_scripts import load

dense_pdhg = load("dense_pdhg")


def test_the_divergence_is_the_gradients_adjoint():
    rng = np.random.default_rng(1)
    p = rng.random((3, 5, 5, 5)) * dense_pdhg.rows_of_gradient(5)
    s = rng.random((5, 5, 5))
    lhs, rhs = (dense_pdhg.gradient(s) * p).sum(), (s * dense_pdhg.gradient_adjoint(p)).sum()
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


def test_the_dual_prox_minimises_its_objective():
    mu, eps, c, s = 0.3, 0.05, 2.0, 0.7
    kappa, radius = s * eps * c * c / mu, mu / c
    rng = np.random.default_rng(2)
    for scale in (0.02, 0.2, 2.0):
        start = rng.normal(size=(3, 1, 1, 1)) * scale
        found = dense_pdhg.dual_tv_prox(start, kappa, radius).ravel()

        def objective(v):
            inside = max(1 - (np.linalg.norm(v) / radius) ** 2, 0.0)
            return 0.5 * ((v - start.ravel()) ** 2).sum() - s * mu * eps * np.sqrt(inside) + 1e3 * (inside == 0)

        best = minimize(objective, found * 0.9, method="Nelder-Mead",
                        options={"xatol": 1e-12, "fatol": 1e-15, "maxiter": 20000})
        assert objective(found) <= best.fun + 1e-12
        assert np.allclose(found, best.x, atol=1e-7)


def test_it_reaches_the_peers_minimum(tmp_path):
    n = 6
    problem = {"n": n, "aabb_min": [-1.0] * 3, "aabb_max": [1.0] * 3, "scale": 1.0, "lambda": 0.05,
               "epsilon": 1e-2, "iterations": 100, "tolerance": 1e-4}
    (tmp_path / "problem.json").write_text(json.dumps(problem))
    rng = np.random.default_rng(3)
    rays = []
    for i in range(60):
        a = i * 0.41
        origin = np.array([4 * np.cos(a), 3 * np.sin(a), 0.5 * np.sin(2 * a)])
        direction = -origin / np.linalg.norm(origin)
        rays.append([*origin, *direction, rng.uniform(0.3, 0.9)])
    np.array(rays, dtype="<f8").tofile(tmp_path / "rays.f64")
    p = dense_pdhg.Problem(str(tmp_path))
    fista, _ = dense_pdhg.solve(p, 20000, 0.0)
    pdhg = dense_pdhg.pdhg(p, 5000, balance=1e-2, gamma=10.0)
    assert p.energy(fista) > 0
    assert abs(p.energy(pdhg) / p.energy(fista) - 1) < 1e-9
