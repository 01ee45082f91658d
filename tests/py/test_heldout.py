"""tools/heldout.py: each anatomy's figures come from the candidate chosen on the other
anatomies, never on itself; the runs share one cache, so a second candidate of a `[select]` key
recomputes only select and metrics; the table and heldout.json hold the same figures."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from test_train_safetensors import BIN

REPO = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("heldout", REPO / "tools" / "heldout.py")
heldout = importlib.util.module_from_spec(spec)
spec.loader.exec_module(heldout)


def figures(guided_centre, ape=10.0):
    return {"guided_centre": guided_centre, "guided_hit": guided_centre, "blind_centre": 0.0, "blind_hit": 0.0,
            "median_dice": 0.5, "median_ape_over_guided_hits_pct": ape}


def test_each_anatomy_is_judged_under_the_choice_of_the_others():
    # a is best on anatomy 1 alone, b on 2 and 3: held out, 1 gets b and 2, 3 get a.
    table = {(1, "a"): figures(1.0), (2, "a"): figures(0.0), (3, "a"): figures(0.0),
             (1, "b"): figures(0.0), (2, "b"): figures(0.5), (3, "b"): figures(0.5)}
    chosen = heldout.leave_one_out(table, ["a", "b"], [1, 2, 3])
    assert chosen == {1: "b", 2: "a", 3: "a"}
    held = [table[(s, chosen[s])]["guided_centre"] for s in (1, 2, 3)]
    assert held == [0.0, 0.0, 0.0], "in sample each candidate scores 1/3; held out the choice scores 0"


def test_ties_go_to_the_lower_ape_then_to_the_first_candidate_listed():
    table = {(s, n): figures(0.5, ape) for s in (1, 2) for n, ape in (("a", 20.0), ("b", 10.0), ("c", 10.0))}
    assert heldout.leave_one_out(table, ["a", "b", "c"], [1, 2]) == {1: "b", 2: "b"}
    table[(1, "b")] = figures(0.5, None)  # no guided hit to size: worst
    assert heldout.leave_one_out(table, ["a", "b", "c"], [1, 2]) == {1: "b", 2: "c"}


def test_bad_arguments_say_how_to_write_them():
    with pytest.raises(SystemExit, match="SECTION.KEY=VALUE1,VALUE2"):
        heldout.choice("rival_ratio")
    with pytest.raises(SystemExit, match="two anatomies"):
        heldout.seeds("3")
    assert heldout.seeds("1,3-5") == [1, 3, 4, 5]


TOY = """[pipeline]
name = "heldout"
cache_dir = "cache"
[dataset]
kind = "phantom"
cohort = "{cohort}"
[drr]
width_px = 48
height_px = 48
[train]
grid = 32
[train.dense_tv]
iterations = 60
"""


def test_the_protocol_runs_every_candidate_on_every_anatomy_from_one_cache(tmp_path):
    (tmp_path / "toy.toml").write_text(TOY.format(cohort=REPO / "tools" / "cohorts" / "paper19"))
    command = [sys.executable, str(REPO / "tools" / "heldout.py"), "toy.toml", "--seeds", "1,2",
               "--choose", "select.blob.rival_ratio=0.5,0.9", "--patients", "LIDC-IDRI-0003", "--group", "all"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True,
                          env={"ARET_PIPE_BIN": BIN, "CI": "true", "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads((tmp_path / "out-heldout" / "heldout.json").read_text())
    assert report["candidates"] == ["select.blob.rival_ratio=0.5", "select.blob.rival_ratio=0.9"]
    for seed in ("1", "2"):
        chosen = report["anatomies"][seed]["chosen"]
        assert report["anatomies"][seed]["held_out"] == report["every_run"][f"seed{seed}"][chosen]
        out = tmp_path / "out-heldout" / f"seed{seed}"
        config = json.loads((out / chosen / "summary.json").read_text())
        assert config["scored"] == 1
        # The second candidate reuses the first one's fit: only select computes, and metrics
        # where select's answer changed.
        records = json.loads((out / "select.blob.rival_ratio=0.9" / "run_report.json").read_text())["records"]
        computed = {r["stage"] for r in records if r["outcome"] == "computed"}
        assert computed - {"metrics"} == {"select"}, computed
    # The second anatomy is a phantom of its own: it is drawn and fitted again.
    records = json.loads((tmp_path / "out-heldout" / "seed2" / "select.blob.rival_ratio=0.5" / "run_report.json")
                         .read_text())["records"]
    assert {"phantom", "train"} <= {r["stage"] for r in records if r["outcome"] == "computed"}
    assert done.stdout.count("| 1 |") == 1 and "held out: mean" in done.stdout
    assert report["held_out"]["guided_hit"]["n"] == 2
