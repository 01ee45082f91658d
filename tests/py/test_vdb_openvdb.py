"""Our OpenVDB files through the official OpenVDB library (the C++ library underneath).

We write MetaImage volumes with numpy, convert them with `aret-pipe convert`, then read the
.vdb back with Debian's OpenVDB Python bindings and `vdb_print`. The bindings (package
python3-openvdb: module `pyopenvdb`, or `openvdb` in newer releases) live in Debian's own
/usr/bin/python3, not in our venv, so the reading runs there in a subprocess and hands back an
.npz. Every voxel is compared, inactive ones included (they must read as the background 0),
and so are the set of active voxels, the index-to-world transform, the voxel size, the grid
class and name, and the compression (zip + active values: a CT-like volume that is mostly air
takes a fraction of its dense size). The bindings missing is a skip on a developer's machine and a failure in CI
(`.ci/run` installs them).
"""
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
SYSTEM_PYTHON = "/usr/bin/python3"
INSTALL = "apt-get install python3-openvdb libopenvdb-tools"

# Runs in Debian's python: reads every grid of argv[1], writes argv[2] (.npz) and prints JSON.
READER = r"""
import json, sys
import numpy as np
try:
    import pyopenvdb as vdb
except ImportError:
    import openvdb as vdb

path, out = sys.argv[1], sys.argv[2]
dims = json.loads(sys.argv[3])
arrays, info = {}, {}
for grid in vdb.readAll(path)[0]:
    name = grid.name
    nx, ny, nz = dims[name]
    dense = np.full((nx, ny, nz), np.float32(-12345.0), dtype=np.float32)
    grid.copyToArray(dense, ijk=(0, 0, 0))  # every voxel, inactive ones as stored (background)
    active = []
    for item in grid.iterOnValues():
        lo, hi = item["min"], item["max"]
        assert lo == hi, f"an active tile {lo}..{hi}; we write voxels only"
        active.append(lo)
    arrays[name + "/dense"] = dense
    arrays[name + "/active"] = np.array(active, dtype=np.int64).reshape(-1, 3)
    cls = grid.gridClass
    cls = cls if isinstance(cls, str) else cls.name.lower().replace("_", " ")
    t = grid.transform
    corners = [(i, j, k) for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)]
    info[name] = {
        "class": cls,
        "background": float(grid.background),
        "active_count": int(grid.activeVoxelCount()),
        "voxel_size": list(t.voxelSize()),
        "index_to_world": {json.dumps(c): list(t.indexToWorld(c)) for c in corners},
        "metadata": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dict(grid.metadata).items()},
    }
np.savez(out, **arrays)
print(json.dumps(info))
"""


def openvdb_module():
    """The name the system python imports OpenVDB under, or None."""
    if not Path(SYSTEM_PYTHON).is_file():
        return None
    for module in ("pyopenvdb", "openvdb"):
        if subprocess.run([SYSTEM_PYTHON, "-c", f"import {module}"], capture_output=True).returncode == 0:
            return module
    return None


def require(found, what):
    if found:
        return
    message = f"{what} is not installed (`{INSTALL}`)"
    if os.environ.get("CI", "") not in ("", "false"):  # CI set, as stages/engine/progress.rs reads it
        pytest.fail(f"{message}; CI must install it (.ci/run does)")
    pytest.skip(message)


def write_mhd(path: Path, volume: np.ndarray, spacing, origin):
    """`volume` indexed [z, y, x] (x fastest on disk), as our MetaImage files are."""
    met = {np.dtype(np.float32): "MET_FLOAT", np.dtype(np.int16): "MET_SHORT"}[volume.dtype]
    volume.tofile(path.with_suffix(".raw"))
    nz, ny, nx = volume.shape
    path.write_text(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        "TransformMatrix = 1 0 0 0 1 0 0 0 1\n"
        f"Offset = {' '.join(map(repr, origin))}\nElementSpacing = {' '.join(map(repr, spacing))}\n"
        f"DimSize = {nx} {ny} {nz}\nElementType = {met}\nElementDataFile = {path.with_suffix('.raw').name}\n"
    )


def aret(*args, cwd):
    proc = subprocess.run([BIN, *map(str, args)], cwd=cwd, capture_output=True, text=True)
    assert proc.returncode == 0, f"aret-pipe {' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def sparse(shape, zero_fraction, seed):
    rng = np.random.default_rng(seed)
    v = rng.uniform(-1.0, 1.0, size=shape).astype(np.float32)
    v[rng.random(shape) < zero_fraction] = 0.0
    v.flat[::53] = np.float32(-0.0)  # exactly zero too: inactive
    return v


def ct_like(shape, seed):
    """`ct_unit`'s scale, (HU + 1000) / 1400 clamped to [0, 1]: per slice an elliptic body of
    soft tissue (40 HU) holding two lungs (-850 HU), integer-HU noise, air exactly 0 (~58 %)."""
    nz, ny, nx = shape
    rng = np.random.default_rng(seed)
    v, u = np.meshgrid(np.arange(ny) / ny, np.arange(nx) / nx, indexing="ij")

    def inside(cx, cy, a, b):
        return ((u - cx) / a) ** 2 + ((v - cy) / b) ** 2 < 1.0

    body = inside(0.5, 0.5, 0.45, 0.3)
    hu = np.where(inside(0.32, 0.48, 0.12, 0.18) | inside(0.68, 0.48, 0.12, 0.18), -850.0, 40.0)
    noisy = np.round(hu + rng.normal(0.0, 20.0, size=shape))
    unit = np.where(body, np.clip((noisy + 1000.0) / 1400.0, 0.0, 1.0), 0.0)
    return unit.astype(np.float32)


# name -> (volume [z, y, x], spacing, origin, --class)
def volumes():
    wide = np.zeros((2, 136, 4100), np.float32)  # crosses the 4096-voxel root-child boundary in x
    for n, (x, y, z) in enumerate([(0, 0, 0), (0, 130, 1), (8, 0, 0), (4095, 135, 1), (4096, 0, 0), (4099, 129, 1)]):
        wide[z, y, x] = n + 0.25
    ct = (np.arange(5 * 6 * 7, dtype=np.int16).reshape(5, 6, 7) * 37 % 401 - 200).astype(np.int16)
    return {
        "density": (sparse((29, 20, 37), 0.6, 1), (0.703125, 1.25, 2.5), (-170.5, 12.25, -312.0), "fog"),
        "uncertainty": (sparse((29, 20, 37), 0.3, 2), (0.703125, 1.25, 2.5), (-170.5, 12.25, -312.0), "other"),
        "wide": (wide, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), "other"),
        "ct": (ct, (0.5, 0.5, 1.25), (10.0, -20.0, 30.5), "other"),
        "ct_unit": (ct_like((40, 160, 160), 7), (0.703125, 0.703125, 2.5), (-180.0, -180.0, -340.0), "other"),
    }


GRIDS = ["density", "uncertainty", "wide", "ct", "ct_unit"]
# file -> the grids it holds (density.vdb: two grids, as the grid stage writes it)
FILES = {"density.vdb": ["density", "uncertainty"], "wide.vdb": ["wide"], "ct.vdb": ["ct"], "ct_unit.vdb": ["ct_unit"]}


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("vdb")
    vols = volumes()
    for name, (volume, spacing, origin, _) in vols.items():
        write_mhd(tmp / f"{name}.mhd", volume, spacing, origin)
    for file, grids in FILES.items():
        classes = [a for g in grids for a in ("--class", vols[g][3])]
        aret("convert", *[f"{g}.mhd" for g in grids], file, *classes, cwd=tmp)
    return tmp, vols


@pytest.fixture(scope="module")
def read_back(converted):
    require(openvdb_module(), f"OpenVDB's Python bindings for {SYSTEM_PYTHON}")
    tmp, vols = converted
    result = {}
    for file, grids in FILES.items():
        dims = {g: list(vols[g][0].shape[::-1]) for g in grids}
        npz = tmp / f"{file}.npz"
        proc = subprocess.run(
            [SYSTEM_PYTHON, "-c", READER, str(tmp / file), str(npz), json.dumps(dims)], capture_output=True, text=True
        )
        assert proc.returncode == 0, f"OpenVDB could not read {file}:\n{proc.stderr}"
        info = json.loads(proc.stdout)
        assert sorted(info) == sorted(grids), f"{file} holds {sorted(info)}"
        arrays = np.load(npz)
        for g in grids:
            result[g] = (info[g], arrays[g + "/dense"], arrays[g + "/active"])
    return result


@pytest.mark.parametrize("name", GRIDS)
def test_openvdb_reads_every_voxel_back(read_back, converted, name):
    _, vols = converted
    volume, _, _, _ = vols[name]
    info, dense, active = read_back[name]
    expected = volume.astype(np.float32).transpose(2, 1, 0)  # [x, y, z], as OpenVDB indexes
    # Every voxel: active ones bit for bit, inactive ones as the background 0.
    assert dense.shape == expected.shape
    want_dense = np.where(expected != 0, expected, np.float32(0.0))  # -0 is background too
    np.testing.assert_array_equal(dense.view(np.uint32), want_dense.view(np.uint32))
    assert info["background"] == 0.0
    # Exactly the non-zero voxels are active.
    want = np.argwhere(expected != 0)
    got = active[np.lexsort(active.T[::-1])] if len(active) else active
    np.testing.assert_array_equal(got, want)
    assert info["active_count"] == len(want) > 0


@pytest.mark.parametrize("name", GRIDS)
def test_transform_maps_index_to_patient_mm(read_back, converted, name):
    _, vols = converted
    _, spacing, origin, _ = vols[name]
    info, _, _ = read_back[name]
    assert info["voxel_size"] == list(spacing)
    assert len(info["index_to_world"]) == 8
    for ijk, world in info["index_to_world"].items():
        want = np.array(origin) + np.array(json.loads(ijk)) * np.array(spacing)
        np.testing.assert_allclose(world, want, rtol=0, atol=1e-9, err_msg=f"index {ijk}")


@pytest.mark.parametrize("name", GRIDS)
def test_class_name_and_statistics_metadata(read_back, converted, name):
    _, vols = converted
    volume, _, _, cls = vols[name]
    info, _, _ = read_back[name]
    assert info["class"] == {"fog": "fog volume", "other": "unknown"}[cls]
    meta = info["metadata"]
    assert meta["name"] == name
    assert meta["is_saved_as_half_float"] is False
    assert meta["file_compression"] == "zip + active values"
    nonzero = np.argwhere(volume.transpose(2, 1, 0) != 0)
    assert meta["file_voxel_count"] == len(nonzero)
    assert meta["file_bbox_min"] == nonzero.min(axis=0).tolist()
    assert meta["file_bbox_max"] == nonzero.max(axis=0).tolist()


def test_vdb_print_lists_each_grid_with_its_voxel_count(converted):
    require(shutil.which("vdb_print"), "vdb_print (libopenvdb-tools)")
    tmp, vols = converted
    for file, grids in FILES.items():
        proc = subprocess.run(["vdb_print", "-l", str(tmp / file)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        assert "ERROR" not in proc.stdout + proc.stderr, proc.stdout + proc.stderr
        sections = re.split(r"^Name: ", proc.stdout, flags=re.M)[1:]
        assert [s.split("\n", 1)[0] for s in sections] == grids
        for grid, section in zip(grids, sections):
            count = re.search(r"Number of active voxels:\s+([\d,]+)", section).group(1)
            assert int(count.replace(",", "")) == np.count_nonzero(vols[grid][0]), section
            assert "Type: Tree_float_5_4_3" in section
            assert "Number of active tiles:        0" in section


def test_mostly_air_volume_takes_a_fraction_of_its_dense_size(converted):
    tmp, vols = converted
    volume = vols["ct_unit"][0]
    dense = 4 * volume.size
    size = (tmp / "ct_unit.vdb").stat().st_size
    air = np.count_nonzero(volume == 0) / volume.size
    assert 0.55 < air < 0.62, air
    # Air is inactive and not stored; the body's quantised values deflate.
    assert size < dense / 3, f"{size} bytes for {volume.size} voxels ({dense} bytes dense)"


def test_bytes_are_identical_from_run_to_run(converted, tmp_path):
    tmp, _ = converted
    again = tmp_path / "again.vdb"
    aret("convert", tmp / "density.mhd", tmp / "uncertainty.mhd", again, "--class", "fog", "--class", "other", cwd=tmp)
    assert again.read_bytes() == (tmp / "density.vdb").read_bytes()
