"""The DRR stage against an independent numpy implementation of the same ray march, reading
our OpenEXR files with the official OpenEXR bindings and our volumes with SimpleITK.

A small CT series (written here with pydicom) goes through `aret-pipe run --until drr`; numpy
then re-casts every pixel's ray from `cameras.json`: the overlap of the scene box and the CT's
outer faces, equal steps of at most half a voxel on every axis, midpoint samples, trilinear
interpolation clamped to the edge voxels, I = exp(-scale * integral).
"""
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import OpenEXR
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
SHAPE = (20, 56, 64)  # slices, rows, columns
SPACING = (3.0, 3.0, 4.0)  # column, row, slice mm
ORIGIN = (-96.0, -84.0, -40.0)


def phantom_hu():
    k, j, i = np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij")
    x, y, z = ORIGIN[0] + SPACING[0] * i, ORIGIN[1] + SPACING[1] * j, ORIGIN[2] + SPACING[2] * k
    hu = np.full(SHAPE, -1000, np.int16)
    body = (x / 90) ** 2 + (y / 70) ** 2 < 1
    hu[body] = 40
    hu[body & ((np.abs(x) - 40) ** 2 + (y / 1.2) ** 2 < 30**2)] = -850
    hu[(x - 35) ** 2 + (y + 5) ** 2 + (z - 8) ** 2 < 12**2] = 30
    hu[(x / 10) ** 2 + ((y - 45) / 10) ** 2 < 1] = 700
    return hu


def write_series(folder: Path, hu):
    folder.mkdir(parents=True)
    series = generate_uid()
    for k in range(SHAPE[0]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(folder / f"{k}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.Modality, ds.SeriesInstanceUID = "CT", series
        ds.Rows, ds.Columns = SHAPE[1], SHAPE[2]
        ds.PixelSpacing = [SPACING[1], SPACING[0]]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [ORIGIN[0], ORIGIN[1], ORIGIN[2] + SPACING[2] * k]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, 0
        ds.PixelData = hu[k].astype("<i2").tobytes()
        ds.save_as(folder / f"{k}.dcm", enforce_file_format=True)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("drr")
    write_series(tmp / "data" / "P1" / "series", phantom_hu())
    (tmp / "pipeline.toml").write_text(
        '[pipeline]\nname = "drr-check"\n[dataset]\nkind = "dicom"\nroot = "data"\n'
        "[drr]\nroi_center = [5.0, -3.0, 2.0]\nwidth_px = 40\nheight_px = 36\nattenuation_scale = 1.5\n"
    )
    proc = subprocess.run([BIN, "run", "pipeline.toml", "--until", "drr"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return tmp / "out" / "P1"


def slab(lo, hi, o, d):
    """Per-ray [t0, t1] of rays o + t d (t >= 0) inside the box lo..hi (arrays of shape (n, 3))."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - o) / d, (hi - o) / d
    near, far = np.minimum(a, b), np.maximum(a, b)
    parallel = d == 0
    inside = (o >= lo) & (o <= hi)
    near = np.where(parallel, np.where(inside, -np.inf, np.inf), near)
    far = np.where(parallel, np.where(inside, np.inf, -np.inf), far)
    return np.maximum(near.max(axis=1), 0.0), far.min(axis=1)


def trilinear(v, p):
    """v indexed [k, j, i]; p (..., 3) continuous (i, j, k), clamped to the edge voxels."""
    dims = np.array(v.shape[::-1])
    x = np.clip(p, 0, dims - 1)
    f = np.minimum(np.floor(x), np.maximum(dims - 2, 0))
    t = x - f
    i0, j0, k0 = (f[..., a].astype(int) for a in range(3))
    i1, j1, k1 = (np.minimum(c + 1, d - 1) for c, d in zip((i0, j0, k0), dims))
    tx, ty, tz = t[..., 0], t[..., 1], t[..., 2]
    c00 = v[k0, j0, i0] * (1 - tx) + v[k0, j0, i1] * tx
    c10 = v[k0, j1, i0] * (1 - tx) + v[k0, j1, i1] * tx
    c01 = v[k1, j0, i0] * (1 - tx) + v[k1, j0, i1] * tx
    c11 = v[k1, j1, i0] * (1 - tx) + v[k1, j1, i1] * tx
    return (c00 * (1 - ty) + c10 * ty) * (1 - tz) + (c01 * (1 - ty) + c11 * ty) * tz


def pixel_rays(cam):
    """Origins and unit directions (scene units) of every pixel centre's ray, row-major."""
    w, h, f = cam["width"], cam["height"], cam["focal_px"]
    m = np.array(cam["camera_to_world"])
    i, j = np.meshgrid(np.arange(w), np.arange(h))
    d_cam = np.stack([(i + 0.5 - w / 2) / f, -(j + 0.5 - h / 2) / f, -np.ones_like(i, float)], -1).reshape(-1, 3)
    d = d_cam @ m[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(m[:3, 3], d.shape), d


def reference_image(cam, cams, v, origin, spacing):
    w, h = cam["width"], cam["height"]
    o, d = pixel_rays(cam)
    scale, center = cams["frame"]["mm_per_unit"], np.array(cams["frame"]["roi_center_mm"])
    # Continuous voxel index of scene point p: (p * scale + center - origin) / spacing.
    o_idx = (o * scale + center - origin) / spacing
    d_idx = d * scale / spacing
    a0, a1 = slab(np.array(cams["aabb"]["min"]), np.array(cams["aabb"]["max"]), o, d)
    dims = np.array(v.shape[::-1])
    f0, f1 = slab(np.full(3, -0.5), dims - 0.5, o_idx, d_idx)
    t0, t1 = np.maximum(a0, f0), np.minimum(a1, f1)
    out = np.zeros(len(d))
    for r in np.nonzero(t1 > t0)[0]:
        step = 0.5 / np.abs(d_idx[r]).max()
        n = max(int(np.ceil((t1[r] - t0[r]) / step - 1e-9)), 1)  # as ours: forgive rounding noise
        delta = (t1[r] - t0[r]) / n
        t = t0[r] + (np.arange(n) + 0.5) * delta
        out[r] = trilinear(v, o_idx[r] + t[:, None] * d_idx[r]).sum() * delta
    return out.reshape(h, w)


def test_drr_pixels_match_the_numpy_ray_march(run):
    cams = json.loads((run / "cameras.json").read_text())
    image = sitk.ReadImage(str(run / "ct_unit.mhd"))
    v = sitk.GetArrayFromImage(image).astype(np.float64)
    origin, spacing = np.array(image.GetOrigin()), np.array(image.GetSpacing())
    assert np.allclose(spacing, SPACING) and np.allclose(origin, ORIGIN)
    assert cams["roi_center_mode"] == "explicit" and cams["frame"]["roi_center_mm"] == [5.0, -3.0, 2.0]
    for cam in cams["cameras"]:
        with OpenEXR.File(str(run / f"drr_{cam['view']}.exr")) as f:
            pixels = f.channels()["Y"].pixels
        assert pixels.dtype == np.float32 and pixels.shape == (cam["height"], cam["width"])
        expected = reference_image(cam, cams, v, origin, spacing) * cams["attenuation_scale"]
        ours = -np.log(pixels.astype(np.float64))
        assert expected.max() > 1.0, "the rays cross real attenuation"
        np.testing.assert_allclose(ours, expected, rtol=1e-6, atol=1e-6, err_msg=cam["view"])


def test_exr_header_carries_pose_focal_size_and_units(run):
    cams = json.loads((run / "cameras.json").read_text())
    for cam in cams["cameras"]:
        with OpenEXR.File(str(run / f"drr_{cam['view']}.exr")) as f:
            header = dict(f.header())
        # Imath stores the transpose of our column-vector camera-to-world (translation last row).
        np.testing.assert_array_equal(header["cameraToWorld"], np.array(cam["camera_to_world"], np.float32).T)
        assert header["focalLengthPixels"] == np.float32(cam["focal_px"])
        assert list(header["imageSize"]) == [cam["width"], cam["height"]]
        assert header["view"] == cam["view"] and "40" in header["units"]
        assert header["lineOrder"] == OpenEXR.INCREASING_Y


def test_previews_are_written(run):
    for view in ("coronal", "sagittal", "axial"):
        assert (run / f"drr_{view}.png").read_bytes()[:4] == b"\x89PNG"


def test_roi_center_lungs_finds_the_lung_field_blind(run):
    tmp = run.parents[1]
    (tmp / "lungs.toml").write_text(
        '[pipeline]\nname = "drr-lungs"\nout_dir = "out-lungs"\n[dataset]\nkind = "dicom"\nroot = "data"\n'
        '[drr]\nroi_center = "lungs"\nwidth_px = 16\nheight_px = 16\n'
    )
    proc = subprocess.run([BIN, "run", "lungs.toml", "--until", "drr"], cwd=tmp, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    cams = json.loads((tmp / "out-lungs" / "P1" / "cameras.json").read_text())
    assert cams["roi_center_mode"] == "lungs"
    # The enclosed air below -400 HU is exactly the two lungs (-850 HU) at x = ±40 mm.
    k, j, i = np.nonzero(phantom_hu() == -850)
    expected = [ORIGIN[0] + SPACING[0] * i.mean(), ORIGIN[1] + SPACING[1] * j.mean(), ORIGIN[2] + SPACING[2] * k.mean()]
    np.testing.assert_allclose(cams["frame"]["roi_center_mm"], expected, atol=1e-6)
