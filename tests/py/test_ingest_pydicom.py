"""Cross-check `aret-pipe run CONFIG --until ingest` against pydicom and SimpleITK.

Real DICOM files not written by us: pydicom's bundled test files (CT_small, MR_small,
dicomdirtests) and the `pydicom-data` package (693_*.dcm, eCT_Supplemental.dcm). Transfer
syntax variants of CT_small and an oblique multi-slice series are written here with pydicom.

For each case the test writes a config whose dataset root holds one folder per patient, runs
the CLI, and compares `<out>/<patient>/ct_hu.mhd/.raw` (int16 HU, MetaImage) with
`apply_modality_lut(ds.pixel_array, ds)` exactly, and the geometry with SimpleITK's own DICOM
series reader. Error cases check the exit status and the stderr line (patient, stage
`ingest`, cause).

Binary: $ARET_PIPE_BIN, default <repo>/target/debug/aret-pipe (build it first). Tests needing
pydicom-data skip only when that package is not installed; a missing file is a failure.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file, get_testdata_files
from pydicom.pixels import apply_modality_lut
from pydicom.uid import (
    DeflatedExplicitVRLittleEndian,
    ExplicitVRBigEndian,
    ImplicitVRLittleEndian,
    generate_uid,
)

REPO = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("ARET_PIPE_BIN", REPO / "target" / "debug" / "aret-pipe"))
HAVE_PYDICOM_DATA = importlib.util.find_spec("data_store") is not None


# ----------------------------------------------------------------------------- helpers


def data_file(name: str) -> Path:
    """A pydicom test file; skip if it lives in pydicom-data and that is not installed."""
    path = get_testdata_file(name, download=False)
    if path is None:
        if not HAVE_PYDICOM_DATA:
            pytest.skip(f"{name} needs the pydicom-data package (pip install pydicom-data)")
        pytest.fail(f"{name} not found although pydicom-data is installed")
    return Path(path)


def dicomdir_series(sub: str) -> list[Path]:
    """The files of one series folder of pydicom's bundled dicomdirtests, e.g. '77654033/CT2'."""
    files = sorted(Path(p) for p in get_testdata_files(f"dicomdirtests/{sub}/*"))
    if not files:
        pytest.fail(f"pydicom's bundled dicomdirtests/{sub} not found")
    return files


@pytest.fixture(scope="session")
def aret_pipe() -> Path:
    if not BIN.is_file():
        pytest.fail(f"aret-pipe binary not found at {BIN}: run `cargo build` or set ARET_PIPE_BIN")
    return BIN


class Run:
    def __init__(self, proc: subprocess.CompletedProcess, out_dir: Path):
        self.proc = proc
        self.out_dir = out_dir

    @property
    def stderr(self) -> str:
        return self.proc.stderr

    def hu(self, patient: str) -> tuple[np.ndarray, dict]:
        """Our HU volume as [slice][row][col] int16, and the header fields."""
        header = read_mhd_header(self.out_dir / patient / "ct_hu.mhd")
        cols, rows, slices = (int(v) for v in header["DimSize"].split())
        assert header["ElementType"] == "MET_SHORT"
        assert header["BinaryDataByteOrderMSB"] == "False"
        raw = self.out_dir / patient / header["ElementDataFile"]
        data = np.fromfile(raw, dtype="<i2")
        assert data.size == cols * rows * slices
        return data.reshape(slices, rows, cols), header


def read_mhd_header(path: Path) -> dict[str, str]:
    fields = {}
    for line in path.read_text().splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            fields[key.strip()] = value.strip()
    return fields


def run_ingest(aret_pipe: Path, tmp_path: Path, patients: dict[str, list]) -> Run:
    """Lay out `patients` ({name: [Path | (file_name, bytes)]}) and run the ingest stage."""
    data = tmp_path / "data"
    for patient, files in patients.items():
        folder = data / patient
        folder.mkdir(parents=True)
        for f in files:
            if isinstance(f, tuple):
                (folder / f[0]).write_bytes(f[1])
            else:
                shutil.copy(f, folder / f.name)
    config = tmp_path / "config.toml"
    config.write_text(
        "[pipeline]\n"
        'name = "pydicom-check"\n'
        f'cache_dir = "{(tmp_path / "cache").as_posix()}"\n'
        f'out_dir = "{(tmp_path / "out").as_posix()}"\n'
        "[dataset]\n"
        'kind = "dicom"\n'
        f'root = "{data.as_posix()}"\n'
    )
    proc = subprocess.run(
        [str(aret_pipe), "run", str(config), "--until", "ingest"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )
    return Run(proc, tmp_path / "out")


def expect_ok(run: Run) -> None:
    assert run.proc.returncode == 0, f"aret-pipe failed:\n{run.proc.stderr}"


def expect_error(run: Run, patient: str, needles: list[str]) -> None:
    assert run.proc.returncode != 0, "aret-pipe succeeded but an error was expected"
    lines = [line for line in run.stderr.splitlines() if patient in line and "ingest" in line]
    assert lines, f"no stderr line names patient {patient!r} and stage 'ingest':\n{run.stderr}"
    # The cause may continue on following lines (an error chain): search all of stderr.
    for needle in needles:
        assert needle in run.stderr, f"{needle!r} missing from stderr:\n{run.stderr}"


def normal_of(ds) -> np.ndarray:
    iop = np.array(ds.ImageOrientationPatient, dtype=float)
    return np.cross(iop[:3], iop[3:])


def expected_hu(files: list[Path]) -> tuple[np.ndarray, list]:
    """pydicom's HU stack, slices sorted by IPP·normal ascending, and the sorted datasets."""
    datasets = [pydicom.dcmread(f) for f in files]
    datasets.sort(key=lambda ds: float(np.dot(np.array(ds.ImagePositionPatient, float),
                                              normal_of(ds))))
    slices = []
    for ds in datasets:
        hu = np.asarray(apply_modality_lut(ds.pixel_array, ds), dtype=np.float64)
        # Exact comparison is only meaningful where HU are integers (as in all CT here).
        assert np.array_equal(hu, np.round(hu)), "non-integral HU in reference data"
        assert hu.min() >= -32768 and hu.max() <= 32767
        slices.append(hu.astype(np.int16))
    return np.stack(slices), datasets


def assert_hu_equal(ours: np.ndarray, expected: np.ndarray) -> None:
    assert ours.shape == expected.shape, (ours.shape, expected.shape)
    diff = np.argwhere(ours != expected)
    assert diff.size == 0, (
        f"{len(diff)} voxels differ, first at {tuple(diff[0])}: "
        f"ours {ours[tuple(diff[0])]} vs pydicom {expected[tuple(diff[0])]}"
    )


def assert_geometry_from_dicom(header: dict, datasets: list, slice_spacing: float) -> None:
    """Our header against the SPEC's rules, computed from pydicom's view of the tags."""
    first = datasets[0]
    ps = [float(v) for v in first.PixelSpacing]
    spacing = [float(v) for v in header["ElementSpacing"].split()]
    np.testing.assert_allclose(spacing, [ps[1], ps[0], slice_spacing], rtol=1e-6)
    origin = [float(v) for v in header["Offset"].split()]
    np.testing.assert_allclose(origin, [float(v) for v in first.ImagePositionPatient], atol=1e-4)
    iop = np.array(first.ImageOrientationPatient, dtype=float)
    direction = np.array([float(v) for v in header["TransformMatrix"].split()]).reshape(3, 3)
    np.testing.assert_allclose(direction[0], iop[:3], atol=1e-5)
    np.testing.assert_allclose(direction[1], iop[3:], atol=1e-5)
    np.testing.assert_allclose(direction[2], normal_of(first), atol=1e-5)


def compare_with_simpleitk(run: Run, patient: str, folder: Path) -> None:
    """Spacing, origin, direction and HU of our MetaImage vs SimpleITK's DICOM reader."""
    sitk = pytest.importorskip("SimpleITK")
    ours = sitk.ReadImage(str(run.out_dir / patient / "ct_hu.mhd"))
    reader = sitk.ImageSeriesReader()
    names = reader.GetGDCMSeriesFileNames(str(folder))
    assert len(names) == ours.GetSize()[2]
    reader.SetFileNames(names)
    theirs = reader.Execute()
    assert ours.GetSize() == theirs.GetSize()
    np.testing.assert_allclose(ours.GetSpacing(), theirs.GetSpacing(), rtol=1e-5)
    np.testing.assert_allclose(ours.GetOrigin(), theirs.GetOrigin(), atol=1e-3)
    np.testing.assert_allclose(ours.GetDirection(), theirs.GetDirection(), atol=1e-5)
    their_hu = sitk.GetArrayFromImage(theirs)
    assert np.array_equal(sitk.GetArrayFromImage(ours).astype(np.float64),
                          their_hu.astype(np.float64))


# ------------------------------------------------------------------------ single files


def test_ct_small_matches_pydicom(aret_pipe, tmp_path):
    src = data_file("CT_small.dcm")
    run = run_ingest(aret_pipe, tmp_path, {"CT_small": [src]})
    expect_ok(run)
    ours, header = run.hu("CT_small")
    expected, datasets = expected_hu([src])
    assert_hu_equal(ours, expected)
    # One slice: the slice spacing is SliceThickness (SPEC).
    assert_geometry_from_dicom(header, datasets, float(datasets[0].SliceThickness))


@pytest.mark.parametrize("name", ["693_UNCI.dcm", "693_UNCR.dcm"])
def test_693_uncompressed_matches_pydicom(aret_pipe, tmp_path, name):
    # BitsStored 14, signed: exercises sign extension from BitsStored.
    src = data_file(name)
    run = run_ingest(aret_pipe, tmp_path, {"p693": [src]})
    expect_ok(run)
    ours, header = run.hu("p693")
    expected, datasets = expected_hu([src])
    assert_hu_equal(ours, expected)
    assert_geometry_from_dicom(header, datasets, float(datasets[0].SliceThickness))


def ct_small_variant(tmp_path: Path, ts) -> Path:
    """CT_small re-encoded in transfer syntax `ts` by pydicom."""
    ds = pydicom.dcmread(data_file("CT_small.dcm"))
    pixels = ds.pixel_array.copy()
    ds.file_meta.TransferSyntaxUID = ts
    if ts == ExplicitVRBigEndian:
        # pydicom does not swap OW values when changing endianness: do it ourselves.
        ds.PixelData = pixels.astype(">i2").tobytes()
    out = tmp_path / "variants" / f"CT_small_{ts}.dcm"
    out.parent.mkdir(exist_ok=True)
    pydicom.dcmwrite(out, ds, enforce_file_format=True)
    back = pydicom.dcmread(out)
    assert back.file_meta.TransferSyntaxUID == ts
    assert np.array_equal(back.pixel_array, pixels), "variant does not round-trip in pydicom"
    return out


@pytest.mark.parametrize(
    "ts", [ImplicitVRLittleEndian, ExplicitVRBigEndian, DeflatedExplicitVRLittleEndian],
    ids=["implicit-le", "explicit-be", "deflated-le"],
)
def test_ct_small_transfer_syntax_variants(aret_pipe, tmp_path, ts):
    variant = ct_small_variant(tmp_path, ts)
    run = run_ingest(aret_pipe, tmp_path, {"variant": [variant]})
    expect_ok(run)
    ours, header = run.hu("variant")
    expected, datasets = expected_hu([variant])
    assert_hu_equal(ours, expected)
    assert_geometry_from_dicom(header, datasets, float(datasets[0].SliceThickness))


def test_ct_small_without_preamble(aret_pipe, tmp_path):
    src = data_file("CT_small.dcm")
    raw = src.read_bytes()
    assert raw[128:132] == b"DICM"
    run = run_ingest(aret_pipe, tmp_path, {"nopre": [("CT_small_nopreamble.dcm", raw[128:])]})
    expect_ok(run)
    ours, _ = run.hu("nopre")
    expected, _ = expected_hu([src])
    assert_hu_equal(ours, expected)


# ----------------------------------------------------------------------- real series


# CT5N: 5 slices of 16x16, z from 8.76 down to -1.24 mm in 2.5 mm steps (decreasing z with the
# file names, so sorting is exercised). CT2: its first slice (17106) is 202.5 mm away from the
# other three (1.25 mm apart), so the last three form a valid series.
REAL_SERIES = [
    ("ct5n", "98892001/CT5N", (), 5, 2.5),
    ("ct2", "77654033/CT2", ("17106",), 3, 1.25),
]


@pytest.mark.parametrize("patient,folder,left_out,n_slices,gap_mm", REAL_SERIES)
def test_dicomdirtests_series_match_pydicom_and_simpleitk(aret_pipe, tmp_path, patient, folder, left_out, n_slices, gap_mm):
    files = [f for f in dicomdir_series(folder) if f.name not in left_out]
    assert len(files) == n_slices
    run = run_ingest(aret_pipe, tmp_path, {patient: files})
    expect_ok(run)
    ours, header = run.hu(patient)
    expected, datasets = expected_hu(files)
    assert_hu_equal(ours, expected)
    assert_geometry_from_dicom(header, datasets, gap_mm)
    compare_with_simpleitk(run, patient, tmp_path / "data" / patient)


def test_non_ct_and_non_dicom_files_in_patient_folder_are_skipped(aret_pipe, tmp_path):
    files = dicomdir_series("98892001/CT5N")
    cr = dicomdir_series("77654033/CR1")  # a CR image of another study
    readme = ("README.txt", b"not DICOM\n")
    xml = ("nodules.xml", b"<?xml version='1.0'?><readingSession/>")
    run = run_ingest(aret_pipe, tmp_path, {"mixed": files + cr + [readme, xml]})
    expect_ok(run)
    ours, _ = run.hu("mixed")
    expected, _ = expected_hu(files)
    assert_hu_equal(ours, expected)


def oblique_series(tmp_path: Path) -> Path:
    """Four CT_small-based slices, oblique (rotated 30° about z, tilted 20° about x), with
    non-square pixels, positions stepped along the normal in *decreasing* order, and a
    different rescale per slice."""
    base = pydicom.dcmread(data_file("CT_small.dcm"))
    a, b = np.radians(30), np.radians(20)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    rot = rx @ rz
    row, col = rot[:, 0], rot[:, 1]
    normal = np.cross(row, col)
    folder = tmp_path / "oblique_src"
    folder.mkdir()
    series_uid = generate_uid()
    origin = np.array([-40.0, 25.0, 100.0])
    for k in range(4):
        ds = pydicom.dcmread(data_file("CT_small.dcm"))
        ds.SeriesInstanceUID = series_uid
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.InstanceNumber = k + 1
        ds.ImageOrientationPatient = [f"{v:.6f}" for v in (*row, *col)]
        ds.ImagePositionPatient = [f"{v:.6f}" for v in origin - 3.0 * k * normal]
        ds.SliceThickness = "3"
        ds.PixelSpacing = ["0.7", "0.6"]  # non-square: catches a row/column spacing swap
        ds.RescaleSlope = ["1", "2", "1", "3"][k]
        ds.RescaleIntercept = ["-1024", "-2048", "-1000", "-3000"][k]
        pixels = base.pixel_array.astype(np.int16) + np.int16(10 * k)
        ds.PixelData = pixels.astype("<i2").tobytes()
        pydicom.dcmwrite(folder / f"IM{k:04d}.dcm", ds, enforce_file_format=True)
    return folder


def test_oblique_series_written_with_pydicom_matches_simpleitk(aret_pipe, tmp_path):
    folder = oblique_series(tmp_path)
    files = sorted(folder.iterdir())
    run = run_ingest(aret_pipe, tmp_path, {"oblique": files})
    expect_ok(run)
    ours, header = run.hu("oblique")
    expected, datasets = expected_hu(files)
    assert_hu_equal(ours, expected)
    assert datasets[0].InstanceNumber == 4  # the last written slice is the lowest
    assert_geometry_from_dicom(header, datasets, 3.0)
    compare_with_simpleitk(run, "oblique", tmp_path / "data" / "oblique")


# ---------------------------------------------------------------------------- errors


def test_jpeg2000_is_a_clear_unsupported_transfer_syntax_error(aret_pipe, tmp_path):
    run = run_ingest(aret_pipe, tmp_path, {"j2k": [data_file("693_J2KR.dcm")]})
    expect_error(run, "j2k", [
        "693_J2KR.dcm", "TransferSyntaxUID (0002,0010)", "1.2.840.10008.1.2.4.90",
        "JPEG 2000 Image Compression (Lossless Only)", "gdcmconv --raw",
    ])


def test_enhanced_ct_multi_frame_is_a_clear_error(aret_pipe, tmp_path):
    run = run_ingest(aret_pipe, tmp_path, {"enh": [data_file("eCT_Supplemental.dcm")]})
    expect_error(run, "enh", [
        "eCT_Supplemental.dcm", "multi-frame", "NumberOfFrames (0028,0008) = 2", "not supported",
    ])


def test_mr_only_folder_has_no_ct_slices(aret_pipe, tmp_path):
    run = run_ingest(aret_pipe, tmp_path, {"mr": [data_file("MR_small.dcm")]})
    expect_error(run, "mr", ["no CT image slices", "1 file(s)", "'MR'", "Modality (0008,0060)"])


def test_ct2_with_its_far_slice_is_non_uniform(aret_pipe, tmp_path):
    run = run_ingest(aret_pipe, tmp_path, {"ct2": dicomdir_series("77654033/CT2")})
    expect_error(run, "ct2", [
        "non-uniform slice spacing", "17106", "17136", "202.5000 mm",
        "ImagePositionPatient (0020,0032)",
    ])


def test_ct2n_mixed_orientations_are_inconsistent(aret_pipe, tmp_path):
    # Two CT slices of one series: one coronal, one sagittal.
    run = run_ingest(aret_pipe, tmp_path, {"ct2n": dicomdir_series("98892001/CT2N")})
    expect_error(run, "ct2n", ["ImageOrientationPatient (0020,0037)", "6293", "6924"])


def test_two_ct_series_in_one_folder_is_a_mixed_series_error(aret_pipe, tmp_path):
    files = dicomdir_series("98892001/CT5N") + dicomdir_series("77654033/CT2")[1:]
    run = run_ingest(aret_pipe, tmp_path, {"two": files})
    expect_error(run, "two", [
        "SeriesInstanceUID (0020,000E)", "1.3.6.1.4.1.5962.1.1.0.0.0.1194734704.16302.0.6",
        "1.3.6.1.4.1.5962.1.1.0.0.0.1196530851.28319.0.2", "(5 slices", "(3 slices",
    ])


def test_errors_do_not_leak_patient_identifiers(aret_pipe, tmp_path):
    ds = pydicom.dcmread(data_file("CT_small.dcm"))
    secrets = [str(ds.PatientName), str(ds.PatientID)]
    secrets = [s for s in secrets if len(s) >= 3]
    del ds.PixelSpacing
    out = tmp_path / "nospacing.dcm"
    pydicom.dcmwrite(out, ds, enforce_file_format=True)
    run = run_ingest(aret_pipe, tmp_path, {"anon": [out]})
    expect_error(run, "anon", ["nospacing.dcm", "PixelSpacing (0028,0030)", "missing"])
    for secret in secrets:
        assert secret not in run.stderr
