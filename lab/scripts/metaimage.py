"""Reading the pipeline's MetaImage volumes (`.mhd` + `.raw`) for the analysis tools: numpy only."""
import os

import numpy as np

DTYPES = {"MET_FLOAT": np.float32, "MET_UCHAR": np.uint8, "MET_SHORT": np.int16}


def read_mhd(path):
    """The volume as a (z, y, x) array, with its spacing and origin (x, y, z mm)."""
    header = dict(line.split(" = ", 1) for line in open(path).read().strip().splitlines())
    dims = [int(v) for v in header["DimSize"].split()]
    spacing = np.array([float(v) for v in header["ElementSpacing"].split()])
    origin = np.array([float(v) for v in header["Offset"].split()])
    raw = os.path.join(os.path.dirname(path), header["ElementDataFile"])
    dtype = np.dtype(DTYPES[header["ElementType"]]).newbyteorder("<")
    return np.fromfile(raw, dtype).reshape(dims[::-1]), spacing, origin
