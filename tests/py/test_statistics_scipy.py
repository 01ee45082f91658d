"""The cohort statistics kernels (stages/kernels/statistics.rs) against scipy, through the hidden
`aret-pipe kernel statistics` developer command (docs/kernels.md), which reads {"x", "y"} as JSON
and prints every statistic:

- Pearson r and Spearman rho with two-sided p-values: scipy.stats.pearsonr / spearmanr;
- the Wilcoxon signed-rank test of x - y: scipy.stats.wilcoxon(x, y) with its defaults (the same
  W, the same p, and the same choice of exact / sign-flip permutation / normal approximation);
- percentile bootstrap CIs (mean, median, paired Pearson and Spearman): scipy.stats.bootstrap
  with method='percentile' and 10,000 resamples, within sampling error (the generators differ);
- Bland-Altman: numpy's mean and sample SD with scipy.stats.t.ppf(0.975, n - 1);
- inputs where scipy answers nan (constant input, too few pairs, no non-zero difference) are
  errors naming the problem.

p-values agree to 1e-6 relative, or 1e-12 absolute where they are tiny.
"""
import json
import os
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("ARET_PIPE_BIN", str(REPO / "target" / "debug" / "aret-pipe"))
RESAMPLES = 10_000


def ours(x, y, *options):
    proc = subprocess.run([BIN, "kernel", "statistics", "-", *map(str, options)], capture_output=True, text=True,
                          input=json.dumps({"x": [float(v) for v in x], "y": [float(v) for v in y]}))
    assert proc.returncode == 0, f"aret-pipe kernel statistics failed:\n{proc.stderr}"
    return json.loads(proc.stdout)


def assert_p(got, want, what):
    assert abs(got - want) <= max(1e-6 * abs(want), 1e-12), f"{what}: ours {got!r}, scipy {want!r}"


def assert_close(got, want, what, rel=1e-9):
    assert abs(got - want) <= rel * max(abs(want), 1e-12), f"{what}: ours {got!r}, reference {want!r}"


def pairs(kind, n, seed):
    """(x, y) of `n` pairs: continuous, with ties, with zero differences, or both."""
    rng = np.random.default_rng(seed)
    truth = rng.lognormal(6.0, 1.0, n)  # nodule-like volumes, mm^3
    pred = truth * rng.normal(1.0, 0.2, n) + rng.normal(0.0, 30.0, n)
    if kind in ("ties", "ties_and_zeros"):
        # Rounded to a coarse grid: tied values, and tied |differences|.
        truth, pred = np.round(truth, -2), np.round(pred, -2)
    if kind in ("zeros", "ties_and_zeros"):
        pred[:: max(2, n // 4)] = truth[:: max(2, n // 4)]
    return pred, truth


CASES = [(kind, n, seed) for kind in ("continuous", "ties", "zeros", "ties_and_zeros")
         for n in (3, 5, 10, 25, 60) for seed in (1, 2)]


def expected_method(x, y):
    """scipy's method='auto' choice (scipy/stats/_wilcoxon.py), in our names."""
    d = np.asarray(x, float) - np.asarray(y, float)
    nonzero = np.abs(d[d != 0])
    ties = len(np.unique(nonzero)) < len(nonzero)
    if len(d) > 50:
        return "normal"
    if not (ties or (d == 0).any()):
        return "exact"
    return "permutation" if len(d) <= 13 else "normal"


@pytest.mark.parametrize("kind,n,seed", CASES)
def test_correlations_match_scipy(kind, n, seed):
    x, y = pairs(kind, n, seed)
    got = ours(x, y, "--resamples", 10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns, then answers nan, for constant input
        for name, scipy_fn in (("pearson", stats.pearsonr), ("spearman", stats.spearmanr)):
            want = scipy_fn(x, y)
            if np.isnan(want.statistic):
                assert "constant" in got[name]["error"], got[name]
                continue
            assert_close(got[name]["r"], want.statistic, f"{name} r", rel=1e-12)
            assert_p(got[name]["p"], want.pvalue, f"{name} p")


@pytest.mark.parametrize("kind,n,seed", CASES)
def test_wilcoxon_matches_scipy(kind, n, seed):
    x, y = pairs(kind, n, seed)
    got = ours(x, y, "--resamples", 10)["wilcoxon"]
    if (x == y).all():
        assert got == {"error": "every paired difference is zero: the signed-rank test is undefined"}
        return
    want = stats.wilcoxon(x, y)
    assert got["method"] == expected_method(x, y)
    assert got["w"] == want.statistic, (got, want)
    assert_p(got["p"], want.pvalue, f"wilcoxon p ({got['method']})")
    assert got["n_nonzero"] == np.count_nonzero(x - y)


def test_wilcoxon_method_boundaries():
    """n = 13 with a tie is still enumerated, n = 14 is approximated; n = 50 without ties is
    exact, n = 51 approximated."""
    for n, method in ((13, "permutation"), (14, "normal")):
        d = np.arange(1.0, n + 1) * np.where(np.arange(n) % 3 == 0, -1, 1)
        d[1] = d[2]  # a tie
        got = ours(d, np.zeros(n), "--resamples", 10)["wilcoxon"]
        assert got["method"] == method
        assert_p(got["p"], stats.wilcoxon(d, np.zeros(n)).pvalue, f"n = {n}")
    for n, method in ((50, "exact"), (51, "normal")):
        d = np.arange(1.0, n + 1) * np.where(np.arange(n) % 4 == 0, -1, 1)
        got = ours(d, np.zeros(n), "--resamples", 10)["wilcoxon"]
        assert got["method"] == method
        assert_p(got["p"], stats.wilcoxon(d, np.zeros(n)).pvalue, f"n = {n}")
    # Every sign the same, n = 3: the smallest exact p, 2/8.
    got = ours([1, 2, 3], [0, 0, 0], "--resamples", 10)["wilcoxon"]
    assert (got["w"], got["p"], got["method"]) == (0, 0.25, "exact")


@pytest.mark.parametrize("n", [3, 5, 10, 25, 60])
def test_bland_altman_matches_numpy_and_scipy_t(n):
    x, y = pairs("continuous", n, 7)
    got = ours(x, y, "--resamples", 10)["bland_altman"]
    d = x - y
    bias, sd = d.mean(), d.std(ddof=1)
    half = stats.t.ppf(0.975, n - 1) * sd / np.sqrt(n)
    assert_close(got["bias"], bias, "bias")
    assert_close(got["sd"], sd, "sd")
    for i, sign in enumerate((-1, 1)):
        assert_close(got["loa"][i], bias + sign * 1.96 * sd, "limit of agreement")
        assert_close(got["bias_ci"][i], bias + sign * half, "bias CI")


def _ranks(a, axis):
    return stats.rankdata(a, axis=axis)


SCIPY_STATISTIC = {
    "mean_x": (lambda x, axis: np.mean(x, axis=axis), False),
    "median_x": (lambda x, axis: np.median(x, axis=axis), False),
    "pearson_r": (lambda x, y, axis: stats.pearsonr(x, y, axis=axis).statistic, True),
    # Spearman's rho is Pearson's r of the ranks: vectorised, unlike spearmanr.
    "spearman_r": (lambda x, y, axis: stats.pearsonr(_ranks(x, axis), _ranks(y, axis), axis=axis).statistic, True),
}


@pytest.mark.parametrize("n,seed", [(10, 3), (25, 4), (60, 5)])
def test_bootstrap_percentile_cis_match_scipy_within_sampling_error(n, seed):
    x, y = pairs("continuous", n, seed)
    got = ours(x, y, "--resamples", RESAMPLES, "--seed", seed)["bootstrap"]
    assert got == ours(x, y, "--resamples", RESAMPLES, "--seed", seed)["bootstrap"], "not deterministic for a seed"
    assert got != ours(x, y, "--resamples", RESAMPLES, "--seed", seed + 1)["bootstrap"]
    for name, (statistic, paired) in SCIPY_STATISTIC.items():
        data = (x, y) if paired else (x,)
        want = stats.bootstrap(data, statistic, paired=paired, method="percentile", n_resamples=RESAMPLES,
                               confidence_level=0.95, rng=np.random.default_rng(seed)).confidence_interval
        # Sampling tolerance: the two generators draw different resamples. The ends of a
        # 10,000-resample percentile interval move by about 1-2 % of the spread of the data (a
        # correlation's range is 2); the median of a small sample jumps between order statistics.
        spread = 2.0 if paired else np.ptp(x)
        tolerance = (0.05 if name == "median_x" else 0.03) * spread
        assert got[name]["undefined"] == 0
        assert abs(got[name]["lo"] - want.low) <= tolerance, (name, got[name], want)
        assert abs(got[name]["hi"] - want.high) <= tolerance, (name, got[name], want)


def test_undefined_inputs_are_errors_where_scipy_answers_nan():
    got = ours([1, 2], [3, 4], "--resamples", 10)
    assert got["pearson"] == {"error": "a correlation needs 3 or more values, got 2"}
    assert got["spearman"] == {"error": "a correlation needs 3 or more values, got 2"}
    got = ours([1, 2, 3, 4], [5, 5, 5, 5], "--resamples", 10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert np.isnan(stats.pearsonr([1, 2, 3, 4], [5, 5, 5, 5]).statistic)
        assert np.isnan(stats.spearmanr([1, 2, 3, 4], [5, 5, 5, 5]).statistic)
    assert got["pearson"] == {"error": "y is constant (every value is 5): the correlation is undefined"}
    assert got["spearman"] == got["pearson"]
    # The correlation is undefined on every resample, so there is no interval.
    assert got["bootstrap"]["pearson_r"] == {"error": "the statistic is undefined (NaN) on every one of the 10 "
                                                      "bootstrap resamples"}
    got = ours([], [], "--resamples", 10)
    assert got["n"] == 0
    assert got["mean_x"] == {"error": "the mean needs 1 or more values, got 0"}
    assert got["bland_altman"] == {"error": "Bland–Altman needs 2 or more values, got 0"}
    got = ours([1, 2, 3], [1, 2], "--resamples", 10)
    assert got["wilcoxon"] == {"error": "paired values differ in length: 3 and 2"}
