"""`[train] model = "dense_tv"` against an independent numpy/scipy solution of its objective.

A small CT (the DRR cross-check's phantom) goes through `aret-pipe run … --until grid` with a
dense 12³ fit (its stop's tolerance off, so it takes every step). numpy rebuilds the projection
from the cameras (pixel-centre rays; Joseph's discretisation, as `tools/dense_fit_peer.py`
writes it: per plane along each ray's dominant axis, bilinear on the lattice of cell centres,
clamped) and the objective `1/(2B) Σ (τ̂ − τ)² + λ mean √(|∇σ|² + ε²)`; then:
- the logged final loss is that objective at the stored σ;
- scipy's L-BFGS-B (bounds σ ≥ 0) on the same objective reaches no lower, and its σ is close;
- `density.mhd` is the stored σ; same inputs give the same bytes, and the VM-only keys
  (`[train.vm]` seed, lr, iterations, in a configuration it `extends`) do not enter the dense
  fit's cache key.
"""
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import scipy.sparse as sparse
import SimpleITK as sitk
from safetensors import safe_open
from safetensors.numpy import load_file
from scipy.optimize import minimize

from test_drr_numpy import phantom_hu, pixel_rays, write_series
from test_train_safetensors import BIN

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from dense_fit_peer import projector  # noqa: E402

N, LAMBDA, EPSILON = 12, 2e-3, 1e-2
TRAIN = (
    f'[train]\nmodel = "dense_tv"\ngrid = {N}\nlog_every = 100\n'
    f"[train.dense_tv]\niterations = 400\ntolerance = 0.0\nlambda = {LAMBDA}\nepsilon = {EPSILON}\n"
)


def config(name, extends=None):
    return (
        (f'extends = "{extends}"\n' if extends else "")
        + f'[pipeline]\nname = "{name}"\ncache_dir = "cache-{name}"\nout_dir = "out-{name}"\n'
        '[dataset]\nkind = "dicom"\nroot = "data"\n'
        "[drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n" + TRAIN
    )


def run(tmp, name, extends=None):
    (tmp / f"{name}.toml").write_text(config(name, extends))
    proc = subprocess.run([BIN, "run", f"{name}.toml", "--until", "grid"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return tmp / f"out-{name}" / "P1", proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dense")
    write_series(tmp / "data" / "P1" / "series", phantom_hu())
    return tmp


@pytest.fixture(scope="module")
def out(tmp):
    return run(tmp, "a")[0]


def system(out):
    """The projection A (rays × nodes, with s × each ray's length between planes) and the
    measured optical depths, from files."""
    cams = json.loads((out / "cameras.json").read_text())
    lo, hi = np.array(cams["aabb"]["min"]), np.array(cams["aabb"]["max"])
    rays, taus = [], []
    for cam in cams["cameras"]:
        o, d = pixel_rays(cam)
        with OpenEXR.File(str(out / f"drr_{cam['view']}.exr")) as exr:
            pixels = exr.channels()["Y"].pixels.astype(np.float64).reshape(-1)
        rays.append(np.column_stack([o, d, pixels]))
        taus.append(-np.log(np.maximum(pixels, 1e-6)))
    return projector(np.concatenate(rays), N, lo, hi, 1.0), np.concatenate(taus)  # [train] scale = 1


def objective(a, tau):
    seen = np.diff(a.indptr) > 0
    b = seen.sum()

    def energy(x):
        v = x.reshape(N, N, N)  # [z, y, x]
        g = np.zeros((3,) + v.shape)
        g[0, :, :, :-1] = np.diff(v, axis=2)
        g[1, :, :-1, :] = np.diff(v, axis=1)
        g[2, :-1, :, :] = np.diff(v, axis=0)
        m = np.sqrt((g**2).sum(0) + EPSILON**2)
        p = g / m
        div = p[0].copy()
        div[:, :, 1:] -= p[0][:, :, :-1]
        div += p[1]
        div[:, 1:, :] -= p[1][:, :-1, :]
        div += p[2]
        div[1:, :, :] -= p[2][:-1, :, :]
        r = np.where(seen, a @ x - tau, 0.0)
        value = (r**2).sum() / (2 * b) + LAMBDA * m.mean()
        return value, a.T @ r / b - LAMBDA / N**3 * div.reshape(-1)

    return energy


def test_the_stored_density_minimises_the_documented_objective(out):
    tensors = load_file(str(out / "model.safetensors"))
    assert list(tensors) == ["density"]
    sigma = tensors["density"].astype(np.float64)
    assert sigma.shape == (N, N, N) and (sigma >= 0).all() and sigma.max() > 0.05
    with safe_open(str(out / "model.safetensors"), framework="numpy") as f:
        meta = json.loads(f.metadata()["aret_pipe"])
    assert (meta["model"], meta["grid"], meta["rank"], meta["parameters"], meta["backend"]) == ("dense_tv", N, 0, N**3, "cpu")
    a, tau = system(out)
    energy = objective(a, tau)
    ours, _ = energy(sigma.reshape(-1))
    log = list(csv.DictReader((out / "train_log.csv").open()))
    assert [int(r["iteration"]) for r in log] == [0, 100, 200, 300, 400]
    np.testing.assert_allclose(float(log[-1]["loss"]), ours, rtol=1e-5)
    assert float(log[-1]["psnr_coronal_db"]) > float(log[0]["psnr_coronal_db"]) + 10
    reference = minimize(energy, np.zeros(N**3), jac=True, method="L-BFGS-B", bounds=[(0, None)] * N**3,
                         options={"maxiter": 20000, "maxfun": 40000, "ftol": 1e-15, "gtol": 1e-12})
    assert ours <= reference.fun * (1 + 1e-4), (ours, reference.fun)
    seen_nodes = np.asarray(a.sum(axis=0)).ravel() > 0
    gap = np.linalg.norm((sigma.reshape(-1) - reference.x)[seen_nodes]) / np.linalg.norm(reference.x[seen_nodes])
    assert gap < 0.05, gap


def test_density_volume_is_the_stored_lattice(out):
    sigma = load_file(str(out / "model.safetensors"))["density"]
    volume = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "density.mhd")))
    np.testing.assert_array_equal(volume, sigma)


def test_deterministic_and_keyed_only_by_what_it_reads(tmp, out):
    again, _ = run(tmp, "b")
    assert (again / "model.safetensors").read_bytes() == (out / "model.safetensors").read_bytes()
    # Same cache as "a", over a VM configuration with keys only the VM fit reads ([train.vm]):
    # picking the dense model drops them, and the dense fit is not redone.
    (tmp / "cache-c").symlink_to(tmp / "cache-a")
    (tmp / "vm.toml").write_text('[train]\nmodel = "vm"\n[train.vm]\nseed = 9\nlr = 0.5\niterations = 7\n')
    _, log = run(tmp, "c", extends="vm.toml")
    assert "grid P1: computed" not in log and "train P1: computed" not in log, log
    # Written in the dense configuration itself, a [train.vm] key is refused, not ignored.
    (tmp / "d.toml").write_text(config("d") + "[train.vm]\nseed = 9\n")
    proc = subprocess.run([BIN, "run", "d.toml", "--until", "grid"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode != 0 and "[train.vm]" in proc.stderr, proc.stdout + proc.stderr
