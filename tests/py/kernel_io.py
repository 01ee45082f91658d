"""What the kernel cross-checks share: MetaImage files in and out of numpy, and the hidden
`aret-pipe kernel` developer command (docs/kernels.md) that runs one kernel on them.

Arrays are numpy's (z, y, x); our volumes are x-fastest, which is the same bytes. Spacing and
origin are written in (x, y, z) order, as the header has them.
"""
import json
import os
import subprocess
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
MET = {np.dtype(np.uint8): "MET_UCHAR", np.dtype(np.float32): "MET_FLOAT", np.dtype(np.float64): "MET_DOUBLE",
       np.dtype(np.uint32): "MET_UINT"}


def write_mhd(path: Path, array, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    """A MetaImage of a (z, y, x) array; spacing and origin in (x, y, z) order."""
    array = np.ascontiguousarray(array)
    nz, ny, nx = array.shape
    path.with_suffix(".raw").write_bytes(array.astype(array.dtype.newbyteorder("<")).tobytes())
    path.write_text(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        "TransformMatrix = 1 0 0 0 1 0 0 0 1\n"
        f"Offset = {' '.join(map(repr, map(float, origin)))}\n"
        f"ElementSpacing = {' '.join(map(repr, map(float, spacing)))}\n"
        f"DimSize = {nx} {ny} {nz}\nElementType = {MET[array.dtype]}\n"
        f"ElementDataFile = {path.with_suffix('.raw').name}\n"
    )


def read_mhd(path: Path):
    header = dict(line.split(" = ", 1) for line in path.read_text().splitlines())
    nx, ny, nz = map(int, header["DimSize"].split())
    dtype = {v: k for k, v in MET.items()}[header["ElementType"]].newbyteorder("<")
    return np.fromfile(path.parent / header["ElementDataFile"], dtype=dtype).reshape(nz, ny, nx)


def kernel(*args):
    """Runs `aret-pipe kernel ARGS…` and returns its JSON answer."""
    proc = subprocess.run([BIN, "kernel", *map(str, args)], capture_output=True, text=True)
    assert proc.returncode == 0, f"aret-pipe kernel {' '.join(map(str, args))} failed:\n{proc.stderr}"
    return json.loads(proc.stdout)
