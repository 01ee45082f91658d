"""The image filters (stages/kernels/filters.rs) against scipy.ndimage and scikit-image, through
the hidden `aret-pipe kernel` developer command (docs/kernels.md) on MetaImage files written here,
with anisotropic spacing taken from the header:

- `kernel gaussian`: scipy.ndimage.gaussian_filter(x, sigma_mm / spacing, mode="nearest") on the
  float64 array (ours is computed in float64 and rounded to float32 once);
- `kernel blob`: -s^2 * sum over axes of gaussian_filter(x, s / spacing, order=2 on that axis,
  mode="nearest") / spacing^2, on float64;
- `kernel hessian-blob`: s^2 * max(0, -numpy.linalg.eigvalsh(H)[..., -1]) with H the Hessian from
  scipy's Gaussian derivative filters (order 1 or 2 per axis, mode="nearest") over spacing_a * spacing_b;
- `kernel edt`: scipy.ndimage.distance_transform_edt(mask, sampling=spacing), to 1e-9 mm;
- `kernel otsu`: skimage.filters.threshold_otsu(x, nbins=256) on the float32 array: the same float;
- `kernel fill-holes`: scipy.ndimage.binary_fill_holes on every 2-D slice along x, y or z: equal.

Arrays here are numpy's (z, y, x); our volumes are x-fastest, which is the same bytes, and
spacing is written (x, y, z) in the header, so scipy's sampling is its reverse.
"""
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage.filters import threshold_otsu

from kernel_io import kernel, read_mhd, write_mhd

SPACING = (3.75, 1.875, 2.1875)  # x, y, z in mm
SHAPES = [(40, 48, 64), (13, 29, 31), (3, 11, 7)]  # (nz, ny, nx): 64 x 48 x 40, odd, thinner than a kernel
# Gaussian / blob tolerance, relative to the reference's value range: ours is float64 rounded to
# float32 once (about 6e-8 of the magnitude).
RELATIVE = 1e-6


def run_filter(tmp_path, name, array, spacing, *options):
    write_mhd(tmp_path / "in.mhd", array, spacing)
    kernel(name, *options, tmp_path / "in.mhd", tmp_path / "out.mhd")
    return read_mhd(tmp_path / "out.mhd")


def balls(seed, shape, spacing, count, radii_mm):
    """A union of balls (radii in mm, spacing x, y, z) as a (z, y, x) mask."""
    rng = np.random.default_rng(seed)
    z, y, x = np.indices(shape)
    mask = np.zeros(shape, bool)
    for _ in range(count):
        c = [rng.uniform(0, n - 1) for n in shape]
        r = rng.uniform(*radii_mm)
        mask |= ((z - c[0]) * spacing[2]) ** 2 + ((y - c[1]) * spacing[1]) ** 2 + ((x - c[2]) * spacing[0]) ** 2 <= r * r
    return mask


def images(shape):
    """Random and structured float32 volumes: noise, a smooth field, balls on noise, a step."""
    rng = np.random.default_rng(sum(shape))
    noise = rng.normal(size=shape).astype(np.float32)
    smooth = ndi.gaussian_filter(rng.normal(size=shape), 2.0).astype(np.float32) * 100
    nodules = (balls(1, shape, SPACING, 4, (3, 12)) * 400 - 800 + rng.normal(0, 30, shape)).astype(np.float32)
    step = np.zeros(shape, np.float32)
    step[:, :, shape[2] // 2:] = 1000
    return {"noise": noise, "smooth": smooth, "nodules": nodules, "step": step}


def assert_close(ours, ref, what):
    ours = ours.astype(np.float64)
    scale = max(float(ref.max() - ref.min()), float(np.abs(ref).max()), 1e-30)
    err = float(np.abs(ours - ref).max())
    assert err <= RELATIVE * scale, f"{what}: max error {err:.3g}, {err / scale:.3g} of the range"


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("sigma_mm", [0.5, 2.0, 5.0, 10.0])
def test_gaussian_equals_scipy(tmp_path, shape, sigma_mm):
    sigma_zyx = [sigma_mm / s for s in SPACING[::-1]]
    for name, x in images(shape).items():
        ref = ndi.gaussian_filter(x.astype(np.float64), sigma_zyx, mode="nearest", truncate=4.0)
        ours = run_filter(tmp_path, "gaussian", x, SPACING, "--sigma-mm", sigma_mm)
        assert ours.dtype == np.float32
        assert_close(ours, ref, f"{name} {shape} sigma {sigma_mm} mm")


def blob_reference(x, s_mm, spacing_xyz):
    spacing_zyx = np.array(spacing_xyz[::-1])
    sv = s_mm / spacing_zyx
    total = np.zeros(x.shape)
    for axis in range(3):
        order = [0, 0, 0]
        order[axis] = 2
        total += ndi.gaussian_filter(x.astype(np.float64), sv, order=order, mode="nearest") / spacing_zyx[axis] ** 2
    return -s_mm * s_mm * total


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("s_mm", [1.0, 3.0, 8.0])
def test_blob_response_equals_scipy(tmp_path, shape, s_mm):
    for name, x in images(shape).items():
        ours = run_filter(tmp_path, "blob", x, SPACING, "--s-mm", s_mm)
        assert_close(ours, blob_reference(x, s_mm, SPACING), f"{name} {shape} s {s_mm} mm")


def test_blob_response_finds_a_ball(tmp_path):
    """Positive and largest at the centre of a bright ball, at the scale radius / sqrt(3)."""
    shape, spacing = (41, 45, 39), (1.0, 0.8, 1.2)
    z, y, x = np.indices(shape)
    centre, radius = (20, 22, 19), 9.0
    ball = ((z - centre[0]) * spacing[2]) ** 2 + ((y - centre[1]) * spacing[1]) ** 2 + ((x - centre[2]) * spacing[0]) ** 2
    image = (ball <= radius * radius).astype(np.float32)
    s = radius / np.sqrt(3)
    ours = run_filter(tmp_path, "blob", image, spacing, "--s-mm", s)
    assert np.unravel_index(np.argmax(ours), shape) == centre
    assert ours[centre] > 0
    at_centre = [run_filter(tmp_path, "blob", image, spacing, "--s-mm", f * s)[centre] for f in (0.6, 1.0, 1.6)]
    assert at_centre[1] > max(at_centre[0], at_centre[2]), at_centre


def hessian_blob_reference(x, s_mm, spacing_xyz):
    spacing_zyx = np.array(spacing_xyz[::-1])
    sv = s_mm / spacing_zyx
    hessian = np.empty(x.shape + (3, 3))
    for a in range(3):
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            h = ndi.gaussian_filter(x.astype(np.float64), sv, order=order, mode="nearest")
            hessian[..., a, b] = hessian[..., b, a] = h / (spacing_zyx[a] * spacing_zyx[b])
    largest = np.linalg.eigvalsh(hessian)[..., -1]
    return s_mm * s_mm * np.maximum(0.0, -largest)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("s_mm", [1.0, 3.0, 8.0])
def test_hessian_blob_response_equals_numpy(tmp_path, shape, s_mm):
    for name, x in images(shape).items():
        ours = run_filter(tmp_path, "hessian-blob", x, SPACING, "--s-mm", s_mm)
        assert ours.dtype == np.float32
        assert_close(ours, hessian_blob_reference(x, s_mm, SPACING), f"{name} {shape} s {s_mm} mm")


def test_hessian_blob_response_ignores_a_line(tmp_path):
    """A bright ball and a bright rod of the same radius: the Laplacian answers both, the Hessian
    response only the ball (on the rod's axis one curvature is zero)."""
    shape, spacing = (48, 40, 56), (1.0, 1.0, 1.0)
    z, y, x = np.indices(shape).astype(float)
    radius = 5.0
    ball = (z - 24) ** 2 + (y - 20) ** 2 + (x - 14) ** 2 <= radius ** 2
    rod = ((z - 24) ** 2 + (y - 20) ** 2 <= radius ** 2) & (x >= 28)
    image = (ball | rod).astype(np.float32)
    s = radius / np.sqrt(3)
    log = run_filter(tmp_path, "blob", image, spacing, "--s-mm", s)
    hess = run_filter(tmp_path, "hessian-blob", image, spacing, "--s-mm", s)
    assert log[24, 20, 42] > 0.5 * log[24, 20, 14] > 0  # the LoG answers the rod's middle
    assert hess[24, 20, 14] > 0
    assert hess[24, 20, 42] < 1e-3 * hess[24, 20, 14]
    assert np.unravel_index(np.argmax(hess), shape) == (24, 20, 14)


def extent_mm(shape):
    return max(n * s for n, s in zip(shape[::-1], SPACING))


def masks(shape):
    rng = np.random.default_rng(sum(shape) + 1)
    border = np.ones(shape, bool)
    border[shape[0] // 2, shape[1] // 2, shape[2] // 2] = False  # one unset voxel, everything else set
    return {
        "random 0.7": rng.random(shape) < 0.7,
        "random 0.97": rng.random(shape) < 0.97,
        "balls": balls(2, shape, SPACING, 5, (4, min(30, extent_mm(shape) / 3))),  # touching the border
        "one hole": border,
        "empty": np.zeros(shape, bool),
    }


@pytest.mark.parametrize("shape", SHAPES)
def test_edt_equals_scipy(tmp_path, shape):
    for name, mask in masks(shape).items():
        ours = run_filter(tmp_path, "edt", mask.astype(np.uint8), SPACING)
        assert ours.dtype == np.float64
        assert not mask.all()
        ref = ndi.distance_transform_edt(mask, sampling=SPACING[::-1])
        err = float(np.abs(ours - ref).max())
        assert err <= 1e-9, f"{name} {shape}: max error {err:.3g} mm"


def test_edt_without_background_is_infinite(tmp_path):
    ours = run_filter(tmp_path, "edt", np.ones((4, 5, 6), np.uint8), SPACING)
    assert np.all(np.isinf(ours))


def otsu_inputs():
    rng = np.random.default_rng(5)
    bimodal = np.concatenate([rng.normal(-700, 80, 30000), rng.normal(40, 60, 8000)])
    return {
        "normal": rng.normal(size=(40, 48, 64)),
        "bimodal HU": bimodal,
        "integers": rng.integers(-1000, 400, 50000),  # float32 with many ties
        "two values": np.array([0, 1, 1, 0, 1, 1]),  # every split ties: skimage takes the first
        "three values": np.array([-3, 5, 5, 7, 7, 7]),
        "uniform": rng.random(262144),
        "narrow range": 1 + rng.random(5000) * 1e-4,  # bins a few float32 ulps wide
        "lognormal": rng.lognormal(0, 2, 20000),
        "nodules": images((40, 48, 64))["nodules"],
    }


@pytest.mark.parametrize("name", list(otsu_inputs()))
def test_otsu_equals_skimage(tmp_path, name):
    x = np.asarray(otsu_inputs()[name], np.float32)
    write_mhd(tmp_path / "v.mhd", x.reshape(1, 1, -1), SPACING)
    ours = kernel("otsu", tmp_path / "v.mhd")["threshold"]
    ref = threshold_otsu(x, nbins=256)
    assert ref.dtype == np.float32
    assert ours == float(ref), f"{name}: ours {ours!r}, skimage {float(ref)!r}"


def test_otsu_without_a_threshold_is_null(tmp_path):
    """A constant (skimage returns the value) and a range too narrow for 256 float32 bins
    (numpy raises "Too many bins for data range") have no threshold."""
    write_mhd(tmp_path / "v.mhd", np.full((2, 3, 4), 7, np.float32), SPACING)
    assert kernel("otsu", tmp_path / "v.mhd")["threshold"] is None
    narrow = (1 + np.random.default_rng(6).random(5000) * 1e-5).astype(np.float32)
    with pytest.raises(ValueError, match="Too many bins"):
        threshold_otsu(narrow)
    write_mhd(tmp_path / "v.mhd", narrow.reshape(1, 1, -1), SPACING)
    assert kernel("otsu", tmp_path / "v.mhd")["threshold"] is None


def fill_reference(mask, axis):
    """binary_fill_holes of every slice perpendicular to our axis (0 = x is numpy's axis 2)."""
    np_axis = 2 - axis
    slices = [ndi.binary_fill_holes(s) for s in np.moveaxis(mask, np_axis, 0)]
    return np.moveaxis(np.stack(slices), 0, np_axis)


def hollow_shapes(shape):
    """Shells, rings and random masks: holes in some slices, leaks in others."""
    z, y, x = np.indices(shape)
    c = [n / 2 - 0.5 for n in shape]
    r2 = ((z - c[0]) / max(shape[0] / 2, 1)) ** 2 + ((y - c[1]) / (shape[1] / 2)) ** 2 + ((x - c[2]) / (shape[2] / 2)) ** 2
    shell = (r2 <= 0.8) & (r2 >= 0.4)
    open_shell = shell & ~((x > c[2]) & (np.abs(y - c[1]) < 1.5))  # a slot: leaks in some slices only
    rng = np.random.default_rng(sum(shape) + 2)
    return {
        "shell": shell,
        "open shell": open_shell,
        "random 0.55": rng.random(shape) < 0.55,
        "random 0.7": rng.random(shape) < 0.7,
        "balls": balls(3, shape, SPACING, 6, (4, 15)) ^ balls(4, shape, SPACING, 6, (2, 10)),
    }


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_fill_holes_per_slice_equals_scipy(tmp_path, shape, axis):
    filled = 0
    for name, mask in hollow_shapes(shape).items():
        ours = run_filter(tmp_path, "fill-holes", mask.astype(np.uint8), SPACING, "--axis", axis) != 0
        ref = fill_reference(mask, axis)
        assert np.array_equal(ours, ref), f"{name} {shape} axis {axis}: {int((ours != ref).sum())} voxels differ"
        filled += int(ref.sum() - mask.sum())
    assert filled > 0, "no hole to fill: the inputs test nothing"
