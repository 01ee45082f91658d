"""tools/train_blob_ranker.py and the select stage's learned ranking (`blind_tie_break = "learned"`).

- `fit` on the committed cases writes the committed model byte for byte;
- the loss's gradient matches finite differences, and the damped Newton optimum matches scipy's
  L-BFGS on the same loss;
- on a phantom run, every blob the blind search accepted carries the score the Python features
  and the committed model give it, and the blind centre is the best scored; `cases` reads the run.
"""
import csv
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from test_heldout import TOY
from test_train_safetensors import BIN

REPO = Path(__file__).resolve().parents[2]
TOOL = REPO / "tools" / "train_blob_ranker.py"
spec = importlib.util.spec_from_file_location("train_blob_ranker", TOOL)
ranker = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ranker)


def test_the_committed_model_is_what_fit_writes_from_the_committed_cases(tmp_path):
    out = tmp_path / "model.json"
    done = subprocess.run([sys.executable, str(TOOL), "fit", str(REPO / "models" / "blob_ranker_cases.csv"),
                           "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert out.read_bytes() == (REPO / "models" / "blob_ranker.json").read_bytes()
    model = json.loads(out.read_text())
    assert model["features"] == list(ranker.FEATURES) and model["anatomies"] == list(range(1, 9))


def synthetic_cases(rng, n=40):
    """Cases where the nodule is a round blob of middling response among drawn-out decoys."""
    cases = []
    for i in range(n):
        blobs = [{"response": 0.2 + 0.1 * rng.random(), "peak_score": 0.3 + 0.2 * rng.random(),
                  "roundness": 0.2 + 0.3 * rng.random(), "diameter_mm": 10 + 30 * rng.random(),
                  "depth_mm": 30 * rng.random(), "rank": 0} for _ in range(4)]
        blobs.append({"response": 0.15 + 0.1 * rng.random(), "peak_score": 0.3, "roundness": 0.6 + 0.3 * rng.random(),
                      "diameter_mm": 20.0, "depth_mm": 20.0, "rank": 0})
        blobs.sort(key=lambda b: -b["response"])
        for rank, b in enumerate(blobs):
            b["rank"] = rank
        strongest = blobs[0]["response"]
        on = [b["roundness"] >= 0.6 for b in blobs]
        cases.append((1 + i % 4, f"P{i}", [ranker.features(b, strongest) for b in blobs], on))
    return cases


def test_the_gradient_matches_finite_differences_and_the_optimum_matches_lbfgs():
    cases = synthetic_cases(np.random.default_rng(7))
    mean, sd = ranker.standardisation([(xs, on) for _, _, xs, on in cases])
    z = [([[(v - m) / s for v, m, s in zip(row, mean, sd)] for row in xs], on) for _, _, xs, on in cases]
    w = list(np.random.default_rng(1).normal(0, 0.5, len(ranker.FEATURES)))
    loss, grad, hess = ranker.loss_gradient_hessian(w, z, 0.5)
    h = 1e-6
    for j in range(len(w)):
        up = [v + (h if i == j else 0.0) for i, v in enumerate(w)]
        down = [v - (h if i == j else 0.0) for i, v in enumerate(w)]
        numeric = (ranker.loss_gradient_hessian(up, z, 0.5)[0] - ranker.loss_gradient_hessian(down, z, 0.5)[0]) / (2 * h)
        assert abs(numeric - grad[j]) < 1e-5 * max(1.0, abs(grad[j])), j
        numeric_row = (np.array(ranker.loss_gradient_hessian(up, z, 0.5)[1])
                       - np.array(ranker.loss_gradient_hessian(down, z, 0.5)[1])) / (2 * h)
        assert np.allclose(numeric_row, hess[j], atol=1e-4), j
    fitted, _, _, used = ranker.fit(cases, 0.5)
    assert used == len(cases)
    reference = minimize(lambda v: ranker.loss_gradient_hessian(list(v), z, 0.5)[:2], np.zeros(len(w)), jac=True,
                         method="L-BFGS-B", options={"gtol": 1e-10, "ftol": 1e-15})
    assert np.allclose(fitted, reference.x, atol=1e-5), (fitted, reference.x)
    # Roundness is what tells the nodule here.
    assert fitted[ranker.FEATURES.index("roundness")] > 1.0
    assert ranker.fit(cases, 0.5)[0] == fitted, "deterministic"


def test_bad_tables_and_runs_are_named(tmp_path):
    (tmp_path / "bad.csv").write_text("anatomy,patient\n1,P\n")
    done = subprocess.run([sys.executable, str(TOOL), "fit", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "m")],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "bad.csv" in done.stderr and "columns" in done.stderr
    done = subprocess.run([sys.executable, str(TOOL), "cases", "seed1", "--out", str(tmp_path / "c.csv")],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "ANATOMY=DIR" in done.stderr


def test_the_blind_search_takes_the_blob_the_committed_model_scores_highest(tmp_path):
    # The toy phantom under the shipped select, whose blind search ranks by the learned ranking.
    (tmp_path / "toy.toml").write_text(TOY.format(cohort=REPO / "tools" / "cohorts" / "paper19"))
    patient = "LIDC-IDRI-0003"
    done = subprocess.run([BIN, "run", "toy.toml", "--patients", patient], cwd=tmp_path, capture_output=True,
                          text=True, env={"CI": "true", "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stdout + done.stderr
    centres = json.loads((tmp_path / "out" / patient / "result.json").read_text())["centres"]
    accepted = centres["blind_accepted"]
    assert len(accepted) >= 2, "a ranking needs blobs to rank"
    model = json.loads((REPO / "models" / "blob_ranker.json").read_text())
    strongest = max(b["blob"]["response"] for b in accepted)
    for b in accepted:
        row = {"response": b["blob"]["response"], "peak_score": b["region"]["peak_score"],
               "roundness": b["region"]["roundness"], "diameter_mm": b["region"]["diameter_mm"],
               "depth_mm": b["depth_mm"], "rank": b["rank"]}
        x = ranker.features(row, strongest)
        score = sum(w * (v - m) / s for w, v, m, s in zip(model["weights"], x, model["mean"], model["sd"]))
        assert math.isclose(b["ranking_score"], score, rel_tol=1e-6, abs_tol=1e-6), (b, score)
    assert centres["blind"]["ranking_score"] == max(b["ranking_score"] for b in accepted)
    assert centres["blind"]["position_mm"] in [b["position_mm"] for b in accepted]
    # The run's accepted blobs are what `cases` collects for training.
    table = tmp_path / "cases.csv"
    done = subprocess.run([sys.executable, str(TOOL), "cases", f"1={tmp_path / 'out'}", "--out", str(table)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    with open(table, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["rank"]) for r in rows] == [b["rank"] for b in accepted]
    assert {r["patient"] for r in rows} == {patient}
