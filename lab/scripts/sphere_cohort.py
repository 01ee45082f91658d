#!/usr/bin/env python3
"""A calibration cohort: solid spheres of known size in the phantom's lungs, outside the paper's 19.

    lab/scripts/sphere_cohort.py tools/cohorts/spheres16 --binary target/release/aret-pipe

Writes <patient>.scan.json + <patient>.xml per patient, the layout of tools/cohorts/paper19, so
`[dataset] kind = "phantom"` reads it like the real cohort (lab/presets/calibration_spheres.toml).
Each patient is a scan geometry drawn from the range LIDC-IDRI scans span (pixel 0.62–0.86 mm,
slices 1.25–2.5 mm) holding one sphere, drawn identically by four readers (so its union, its
readers' grading and its 50 % consensus are the same object), with a diameter from an even
ladder over `--diameters-mm`. Nothing here comes from the paper's 19 patients.

Where each sphere goes is drawn at random and kept only where the phantom puts lung around it:
the tool generates each candidate's phantom (`aret-pipe phantom`, the pipeline's own seed) and
reads it back with pydicom; at least `--lung-fraction` of the shell from 2 to 6 mm outside the
sphere must be lung (below −500 HU), so a sphere is an isolated intraparenchymal nodule, the
case a calibration of sizing is about. Deterministic for a given --seed and binary.

Needs numpy and pydicom (tools/setup-venv installs both).
"""
import argparse
import hashlib
import json
import math
import os
import random
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import pydicom

READERS = 4
# Every rating present: a solid (texture 5), round, smooth nodule; missing ratings would make
# a read not count as a ≥ 3 mm nodule (stages/formats/lidc_xml.rs).
CHARACTERISTICS = dict(subtlety=5, internalStructure=1, calcification=6, sphericity=5, margin=5,
                       lobulation=1, spiculation=1, texture=5, malignancy=3)


def uid(*parts):
    """A DICOM UID under the 2.25 (UUID-derived) root, a pure function of `parts`."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()[:16]
    return "2.25." + str(int.from_bytes(digest, "big"))


def scan_geometry(rng, patient_id):
    """A scan as LIDC-IDRI has them: 512², pixel 0.62–0.86 mm, 1.25/2/2.5-mm slices, ~300 mm."""
    pixel_mm = round(rng.uniform(0.62, 0.86), 6)
    slice_mm = rng.choice([1.25, 2.0, 2.5, 2.5])
    count = int(round(rng.uniform(290.0, 350.0) / slice_mm))
    z0 = -round(rng.uniform(300.0, 400.0) / slice_mm) * slice_mm
    series = uid(patient_id, "series")
    return {
        "format": "aret-pipe sphere cohort/1",
        "note": "synthetic calibration patient written by tools/sphere_cohort.py: not an LIDC-IDRI scan",
        "patient_id": patient_id,
        "study_instance_uid": uid(patient_id, "study"),
        "series_instance_uid": series,
        "pixel_spacing_mm": pixel_mm,
        "slice_thickness_mm": slice_mm,
        "rows": 512,
        "cols": 512,
        "zvals_mm": [round(z0 + k * slice_mm, 4) for k in range(count)],
        "sop_uids": [uid(series, k) for k in range(count)],
    }


def sphere_contours(scan, centre_mm, diameter_mm):
    """Per slice, the reader's outline of the sphere's section: an 8-connected chain of pixels
    just outside the disc (LIDC outlines are drawn around the nodule; the consensus mask is the
    pixels inside them)."""
    ps, half = scan["pixel_spacing_mm"], scan["cols"] / 2.0
    cj, ci = centre_mm[0] / ps + half, centre_mm[1] / ps + half
    radius = diameter_mm / 2.0
    rois = []
    for k, z in enumerate(scan["zvals_mm"]):
        dz = z - centre_mm[2]
        if abs(dz) >= radius:
            continue
        r_px = math.sqrt(radius * radius - dz * dz) / ps
        if r_px < 1.0:
            continue  # a section under two pixels across is not drawn
        ring = r_px + 0.5
        steps = max(16, int(math.ceil(2.0 * math.pi * ring * 3)))
        chain = []
        for s in range(steps):
            a = 2.0 * math.pi * s / steps
            p = (int(round(cj + ring * math.cos(a))), int(round(ci + ring * math.sin(a))))
            if not chain or chain[-1] != p:
                chain.append(p)
        if chain[0] == chain[-1]:
            chain.pop()
        rois.append((z, scan["sop_uids"][k], chain))
    return rois


def lidc_xml(scan, rois):
    sessions = []
    for reader in range(READERS):
        chars = "".join(f"      <{k}>{v}</{k}>\n" for k, v in CHARACTERISTICS.items())
        roi_xml = "".join(
            "    <roi>\n"
            f"      <imageZposition>{z}</imageZposition>\n"
            f"      <imageSOP_UID>{sop}</imageSOP_UID>\n"
            "      <inclusion>TRUE</inclusion>\n"
            + "".join(f"<edgeMap><xCoord>{x}</xCoord><yCoord>{y}</yCoord></edgeMap>\n" for x, y in chain)
            + "    </roi>\n"
            for z, sop, chain in rois
        )
        sessions.append(
            "<readingSession>\n"
            "  <annotationVersion>3.12</annotationVersion>\n"
            f"  <servicingRadiologistID>reader{reader + 1}</servicingRadiologistID>\n"
            "  <unblindedReadNodule>\n"
            f"    <noduleID>sphere-{reader + 1}</noduleID>\n"
            f"    <characteristics>\n{chars}    </characteristics>\n"
            f"{roi_xml}"
            "  </unblindedReadNodule>\n"
            "</readingSession>\n"
        )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        "<!-- synthetic: one sphere drawn identically by four readers (tools/sphere_cohort.py) -->\n"
        f'<LidcReadMessage uid="{uid(scan["series_instance_uid"], -1)}" xmlns="http://www.nih.gov">\n'
        "<ResponseHeader>\n"
        f"  <SeriesInstanceUid>{scan['series_instance_uid']}</SeriesInstanceUid>\n"
        f"  <StudyInstanceUID>{scan['study_instance_uid']}</StudyInstanceUID>\n"
        "</ResponseHeader>\n" + "".join(sessions) + "</LidcReadMessage>\n"
    )


def draw_centre(rng, scan, diameter_mm):
    """A candidate centre in either lung's usual place (patient mm; +y is posterior)."""
    fov = scan["pixel_spacing_mm"] * scan["cols"]
    z = scan["zvals_mm"]
    side = rng.choice([-1.0, 1.0])
    x = side * rng.uniform(0.10, 0.36) * fov
    y = rng.uniform(-0.18, 0.22) * fov
    margin = diameter_mm / 2.0 + 10.0
    zc = rng.uniform(z[0] + 0.25 * (z[-1] - z[0]) + margin, z[-1] - margin)
    return [round(x, 3), round(y, 3), round(zc, 3)]


def read_series(folder):
    slices = [pydicom.dcmread(os.path.join(folder, f)) for f in os.listdir(folder) if f.endswith(".dcm")]
    slices.sort(key=lambda s: float(s.ImagePositionPatient[2]))
    hu = np.stack([s.pixel_array * float(s.RescaleSlope) + float(s.RescaleIntercept) for s in slices])
    first = slices[0]
    origin = [float(v) for v in first.ImagePositionPatient]
    spacing = [float(first.PixelSpacing[1]), float(first.PixelSpacing[0]),
               float(slices[1].ImagePositionPatient[2]) - origin[2]]
    return hu, origin, spacing  # hu[k, i, j]


def lung_shell_fraction(hu, origin, spacing, centre_mm, diameter_mm):
    """Fraction of the shell 2–6 mm outside the sphere that is lung (< −500 HU)."""
    r = diameter_mm / 2.0
    reach = r + 6.0
    lo = [int(math.floor((centre_mm[a] - reach - origin[a]) / spacing[a])) for a in range(3)]
    hi = [int(math.ceil((centre_mm[a] + reach - origin[a]) / spacing[a])) + 1 for a in range(3)]
    shape = (hu.shape[2], hu.shape[1], hu.shape[0])  # x, y, z
    if any(lo[a] < 0 or hi[a] > shape[a] for a in range(3)):
        return 0.0
    k, i, j = np.meshgrid(*(np.arange(lo[a], hi[a]) for a in (2, 1, 0)), indexing="ij")
    d = np.sqrt((j * spacing[0] + origin[0] - centre_mm[0]) ** 2
                + (i * spacing[1] + origin[1] - centre_mm[1]) ** 2
                + (k * spacing[2] + origin[2] - centre_mm[2]) ** 2)
    shell = (d >= r + 2.0) & (d <= reach)
    return float((hu[k, i, j][shell] < -500.0).mean())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="the cohort folder to write")
    ap.add_argument("--binary", default="target/release/aret-pipe", help="aret-pipe, to generate the phantoms")
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--diameters-mm", type=float, nargs=2, default=[8.0, 32.0])
    ap.add_argument("--seed", type=int, default=2026, help="seed of the geometries and positions")
    ap.add_argument("--phantom-seed", type=int, default=1, help="the pipeline's [dataset.phantom] seed")
    ap.add_argument("--lung-fraction", type=float, default=0.85)
    ap.add_argument("--attempts", type=int, default=40)
    args = ap.parse_args()

    rng = random.Random(args.seed)
    lo, hi = args.diameters_mm
    diameters = [round(lo + (hi - lo) * n / (args.count - 1), 2) for n in range(args.count)]
    rng.shuffle(diameters)  # sizes independent of geometry
    os.makedirs(args.out, exist_ok=True)
    work = tempfile.mkdtemp(prefix="sphere_cohort.")
    try:
        for n, diameter in enumerate(diameters):
            pid = f"SPHERE-{n + 1:02d}"
            scan = scan_geometry(rng, pid)
            for attempt in range(args.attempts):
                centre = draw_centre(rng, scan, diameter)
                rois = sphere_contours(scan, centre, diameter)
                scan["sphere"] = {"centre_mm": centre, "diameter_mm": diameter}
                cohort, generated = os.path.join(work, "cohort"), os.path.join(work, "generated")
                shutil.rmtree(cohort, ignore_errors=True)
                shutil.rmtree(generated, ignore_errors=True)
                os.makedirs(cohort)
                with open(os.path.join(cohort, f"{pid}.scan.json"), "w") as f:
                    json.dump(scan, f, indent=1)
                with open(os.path.join(cohort, f"{pid}.xml"), "w") as f:
                    f.write(lidc_xml(scan, rois))
                subprocess.run([args.binary, "phantom", "--cohort", cohort, "--out", generated,
                                "--seed", str(args.phantom_seed)], check=True, stdout=subprocess.DEVNULL)
                hu, origin, spacing = read_series(os.path.join(generated, pid, "series"))
                fraction = lung_shell_fraction(hu, origin, spacing, centre, diameter)
                print(f"{pid}: {diameter:5.2f} mm at {centre}: lung shell {fraction:.2f}", file=sys.stderr)
                if fraction >= args.lung_fraction:
                    for name in (f"{pid}.scan.json", f"{pid}.xml"):
                        shutil.copy(os.path.join(cohort, name), os.path.join(args.out, name))
                    break
            else:
                sys.exit(f"{pid}: no place with lung around a {diameter} mm sphere in {args.attempts} attempts")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
