"""Our OpenEXR DRR files through OpenEXR's own Python bindings (the C++ library underneath).

`examples/write_exr_sample` writes a known 128x128 image: pixel (x, y) = x + 1000*y + 0.25 with
row y = 0 at the top, camera-to-world rotated +90 degrees about x and translated 50 along y,
focal 1280.5 px, view "coronal". The official reader must see one FLOAT channel `Y` with exactly
those pixels, and the attributes exactly as stages/formats/exr_image.rs documents them: the m44f
`cameraToWorld` is an Imath matrix (row-vector convention), so the translation is its last row.
"""
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = "write_exr_sample"


def example_binary():
    """The example as `tools/test` builds it (`cargo build --all-targets`), or None."""
    dirs = [os.environ.get("CARGO_TARGET_DIR"), REPO / "target"]
    for d in filter(None, dirs):
        path = Path(d) / "debug" / "examples" / EXAMPLE
        if path.is_file():
            return path
    return None


def write_sample(path: Path):
    binary = example_binary()
    if binary is not None:
        cmd = [str(binary), str(path)]
    else:
        cmd = [shutil.which("cargo") or "cargo", "run", "--quiet", "--example", EXAMPLE, "--", str(path)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}"


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    path = tmp_path_factory.mktemp("exr") / "sample.exr"
    write_sample(path)
    return path


def expected_pixels():
    y, x = np.mgrid[0:128, 0:128]
    return (x + 1000 * y).astype(np.float32) + np.float32(0.25)


def test_one_float_luminance_channel_with_the_exact_pixels(sample):
    with OpenEXR.File(str(sample)) as f:
        channels = f.channels()
        assert list(channels) == ["Y"]
        y = channels["Y"]
        assert y.type() == OpenEXR.FLOAT
        assert (y.xSampling, y.ySampling) == (1, 1)
        pixels = y.pixels
    assert pixels.dtype == np.float32 and pixels.shape == (128, 128)  # (rows, columns)
    assert pixels[0, 0] == np.float32(0.25) and pixels[0, 1] == np.float32(1.25)
    assert pixels[1, 0] == np.float32(1000.25)  # row 1 is the second scanline from the top
    np.testing.assert_array_equal(pixels, expected_pixels())
    assert pixels.view(np.uint32).tobytes() == expected_pixels().view(np.uint32).tobytes()


def test_attributes_hold_the_camera_and_descriptions(sample):
    with OpenEXR.File(str(sample)) as f:
        header = dict(f.header())  # the File's own dict is emptied when it closes

    m = header["cameraToWorld"]
    assert isinstance(m, np.ndarray) and m.dtype == np.float32 and m.shape == (4, 4)
    # Imath row-vector layout: p_world = p_camera * M, translation in the last row.
    imath = np.array(
        [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 50.0, 0.0, 1.0],
        ],
        dtype=np.float32,
    )
    np.testing.assert_array_equal(m, imath)
    # The same transform applied Imath's way: the camera origin lands at (0, 50, 0), the
    # camera's +y axis at world +z, its +z axis at world -y.
    assert np.array_equal(np.array([0, 0, 0, 1], np.float32) @ m, [0, 50, 0, 1])
    assert np.array_equal(np.array([0, 1, 0, 0], np.float32) @ m, [0, 0, 1, 0])
    assert np.array_equal(np.array([0, 0, 1, 0], np.float32) @ m, [0, -1, 0, 0])

    assert header["focalLengthPixels"] == 1280.5
    assert list(header["imageSize"]) == [128, 128]
    assert header["units"] == "scene units (1 unit = 40 mm); pixel value = I/I0"
    assert header["view"] == "coronal"

    assert header["compression"] == OpenEXR.NO_COMPRESSION
    assert header["lineOrder"] == OpenEXR.INCREASING_Y
    assert header["type"] == OpenEXR.scanlineimage
    lo, hi = header["dataWindow"]
    assert list(lo) == [0, 0] and list(hi) == [127, 127]
    lo, hi = header["displayWindow"]
    assert list(lo) == [0, 0] and list(hi) == [127, 127]
    assert header["pixelAspectRatio"] == 1.0


def test_bytes_are_identical_from_run_to_run(sample, tmp_path):
    again = tmp_path / "again.exr"
    write_sample(again)
    assert again.read_bytes() == sample.read_bytes()
