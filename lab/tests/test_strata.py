"""lab/scripts/strata.py sorts each target into solid and enclosed, solid and against the lung's
wall, or subsolid, from ingest's ground truth and target site, and names the patients each rule
missed."""
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import strata  # noqa: E402


def test_the_rating_decides_subsolid_then_the_site_attached():
    assert strata.kind(4.5, False) == "free"
    assert strata.kind(4.5, True) == "attached"
    assert strata.kind(1.5, True) == "subsolid", "a ground-glass nodule is subsolid wherever it lies"
    assert strata.kind(3.25, False) == "subsolid"
    assert strata.kind(3.5, False) == "free", "3.5 is solid, as summary.json splits"


def patient(out, name, diameter_mm, texture, attached, guided_hit, blind_hit):
    d = out / name
    d.mkdir(parents=True)
    nodule = {"annotated_diameter_mm": diameter_mm, "texture_mean": texture}
    (d / "ground_truth.json").write_text(json.dumps({"target": 0, "nodules": [nodule]}))
    (d / "target_site.json").write_text(json.dumps({"attached": attached}))
    rule = lambda hit: {"localization": {"hit": hit}}
    result = {"guided": rule(guided_hit), "blind_persistent": rule(blind_hit), "blind_rule": "blind_persistent"}
    (d / "result.json").write_text(json.dumps(result))


def test_the_table_counts_hits_per_stratum_and_names_the_misses(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    patient(out, "LIDC-IDRI-0001", 32.8, 4.8, True, True, False)
    patient(out, "LIDC-IDRI-0002", 30.8, 1.5, False, False, False)
    patient(out, "LIDC-IDRI-0003", 31.0, 4.0, False, True, True)
    patient(out, "LIDC-IDRI-0004", 6.8, 5.0, False, False, False)  # below 10 mm: left out
    monkeypatch.setattr(sys, "argv", ["strata.py", str(out)])
    strata.main()
    lines = capsys.readouterr().out.splitlines()
    assert "free      n= 1  guided  1  blind  1   guided misses: -; blind misses: -" in lines[1]
    assert "attached  n= 1  guided  1  blind  0   guided misses: -; blind misses: 0001" in lines[2]
    assert "subsolid  n= 1  guided  0  blind  0   guided misses: 0002; blind misses: 0002" in lines[3]


def test_the_bands_hold_their_lower_edge(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    patient(out, "LIDC-IDRI-0001", 10.0, 4.8, False, True, False)
    patient(out, "LIDC-IDRI-0002", 15.0, 1.5, False, False, False)
    patient(out, "LIDC-IDRI-0003", 19.9, 4.0, True, True, True)
    patient(out, "LIDC-IDRI-0004", 20.0, 5.0, False, False, True)
    patient(out, "LIDC-IDRI-0005", 9.9, 5.0, False, True, True)  # below 10 mm: left out
    monkeypatch.setattr(sys, "argv", ["strata.py", str(out)])
    strata.main()
    lines = capsys.readouterr().out.splitlines()
    assert "10-15 mm  n= 1  guided  1  blind  0   guided misses: -; blind misses: 0001" in lines[4]
    assert "15-20 mm  n= 2  guided  1  blind  1   guided misses: 0002; blind misses: 0002" in lines[5]
    assert ">=20 mm   n= 1  guided  0  blind  1   guided misses: 0004; blind misses: -" in lines[6]


def test_an_out_dir_from_before_the_site_says_to_rerun(tmp_path, monkeypatch):
    out = tmp_path / "out"
    patient(out, "LIDC-IDRI-0001", 32.8, 4.8, True, True, False)
    (out / "LIDC-IDRI-0001" / "target_site.json").unlink()
    monkeypatch.setattr(sys, "argv", ["strata.py", str(out)])
    with pytest.raises(SystemExit, match="target_site.json is missing"):
        strata.main()
