"""Writes a synthetic cohort of CT series (pydicom) for benchmarks of the engine.

Geometry like an LIDC scan: 512 x 512 pixels, 0.7 mm, `--slices` slices 2.5 mm apart. The
pixel values are smooth noise, not anatomy: the benchmark measures caching, not medicine.
"""
import argparse
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid


def write_series(folder: Path, slices: int, seed: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 1400, size=(512, 512), dtype=np.int16)
    series_uid = generate_uid()
    for k in range(slices):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(folder / f"{k:04d}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.SeriesInstanceUID = series_uid
        ds.Rows, ds.Columns = 512, 512
        ds.PixelSpacing = [0.7, 0.7]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [-179.0, -179.0, -300.0 + 2.5 * k]
        ds.SliceThickness = 2.5
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = np.roll(base, k, axis=0).tobytes()
        ds.save_as(folder / f"{k:04d}.dcm", enforce_file_format=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--patients", type=int, default=19)
    ap.add_argument("--slices", type=int, default=130)
    a = ap.parse_args()
    for p in range(a.patients):
        write_series(a.out / f"BENCH-{p + 1:04d}", a.slices, seed=p)
    print(f"wrote {a.patients} series of {a.slices} slices to {a.out}")


if __name__ == "__main__":
    main()
