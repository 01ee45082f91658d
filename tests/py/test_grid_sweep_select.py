"""The grid, sweep and select stages' files, checked by independent readers and references.

A small CT goes through `aret-pipe run … --until select` with a short training. Then:
- SimpleITK and pyvista read `density.mhd` with the lattice's spacing and origin (patient mm);
  the density equals ReLU(F + Δ) recomposed in numpy from `model.safetensors`; the
  uncertainty equals |numpy.gradient| scaled to [0, 1]; the official OpenVDB reader finds the
  same values in `density.vdb`;
- `sweep.csv` equals the sweep re-done with numpy percentiles and scipy.ndimage (label, drop
  small, padded ball closing, label, diameter filter) at every threshold;
- `nodule.obj` is watertight for trimesh with the enclosed volume `result.json` reports.
"""
import csv
import json
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
import SimpleITK as sitk
import trimesh
from safetensors.numpy import load_file
from scipy import ndimage

from test_drr_numpy import phantom_hu, write_series
from test_train_safetensors import BIN
from test_vdb_openvdb import READER, SYSTEM_PYTHON, openvdb_module, require

# The built-in `[select.half_max] fraction`, which pipeline.toml spells out.
FRACTION = tomllib.loads((Path(__file__).parents[2] / "pipeline.toml").read_text())["select"]["half_max"]["fraction"]

CONFIG = (
    '[pipeline]\nname = "grid"\n[dataset]\nkind = "dicom"\nroot = "data"\n'
    "[drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n"
    '[train]\nmodel = "vm"\ngrid = 24\nlog_every = 50\n'
    "[train.vm]\nrank = 4\niterations = 150\nbatch_rays = 512\nseed = 3\n"
    '[sweep]\nmin_voxels = 4\ndiameter_mm = [5.0, 400.0]\nscore = "density"\nregion = "box"\n'
    '[select]\nprimary = "blind_largest"\nlocalize = "none"\nsizing = "candidates"\n'
)


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("grid")
    write_series(tmp / "data" / "P1" / "series", phantom_hu())
    (tmp / "p.toml").write_text(CONFIG)
    proc = subprocess.run([BIN, "run", "p.toml", "--until", "select"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return tmp / "out" / "P1"


def raw(out: Path, name: str, n: int) -> np.ndarray:
    return np.fromfile(out / f"{name}.raw", dtype="<f4").reshape(n, n, n)  # [z, y, x]


def lattice(out: Path):
    cams = json.loads((out / "cameras.json").read_text())
    lo, hi = np.array(cams["aabb"]["min"]), np.array(cams["aabb"]["max"])
    frame = cams["frame"]
    cell = (hi - lo) / 24
    origin = (lo + cell / 2) * frame["mm_per_unit"] + np.array(frame["roi_center_mm"])
    return cell * frame["mm_per_unit"], origin


def test_readers_place_the_density_in_patient_mm(out):
    spacing, origin = lattice(out)
    image = sitk.ReadImage(str(out / "density.mhd"))
    assert image.GetSize() == (24, 24, 24)
    np.testing.assert_allclose(image.GetSpacing(), spacing, rtol=1e-12)
    np.testing.assert_allclose(image.GetOrigin(), origin, rtol=1e-12, atol=1e-9)
    grid = pv.read(str(out / "density.mhd"))
    np.testing.assert_allclose(grid.spacing, spacing, rtol=1e-12)
    np.testing.assert_allclose(grid.origin, origin, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), raw(out, "density", 24))


def test_density_is_the_relu_of_the_recomposed_field(out):
    t = load_file(str(out / "model.safetensors"))
    f = (
        np.einsum("ryx,rz->zyx", t["plane_xy"], t["line_z"], dtype=np.float64)
        + np.einsum("rzx,ry->zyx", t["plane_xz"], t["line_y"], dtype=np.float64)
        + np.einsum("rzy,rx->zyx", t["plane_yz"], t["line_x"], dtype=np.float64)
    )
    assert "alpha_mask" not in t  # 150 iterations: before the first mask
    np.testing.assert_allclose(raw(out, "density", 24), np.maximum(f, 0.0), atol=2e-5)


def test_uncertainty_is_the_scaled_gradient_magnitude(out):
    spacing, _ = lattice(out)
    d = raw(out, "density", 24).astype(np.float64)
    gz, gy, gx = np.gradient(d, spacing[2], spacing[1], spacing[0])
    m = np.sqrt(gx**2 + gy**2 + gz**2)
    np.testing.assert_allclose(raw(out, "uncertainty", 24), m / m.max(), atol=1e-6)


def test_openvdb_reads_both_grids_with_the_volumes_values(out, tmp_path):
    require(openvdb_module(), "python3-openvdb")
    dims = json.dumps({"density": [24, 24, 24], "uncertainty": [24, 24, 24]})
    npz = tmp_path / "grids.npz"
    proc = subprocess.run(
        [SYSTEM_PYTHON, "-c", READER, str(out / "density.vdb"), str(npz), dims], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    info, arrays = json.loads(proc.stdout), np.load(npz)
    spacing, origin = lattice(out)
    for name in ("density", "uncertainty"):
        dense = arrays[f"{name}/dense"].transpose(2, 1, 0)  # OpenVDB (x, y, z) → our [z, y, x]
        np.testing.assert_array_equal(dense, raw(out, name, 24))
        np.testing.assert_allclose(info[name]["voxel_size"], spacing, rtol=1e-12)
        np.testing.assert_allclose(info[name]["index_to_world"]["[0, 0, 0]"], origin, rtol=1e-12, atol=1e-9)


def scipy_sweep(density: np.ndarray, spacing, percentile: float, min_voxels: int, diameter_mm):
    """SPEC §3 sweep with numpy and scipy: the candidates' voxel counts, in label order."""
    structure = ndimage.generate_binary_structure(3, 3)
    nonzero = density[density != 0]
    threshold = np.percentile(nonzero.astype(np.float64), percentile)
    labels, count = ndimage.label(density >= threshold, structure)
    sizes = np.bincount(labels.ravel())[1:]
    kept = np.isin(labels, 1 + np.flatnonzero(sizes >= min_voxels))
    r = np.arange(-2, 3)
    ball = (r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2) <= 4
    closed = ndimage.binary_closing(np.pad(kept, 2), structure=ball)[2:-2, 2:-2, 2:-2]
    labels, _ = ndimage.label(closed, structure)
    sizes = np.bincount(labels.ravel())[1:]
    d = np.cbrt(6 * sizes * np.prod(spacing) / np.pi)
    return threshold, [int(s) for s, di in zip(sizes, d) if diameter_mm[0] <= di <= diameter_mm[1]]


def test_sweep_equals_numpy_and_scipy(out):
    spacing, _ = lattice(out)
    density = raw(out, "density", 24)
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) >= len([85, 88] + list(range(90, 100)))  # candidates at (about) every level
    percentiles = [85, 88] + list(range(90, 100))
    for p in percentiles:
        threshold, sizes = scipy_sweep(density, spacing, p, 4, (5.0, 400.0))
        ours = [r for r in rows if float(r["percentile"]) == p]
        assert [int(r["voxels"]) for r in ours] == sizes, f"percentile {p}"
        for r in ours:
            assert float(r["threshold"]) == threshold
            assert float(r["volume_mm3"]) == pytest.approx(int(r["voxels"]) * np.prod(spacing), rel=1e-6)


def test_nodule_mesh_is_watertight_with_the_reported_volume(out):
    result = json.loads((out / "result.json").read_text())
    assert result["verdict"].startswith("unverified")  # no annotations for this CT
    mesh = trimesh.load(out / "nodule.obj", force="mesh", process=False)
    assert len(mesh.faces) == result["mesh_triangles"] > 0
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.volume == pytest.approx(result["mesh_volume_mm3"], rel=1e-6)
    mask = np.fromfile(out / "nodule_mask.raw", dtype=np.uint8)
    spacing, _ = lattice(out)
    assert mask.sum() * np.prod(spacing) == pytest.approx(result["voxel_volume_mm3"], rel=1e-9)


def test_half_max_sizing_equals_scipy(out):
    """`[select] sizing = "half_max"` at the scene origin: the region of σ ≥ the default fraction
    of its peak beside the centre that holds the peak, re-done with scipy.ndimage.label
    (26-connected)."""
    tmp = out.parent.parent
    config = CONFIG.replace('localize = "none"\nsizing = "candidates"\n', 'localize = "origin"\nsizing = "half_max"\n')
    assert config != CONFIG
    config = config.replace(
        '[pipeline]\nname = "grid"\n', '[pipeline]\nname = "grid"\nout_dir = "out-half-max"\n'
    )
    (tmp / "half_max.toml").write_text(config)
    proc = subprocess.run([BIN, "run", "half_max.toml", "--until", "select"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # Only select recomputes: the fit, grid and sweep are the first run's.
    assert "1 computed, 6 cached, 0 failed" in proc.stderr + proc.stdout, proc.stdout + proc.stderr
    half = tmp / "out-half-max" / "P1"
    result = json.loads((half / "result.json").read_text())
    density = raw(out, "density", 24)
    x, y, z = result["centres"]["blind"]["voxel"]
    near = density[max(z - 1, 0) : z + 2, max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2]
    assert near.max() > 0, "the test CT should have density at the origin"
    dz, dy, dx = np.unravel_index(np.argmax(near), near.shape)
    seed = (max(z - 1, 0) + dz, max(y - 1, 0) + dy, max(x - 1, 0) + dx)
    labels, _ = ndimage.label(density >= FRACTION * np.float64(near.max()), ndimage.generate_binary_structure(3, 3))
    expected = labels == labels[seed]
    mask = np.fromfile(half / "nodule_mask.raw", dtype=np.uint8).reshape(24, 24, 24).astype(bool)
    np.testing.assert_array_equal(mask, expected)
    selection = result["blind_largest"]
    # Both blind rules size the blind centre alike.
    assert {**selection, "rule": None} == {**result["blind_persistent"], "rule": None}
    assert selection["candidate"]["voxels"] == expected.sum()
    assert selection["candidate"]["threshold"] == pytest.approx(FRACTION * float(near.max()), rel=1e-12)
    lo, hi = selection["volume_interval_mm3"]
    assert lo <= selection["candidate"]["volume_mm3"] <= hi
