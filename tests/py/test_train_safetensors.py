"""`model.safetensors` through Python's `safetensors` + numpy, and training's determinism.

A small CT (the DRR cross-check's phantom) goes through `aret-pipe run` with a short training;
the model must load with safetensors, carry its metadata, and come out byte-identical from a
second run with the same seed on a separate cache (another seed differs).
"""
import csv
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import load_file

from test_drr_numpy import phantom_hu, write_series

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
# TensoRF's VM field (its keys in [train.vm]), not the built-in dense one.
TRAIN = (
    '[train]\nmodel = "vm"\ngrid = 16\nlog_every = 20\n'
    "[train.vm]\nrank = 4\niterations = 60\nbatch_rays = 512\nseed = {seed}\n"
)


def run(tmp: Path, name: str, seed: int) -> Path:
    (tmp / f"{name}.toml").write_text(
        f'[pipeline]\nname = "{name}"\ncache_dir = "cache-{name}"\nout_dir = "out-{name}"\n'
        '[dataset]\nkind = "dicom"\nroot = "data"\n'
        "[drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n" + TRAIN.format(seed=seed)
    )
    proc = subprocess.run([BIN, "run", f"{name}.toml", "--until", "train"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return tmp / f"out-{name}" / "P1"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("train")
    write_series(tmp / "data" / "P1" / "series", phantom_hu())
    return run(tmp, "a", 5), run(tmp, "b", 5), run(tmp, "c", 6)


def test_model_loads_with_safetensors_and_numpy(runs):
    out = runs[0]
    tensors = load_file(str(out / "model.safetensors"))
    for name in ("plane_xy", "plane_xz", "plane_yz"):
        assert tensors[name].dtype == np.float32 and tensors[name].shape == (4, 16, 16)
    for name in ("line_z", "line_y", "line_x"):
        assert tensors[name].dtype == np.float32 and tensors[name].shape == (4, 16)
    with safe_open(str(out / "model.safetensors"), framework="numpy") as f:
        meta = json.loads(f.metadata()["aret_pipe"])
    assert (meta["grid"], meta["rank"], meta["iterations"], meta["seed"]) == (16, 4, 60, 5)
    assert meta["backend"] == "cpu" and meta["shift"] == 0.0 and meta["scale"] == 1.0
    assert meta["parameters"] == 3 * 4 * 16 * 17
    cams = json.loads((out / "cameras.json").read_text())
    assert meta["aabb"] == cams["aabb"]
    # The nodes in patient space without cameras.json: cell centres of the box, scaled and
    # shifted by the scene frame.
    space, frame = meta["patient_space"], cams["frame"]
    lo, hi = np.array(cams["aabb"]["min"]), np.array(cams["aabb"]["max"])
    cell = (hi - lo) / 16
    origin = np.array(frame["roi_center_mm"]) + (lo + cell / 2) * frame["mm_per_unit"]
    np.testing.assert_allclose(space["origin_mm"], origin, rtol=0, atol=1e-9)
    np.testing.assert_allclose(space["spacing_mm"], cell * frame["mm_per_unit"], rtol=1e-12)
    assert space["direction"] == [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert space["index_order"] == ["z", "y", "x"]
    # The composed field: F[z, y, x] = Σ_r Pxy[r, y, x] Lz[r, z] + Pxz[r, z, x] Ly[r, y] + Pyz[r, z, y] Lx[r, x].
    f = (
        np.einsum("ryx,rz->zyx", tensors["plane_xy"], tensors["line_z"])
        + np.einsum("rzx,ry->zyx", tensors["plane_xz"], tensors["line_y"])
        + np.einsum("rzy,rx->zyx", tensors["plane_yz"], tensors["line_x"])
    )
    assert np.isfinite(f).all() and (f > 0).mean() > 0.05, "training produced positive density somewhere"


def test_training_log_and_plot(runs):
    rows = list(csv.DictReader((runs[0] / "train_log.csv").open()))
    assert [int(r["iteration"]) for r in rows] == [0, 20, 40, 60]
    assert set(rows[0]) >= {"loss", "photo", "l1", "tv", "psnr_coronal_db", "psnr_sagittal_db", "psnr_axial_db", "lr"}
    assert "seconds" not in rows[0], "no output holds a wall time: whoever fits a key writes the same bytes"
    assert float(rows[-1]["psnr_coronal_db"]) > float(rows[0]["psnr_coronal_db"])
    assert (runs[0] / "loss.svg").read_text().startswith("<svg")


def test_same_seed_same_bytes_other_seed_differs(runs):
    a, b, c = (r / "model.safetensors" for r in runs)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
