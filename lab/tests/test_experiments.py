"""lab/scripts/experiments.py at a checkout past lab-v1: rows whose presets are gone keep their
lines and say where they re-run, instead of crashing."""

import pytest

from lab_scripts import ROOT, load

experiments = load("experiments")


def block(doc):
    return doc.split(experiments.START, 1)[1].split(experiments.END, 1)[0]


def test_without_results_the_table_is_the_logs_own():
    doc = (ROOT / "lab" / "log.md").read_text()
    table = experiments.table({}, experiments.rows_in(doc))
    assert table.splitlines()[2:] == block(doc).strip().split("\n\n", 1)[0].splitlines()[2:]


def test_a_row_with_neither_preset_nor_line_says_it_runs_only_at_lab_v1():
    lines = experiments.table({}, {}).splitlines()
    seed2 = next(line for line in lines if line.startswith("| default-seed2 |"))
    assert "`presets/default_seed2.toml` | – |" in seed2 and "only at lab-v1" in seed2
    # A product preset that kept a row's name with another configuration re-runs only there too.
    readers = next(line for line in lines if line.startswith("| phantom-readers |"))
    assert "`presets/phantom_readers.toml` | – |" in readers and "only at lab-v1" in readers
    paper = next(line for line in lines if line.startswith("| paper |"))
    assert "| readers |" in paper, "the shipped phantom, which the paper preset does not change"
    assert experiments.out_dir(str(ROOT / "presets" / "paper.toml")) == str(ROOT / "out-paper")


def test_asking_for_a_row_whose_preset_is_gone_points_to_lab_v1_and_runs_nothing(tmp_path):
    doc = tmp_path / "log.md"
    doc.write_text((ROOT / "lab" / "log.md").read_text())
    with pytest.raises(SystemExit) as e:
        experiments.main(["--only", "paper", "default-seed2", "--bin", str(tmp_path / "no-binary"), "--doc", str(doc)])
    assert "default-seed2 (presets/default_seed2.toml)" in str(e.value) and "git checkout lab-v1" in str(e.value)
    assert "paper (" not in str(e.value)
    with pytest.raises(SystemExit, match="no row nope"):
        experiments.main(["--only", "nope", "--doc", str(doc)])
    assert doc.read_text() == (ROOT / "lab" / "log.md").read_text()


def test_rebuilding_the_table_keeps_the_rows_it_cannot_run(tmp_path, monkeypatch):
    doc = tmp_path / "log.md"
    doc.write_text((ROOT / "lab" / "log.md").read_text())
    # No out dir holds results: every row keeps its line.
    monkeypatch.setattr(experiments, "out_dir", lambda path: str(tmp_path / "nowhere"))
    assert experiments.main(["--no-run", "--doc", str(doc)]) == 0
    assert doc.read_text() == (ROOT / "lab" / "log.md").read_text()
