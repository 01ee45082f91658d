//! The inferential statistics of the cohort metrics stage (SPEC §3 metrics): Pearson and
//! Spearman correlations with two-sided p-values, the Wilcoxon signed-rank test, percentile
//! bootstrap confidence intervals and Bland–Altman agreement — each computed as scipy computes
//! it (checked against scipy in `tests/py/test_statistics_scipy.py`; the choices are in
//! `docs/kernels.md`). Pure: slices in, numbers out; the metrics stage decides what to compare.
//!
//! Where scipy answers nan (a constant input, too few values, no non-zero difference) we
//! return a [`StatisticsError`] naming the problem instead, and any NaN or infinite input is an
//! error rather than a nan result.

use crate::kernels::stats;
use rand::{Rng as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use statrs::distribution::{ContinuousCDF as _, StudentsT};
use statrs::function::{beta::beta_reg, erf::erfc};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatisticsError {
    #[error("{what} needs {min} or more values, got {len}")]
    TooFew { what: &'static str, min: usize, len: usize },
    #[error("paired values differ in length: {x} and {y}")]
    LengthMismatch { x: usize, y: usize },
    #[error("{which}[{index}] is {value}: only finite values are accepted")]
    NotFinite { which: &'static str, index: usize, value: f64 },
    #[error("{which} is constant (every value is {value}): the correlation is undefined")]
    Constant { which: &'static str, value: f64 },
    #[error("every paired difference is zero: the signed-rank test is undefined")]
    AllDifferencesZero,
    #[error("the confidence level must be in (0, 1), got {0}")]
    Confidence(f64),
    #[error("the bootstrap needs at least one resample")]
    NoResamples,
    #[error("the statistic is undefined (NaN) on every one of the {0} bootstrap resamples")]
    UndefinedOnEveryResample(usize),
}

/// A correlation coefficient and its two-sided p-value for "no correlation".
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Correlation {
    pub r: f64,
    pub p_two_sided: f64,
}

/// How a [`Wilcoxon`] p-value was computed; scipy's `method='auto'` choice.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum WilcoxonMethod {
    /// The exact null distribution of W+ over ranks 1..n (n ≤ 50, no ties, no zeros).
    Exact,
    /// Every one of the 2ⁿ sign assignments enumerated (n ≤ 13 with ties or zeros): scipy's
    /// `permutation_test`, which is exhaustive, hence deterministic, at that size.
    Permutation,
    /// The normal approximation with the tie correction, without continuity correction.
    Normal,
}

/// The Wilcoxon signed-rank test of paired samples, two-sided.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Wilcoxon {
    /// min(W+, W−), the statistic scipy reports for the two-sided test.
    pub w: f64,
    pub p_two_sided: f64,
    pub method: WilcoxonMethod,
    /// Pairs with a non-zero difference (zero differences are dropped, `zero_method='wilcox'`).
    pub n_nonzero: usize,
}

/// A percentile bootstrap confidence interval.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BootstrapCi {
    pub lo: f64,
    pub hi: f64,
    /// Resamples whose statistic was undefined (NaN), left out of the percentiles.
    pub undefined: usize,
}

/// Bland–Altman agreement of a measurement with a reference.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BlandAltman {
    /// Mean of the differences `pred − truth`.
    pub bias: f64,
    /// Sample standard deviation of the differences (ddof 1).
    pub sd: f64,
    /// 95 % limits of agreement, `bias ∓ 1.96·sd`.
    pub loa: [f64; 2],
    /// 95 % confidence interval of the bias, `bias ∓ t(0.975, n−1)·sd/√n`.
    pub bias_ci: [f64; 2],
}

/// The arithmetic mean; an error for no values or a non-finite one.
pub fn mean(values: &[f64]) -> Result<f64, StatisticsError> {
    check(values, "values", "the mean", 1)?;
    Ok(values.iter().sum::<f64>() / values.len() as f64)
}

/// The median (numpy's: the two middle values averaged); an error for no values or a
/// non-finite one.
pub fn median(values: &[f64]) -> Result<f64, StatisticsError> {
    check(values, "values", "the median", 1)?;
    Ok(stats::median(values))
}

/// Pearson's r and its two-sided p-value, as `scipy.stats.pearsonr(x, y)`: r from the centred
/// vectors each scaled to unit length (clipped to [−1, 1]), p from r's exact null
/// distribution Beta(n/2 − 1, n/2 − 1) on [−1, 1] — the t test with n − 2 degrees of freedom.
/// Needs n ≥ 3 (scipy answers r = ±1, p = 1 for n = 2) and non-constant inputs (scipy answers nan).
pub fn pearson(x: &[f64], y: &[f64]) -> Result<Correlation, StatisticsError> {
    check_pairs(x, y, "a correlation", 3)?;
    check_not_constant(x, "x")?;
    check_not_constant(y, "y")?;
    let r = pearson_r(x, y).clamp(-1.0, 1.0);
    // scipy: 2·min(cdf(r), sf(r)) of Beta(a, a) on [−1, 1], i.e. 2·I_{(1−|r|)/2}(a, a).
    // (1 − |r|)/2 keeps its precision as |r| → 1, where 1 − r² would not.
    let a = x.len() as f64 / 2.0 - 1.0;
    let p = (2.0 * beta_reg(a, a, (1.0 - r.abs()) / 2.0)).min(1.0);
    Ok(Correlation { r, p_two_sided: p })
}

/// Spearman's ρ and its two-sided p-value, as `scipy.stats.spearmanr(x, y)`: Pearson's r of the
/// average ranks ([`rank_average`]), p from t = ρ·√((n − 2)/((1 + ρ)(1 − ρ))) with n − 2 degrees
/// of freedom. Needs n ≥ 3 and non-constant inputs (scipy answers nan).
pub fn spearman(x: &[f64], y: &[f64]) -> Result<Correlation, StatisticsError> {
    check_pairs(x, y, "a correlation", 3)?;
    check_not_constant(x, "x")?;
    check_not_constant(y, "y")?;
    let rho = corrcoef(&rank_average(x), &rank_average(y)).clamp(-1.0, 1.0);
    let dof = (x.len() - 2) as f64;
    let t = rho * (dof / ((rho + 1.0) * (1.0 - rho))).max(0.0).sqrt();
    // Two-sided tail of Student's t: I_{dof/(dof+t²)}(dof/2, 1/2); |ρ| = 1 gives t = ∞, p = 0.
    let p = if t.is_finite() { beta_reg(dof / 2.0, 0.5, dof / (dof + t * t)) } else { 0.0 };
    Ok(Correlation { r: rho, p_two_sided: p.min(1.0) })
}

/// Ranks 1..n with ties given their average rank (`scipy.stats.rankdata(values, 'average')`).
/// Values must not be NaN.
pub fn rank_average(values: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut ranks = vec![0.0; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        // `==`, not total_cmp: −0.0 and 0.0 tie, as in numpy.
        while end < order.len() && values[order[end]] == values[order[start]] {
            end += 1;
        }
        // Ranks start+1 ..= end averaged; a half-integer, exact in f64.
        let rank = (start + 1 + end) as f64 / 2.0;
        for &i in &order[start..end] {
            ranks[i] = rank;
        }
        start = end;
    }
    ranks
}

/// The Wilcoxon signed-rank test of the differences `x − y`, two-sided, as
/// `scipy.stats.wilcoxon(x, y)` with its defaults (`zero_method='wilcox'`, `correction=False`,
/// `method='auto'`, as scipy 1.17 decides it): zero differences are dropped, |differences|
/// ranked with average ties, and the p-value is
/// - exact (the null distribution of W+ over ranks 1..m) when n ≤ 50 and there are no ties
///   and no zeros;
/// - an exhaustive sign-flip permutation test when n ≤ 13 with ties or zeros;
/// - otherwise the normal approximation of W+ with the tie correction (no continuity correction),
///
/// n counting the zero differences too, as scipy does. Every difference zero is an error
/// (scipy answers p = 1 for n ≤ 13, nan above).
pub fn wilcoxon_signed_rank(x: &[f64], y: &[f64]) -> Result<Wilcoxon, StatisticsError> {
    check_pairs(x, y, "the signed-rank test", 1)?;
    let n = x.len();
    let d: Vec<f64> = x.iter().zip(y).map(|(a, b)| a - b).filter(|&d| d != 0.0).collect();
    if d.is_empty() {
        return Err(StatisticsError::AllDifferencesZero);
    }
    let has_zeros = d.len() < n;
    let magnitudes: Vec<f64> = d.iter().map(|v| v.abs()).collect();
    let ranks = rank_average(&magnitudes);
    // Folded from +0.0: an empty f64 `sum()` is −0.0, which the report would print as "-0".
    let rank_sum =
        |positive: bool| d.iter().zip(&ranks).filter(|(v, _)| (**v > 0.0) == positive).fold(0.0, |sum, (_, r)| sum + r);
    let (w_plus, w_minus) = (rank_sum(true), rank_sum(false));
    let tie_sizes = tie_sizes(&magnitudes);
    let has_ties = tie_sizes.iter().any(|&t| t > 1);

    let method = if n > 50 {
        WilcoxonMethod::Normal
    } else if !(has_ties || has_zeros) {
        WilcoxonMethod::Exact
    } else if n <= 13 {
        WilcoxonMethod::Permutation
    } else {
        WilcoxonMethod::Normal
    };
    let p = match method {
        // Without ties the doubled ranks are 2, 4, …, 2m: the same enumeration is the exact
        // distribution, so one routine serves both.
        WilcoxonMethod::Exact | WilcoxonMethod::Permutation => sign_flip_p(&ranks, w_plus),
        WilcoxonMethod::Normal => {
            let m = d.len() as f64;
            let mean = m * (m + 1.0) * 0.25;
            let tie_term: f64 = tie_sizes.iter().map(|&t| (t as f64).powi(3) - t as f64).sum();
            let se = ((m * (m + 1.0) * (2.0 * m + 1.0) - tie_term / 2.0) / 24.0).sqrt();
            let z = (w_plus - mean) / se;
            // 2·Φ(−|z|) = erfc(|z|/√2).
            erfc(z.abs() / std::f64::consts::SQRT_2).min(1.0)
        }
    };
    Ok(Wilcoxon { w: w_plus.min(w_minus), p_two_sided: p, method, n_nonzero: d.len() })
}

/// Two-sided p-value of W+ = `w_plus` over all 2^m sign assignments to `ranks`:
/// 2·min(P(W+ ≤ w), P(W+ ≥ w)), at most 1. Ranks are half-integers, so the sums are counted on
/// doubled ranks, in integers: no tolerance is needed where scipy's permutation test uses one.
fn sign_flip_p(ranks: &[f64], w_plus: f64) -> f64 {
    let doubled: Vec<usize> = ranks.iter().map(|r| (2.0 * r).round() as usize).collect();
    let total: usize = doubled.iter().sum();
    // counts[s]: sign assignments whose positive doubled ranks sum to s. Counts stay below
    // 2^50 for n ≤ 50, exact in f64.
    let mut counts = vec![0.0f64; total + 1];
    counts[0] = 1.0;
    let mut reach = 0;
    for &r in &doubled {
        for s in (0..=reach).rev() {
            counts[s + r] += counts[s];
        }
        reach += r;
    }
    let observed = (2.0 * w_plus).round() as usize;
    let all: f64 = counts.iter().sum();
    let below: f64 = counts[..=observed].iter().sum();
    let above: f64 = counts[observed..].iter().sum();
    (2.0 * below.min(above) / all).min(1.0)
}

/// Sizes of the groups of equal values (1 for an untied value).
fn tie_sizes(values: &[f64]) -> Vec<usize> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let mut sizes = Vec::new();
    let mut start = 0;
    for i in 1..=v.len() {
        if i == v.len() || v[i] != v[start] {
            sizes.push(i - start);
            start = i;
        }
    }
    sizes
}

/// A percentile bootstrap confidence interval of `statistic` over `values`, as
/// `scipy.stats.bootstrap((values,), statistic, method='percentile')`: `resamples` resamples of
/// n values drawn with replacement by a ChaCha8 generator seeded with `seed` (so the interval
/// is deterministic for a seed; scipy's own generator differs, so its interval agrees only
/// within sampling error), ends at numpy's linear percentiles (1 ∓ confidence)/2 of the
/// bootstrap distribution. Resamples where the statistic is NaN are left out and counted
/// (scipy would answer nan for the whole interval).
pub fn bootstrap_ci(
    values: &[f64],
    statistic: impl Fn(&[f64]) -> f64,
    resamples: usize,
    confidence: f64,
    seed: u64,
) -> Result<BootstrapCi, StatisticsError> {
    check(values, "values", "the bootstrap", 1)?;
    let mut resample = vec![0.0; values.len()];
    bootstrap(values.len(), resamples, confidence, seed, |indices| {
        for (slot, &i) in resample.iter_mut().zip(indices) {
            *slot = values[i];
        }
        statistic(&resample)
    })
}

/// [`bootstrap_ci`] of a statistic of pairs (a correlation): each resample draws n (x, y)
/// pairs together, as `scipy.stats.bootstrap((x, y), statistic, paired=True,
/// method='percentile')`.
pub fn bootstrap_ci_paired(
    x: &[f64],
    y: &[f64],
    statistic: impl Fn(&[f64], &[f64]) -> f64,
    resamples: usize,
    confidence: f64,
    seed: u64,
) -> Result<BootstrapCi, StatisticsError> {
    check_pairs(x, y, "the bootstrap", 1)?;
    let (mut rx, mut ry) = (vec![0.0; x.len()], vec![0.0; y.len()]);
    bootstrap(x.len(), resamples, confidence, seed, |indices| {
        for ((sx, sy), &i) in rx.iter_mut().zip(ry.iter_mut()).zip(indices) {
            (*sx, *sy) = (x[i], y[i]);
        }
        statistic(&rx, &ry)
    })
}

/// The resampling loop shared by both bootstraps: `statistic_of` gets each resample's indices.
fn bootstrap(
    n: usize,
    resamples: usize,
    confidence: f64,
    seed: u64,
    mut statistic_of: impl FnMut(&[usize]) -> f64,
) -> Result<BootstrapCi, StatisticsError> {
    if !(confidence > 0.0 && confidence < 1.0) {
        return Err(StatisticsError::Confidence(confidence));
    }
    if resamples == 0 {
        return Err(StatisticsError::NoResamples);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut indices = vec![0; n];
    let mut distribution = Vec::with_capacity(resamples);
    for _ in 0..resamples {
        for i in indices.iter_mut() {
            *i = rng.gen_range(0..n);
        }
        distribution.push(statistic_of(&indices));
    }
    let before = distribution.len();
    distribution.retain(|v| !v.is_nan());
    let undefined = before - distribution.len();
    if distribution.is_empty() {
        return Err(StatisticsError::UndefinedOnEveryResample(resamples));
    }
    let alpha = (1.0 - confidence) / 2.0;
    let ends = stats::percentiles(&distribution, &[100.0 * alpha, 100.0 * (1.0 - alpha)])
        .expect("a non-empty distribution and percentiles inside [0, 100]");
    Ok(BootstrapCi { lo: ends[0], hi: ends[1], undefined })
}

/// Bland–Altman agreement of `pred` with `truth` (differences `pred − truth`): the bias, the
/// sample SD, the 95 % limits of agreement `bias ∓ 1.96·sd` and the bias CI
/// `bias ∓ t(0.975, n−1)·sd/√n` (SPEC §3 metrics). Needs n ≥ 2 for a standard deviation.
pub fn bland_altman(pred: &[f64], truth: &[f64]) -> Result<BlandAltman, StatisticsError> {
    check_pairs(pred, truth, "Bland–Altman", 2)?;
    let d: Vec<f64> = pred.iter().zip(truth).map(|(p, t)| p - t).collect();
    let n = d.len() as f64;
    let bias = d.iter().sum::<f64>() / n;
    let sd = (d.iter().map(|v| (v - bias).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let t = StudentsT::new(0.0, 1.0, n - 1.0).expect("n − 1 ≥ 1 degrees of freedom").inverse_cdf(0.975);
    let half = t * sd / n.sqrt();
    Ok(BlandAltman { bias, sd, loa: [bias - 1.96 * sd, bias + 1.96 * sd], bias_ci: [bias - half, bias + half] })
}

/// r of two equally long, non-constant, finite samples, formed operation by operation as
/// scipy's pearsonr forms it (centred vectors scaled by their largest magnitude for the norm,
/// then each divided by its norm, then dotted): near |r| = 1 the p-value of a small sample
/// depends on r's last bits (p ∝ √(1 − |r|) for n = 3), so the rounding must be scipy's too.
fn pearson_r(x: &[f64], y: &[f64]) -> f64 {
    let unit = |v: &[f64]| {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        let centred: Vec<f64> = v.iter().map(|a| a - m).collect();
        let max = centred.iter().fold(0.0f64, |acc, a| acc.max(a.abs()));
        let norm = max * centred.iter().map(|a| (a / max) * (a / max)).sum::<f64>().sqrt();
        centred.into_iter().map(|a| a / norm).collect::<Vec<f64>>()
    };
    unit(x).iter().zip(unit(y)).map(|(a, b)| a * b).sum()
}

/// r as `np.corrcoef` forms it, which spearmanr uses: the covariance divided by each standard
/// deviation in turn (so identical rankings give exactly 1, where [`pearson_r`] may not).
fn corrcoef(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let dot = |a: &[f64], ma: f64, b: &[f64], mb: f64| a.iter().zip(b).map(|(u, v)| (u - ma) * (v - mb)).sum::<f64>();
    let scale = 1.0 / (n - 1.0);
    let (cxy, cxx, cyy) = (dot(x, mx, y, my) * scale, dot(x, mx, x, mx) * scale, dot(y, my, y, my) * scale);
    cxy / cxx.sqrt() / cyy.sqrt()
}

/// At least `min` values, all finite.
fn check(values: &[f64], which: &'static str, what: &'static str, min: usize) -> Result<(), StatisticsError> {
    if values.len() < min {
        return Err(StatisticsError::TooFew { what, min, len: values.len() });
    }
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(StatisticsError::NotFinite { which, index, value: values[index] }),
        None => Ok(()),
    }
}

/// Equal lengths, at least `min` pairs, all finite.
fn check_pairs(x: &[f64], y: &[f64], what: &'static str, min: usize) -> Result<(), StatisticsError> {
    if x.len() != y.len() {
        return Err(StatisticsError::LengthMismatch { x: x.len(), y: y.len() });
    }
    check(x, "x", what, min)?;
    check(y, "y", what, min)
}

fn check_not_constant(values: &[f64], which: &'static str) -> Result<(), StatisticsError> {
    if values.iter().all(|&v| v == values[0]) {
        return Err(StatisticsError::Constant { which, value: values[0] });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * b.abs().max(1e-300)
    }

    #[test]
    fn ranks_average_ties_as_scipy_rankdata() {
        // scipy.stats.rankdata([3, 1, 4, 1, 5, 9, 2, 6, 5])
        let got = rank_average(&[3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0, 5.0]);
        assert_eq!(got, vec![4.0, 1.5, 5.0, 1.5, 6.5, 9.0, 3.0, 8.0, 6.5]);
        assert!(rank_average(&[]).is_empty());
    }

    #[test]
    fn pearson_and_spearman_match_scipy() {
        // scipy.stats.pearsonr([1, 2, 3, 4, 5], [2, 1, 4, 3, 5]) = (0.8, 0.10408803866182782)
        let c = pearson(&[1.0, 2.0, 3.0, 4.0, 5.0], &[2.0, 1.0, 4.0, 3.0, 5.0]).unwrap();
        assert!(close(c.r, 0.8, 1e-14) && close(c.p_two_sided, 0.10408803866182782, 1e-10), "{c:?}");
        // scipy.stats.spearmanr([1, 2, 3, 4, 5], [2, 2, 4, 3, 5]) = (0.8720815992723809, 0.05385421772754213)
        let s = spearman(&[1.0, 2.0, 3.0, 4.0, 5.0], &[2.0, 2.0, 4.0, 3.0, 5.0]).unwrap();
        assert!(close(s.r, 0.8720815992723809, 1e-14) && close(s.p_two_sided, 0.05385421772754213, 1e-10), "{s:?}");
        // A perfect monotone relation: ρ = 1, p = 0; a perfect line: r = 1, p = 0.
        let s = spearman(&[1.0, 2.0, 3.0], &[1.0, 4.0, 9.0]).unwrap();
        assert_eq!((s.r, s.p_two_sided), (1.0, 0.0));
        // scipy.stats.pearsonr([1, 2, 3], [-2, -4, -6]) = (-0.9999999999999998, 1.3415758552508146e-08):
        // rounding keeps r off −1, in scipy too.
        let c = pearson(&[1.0, 2.0, 3.0], &[-2.0, -4.0, -6.0]).unwrap();
        assert!(close(c.r, -1.0, 1e-15) && close(c.p_two_sided, 1.3415758552508146e-08, 1e-6), "{c:?}");
    }

    #[test]
    fn correlations_reject_what_scipy_answers_nan_for() {
        let e = pearson(&[1.0, 2.0], &[1.0, 2.0]).unwrap_err();
        assert_eq!(e, StatisticsError::TooFew { what: "a correlation", min: 3, len: 2 });
        assert_eq!(e.to_string(), "a correlation needs 3 or more values, got 2");
        let e = spearman(&[1.0, 2.0, 3.0], &[4.0, 4.0, 4.0]).unwrap_err();
        assert_eq!(e.to_string(), "y is constant (every value is 4): the correlation is undefined");
        let e = pearson(&[1.0, f64::NAN, 3.0], &[1.0, 2.0, 3.0]).unwrap_err();
        assert_eq!(e.to_string(), "x[1] is NaN: only finite values are accepted");
        assert_eq!(pearson(&[], &[]).unwrap_err(), StatisticsError::TooFew { what: "a correlation", min: 3, len: 0 });
        assert_eq!(pearson(&[1.0], &[1.0, 2.0]).unwrap_err(), StatisticsError::LengthMismatch { x: 1, y: 2 });
    }

    #[test]
    fn wilcoxon_exact_permutation_and_normal_as_scipy() {
        let zeros = [0.0; 20];
        // scipy.stats.wilcoxon([1, 2, 3, 4, 5, 6], [0] * 6): W = 0, p = 2/64 (exact)
        let w = wilcoxon_signed_rank(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], &zeros[..6]).unwrap();
        assert_eq!((w.w, w.p_two_sided, w.method), (0.0, 0.03125, WilcoxonMethod::Exact));
        // [1.5, −2, 3, 4, 5, −6, 7]: W− = 2 + 6 = 8, p = 0.375 (exact)
        let w = wilcoxon_signed_rank(&[1.5, -2.0, 3.0, 4.0, 5.0, -6.0, 7.0], &zeros[..7]).unwrap();
        assert_eq!((w.w, w.p_two_sided, w.method), (8.0, 0.375, WilcoxonMethod::Exact));
        // A tie and a zero, n = 6 ≤ 13: the exhaustive sign flips; W = 1.5, p = 0.1875
        let w = wilcoxon_signed_rank(&[1.0, -1.0, 2.0, 0.0, 3.0, 4.0], &zeros[..6]).unwrap();
        assert_eq!((w.w, w.p_two_sided, w.method, w.n_nonzero), (1.5, 0.1875, WilcoxonMethod::Permutation, 5));
        // n = 20 with a zero: the normal approximation; W = 65, p = 0.22732992995598733
        let d: Vec<f64> = (1..=20)
            .map(|i| {
                if i == 6 {
                    0.0
                } else if (i - 1) % 3 == 0 {
                    -(i as f64)
                } else {
                    i as f64
                }
            })
            .collect();
        let w = wilcoxon_signed_rank(&d, &zeros).unwrap();
        assert_eq!((w.w, w.method), (65.0, WilcoxonMethod::Normal));
        // statrs' erfc is good to about 1e-10 relative here.
        assert!(close(w.p_two_sided, 0.22732992995598733, 1e-9), "{w:?}");
    }

    #[test]
    fn wilcoxon_w_is_plus_zero_when_every_difference_has_one_sign() {
        // scipy.stats.wilcoxon([1, 2, 3, 4, 5, 6], [2, 4, 6, 8, 10, 12]): statistic 0.0, p 0.03125.
        let w = wilcoxon_signed_rank(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], &[2.0, 4.0, 6.0, 8.0, 10.0, 12.0]).unwrap();
        assert!(w.w == 0.0 && w.w.is_sign_positive(), "{w:?}");
        assert!(close(w.p_two_sided, 0.03125, 1e-12), "{w:?}");
    }

    #[test]
    fn wilcoxon_rejects_no_differences_and_nan() {
        let e = wilcoxon_signed_rank(&[1.0, 2.0], &[1.0, 2.0]).unwrap_err();
        assert_eq!(e.to_string(), "every paired difference is zero: the signed-rank test is undefined");
        assert!(matches!(wilcoxon_signed_rank(&[], &[]), Err(StatisticsError::TooFew { .. })));
        let e = wilcoxon_signed_rank(&[1.0, 2.0], &[1.0, f64::INFINITY]).unwrap_err();
        assert_eq!(e, StatisticsError::NotFinite { which: "y", index: 1, value: f64::INFINITY });
    }

    #[test]
    fn bootstrap_is_seeded_and_brackets_the_statistic() {
        let values: Vec<f64> = (0..40).map(|i| (i as f64 * 0.37).sin() * 10.0 + 20.0).collect();
        let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let a = bootstrap_ci(&values, mean_of, 2000, 0.95, 7).unwrap();
        assert_eq!(a, bootstrap_ci(&values, mean_of, 2000, 0.95, 7).unwrap());
        assert_ne!(a, bootstrap_ci(&values, mean_of, 2000, 0.95, 8).unwrap());
        let m = mean(&values).unwrap();
        assert!(a.lo < m && m < a.hi && a.undefined == 0, "{a:?} around {m}");
        // All values equal: every resample has the same mean.
        let c = bootstrap_ci(&[3.0; 5], mean_of, 100, 0.95, 1).unwrap();
        assert_eq!((c.lo, c.hi), (3.0, 3.0));
    }

    #[test]
    fn paired_bootstrap_leaves_out_undefined_resamples() {
        // n = 3: a resample of one pair drawn thrice is constant, its r undefined (3 of 27).
        let r_of = |x: &[f64], y: &[f64]| pearson(x, y).map_or(f64::NAN, |c| c.r);
        let ci = bootstrap_ci_paired(&[1.0, 2.0, 3.0], &[1.0, 3.0, 2.0], r_of, 2700, 0.95, 3).unwrap();
        assert!(ci.undefined > 200 && ci.undefined < 400, "{ci:?}");
        assert!(-1.0 <= ci.lo && ci.lo <= ci.hi && ci.hi <= 1.0, "{ci:?}");
        let nan = |_: &[f64]| f64::NAN;
        assert_eq!(bootstrap_ci(&[1.0, 2.0], nan, 10, 0.95, 0), Err(StatisticsError::UndefinedOnEveryResample(10)));
        let mean_of = |v: &[f64]| v[0];
        assert_eq!(bootstrap_ci(&[1.0], mean_of, 10, 1.0, 0), Err(StatisticsError::Confidence(1.0)));
        assert_eq!(bootstrap_ci(&[1.0], mean_of, 0, 0.95, 0), Err(StatisticsError::NoResamples));
        assert!(matches!(bootstrap_ci(&[], mean_of, 10, 0.95, 0), Err(StatisticsError::TooFew { .. })));
    }

    #[test]
    fn bland_altman_by_hand() {
        // Differences [1, −1, 0, 2, 1]: bias 0.6, sd 1.140175425099138, t(0.975, 4) = 2.7764451051977934
        let pred = [10.0, 12.0, 9.0, 15.0, 11.0];
        let truth = [9.0, 13.0, 9.0, 13.0, 10.0];
        let b = bland_altman(&pred, &truth).unwrap();
        assert!(close(b.bias, 0.6, 1e-15) && close(b.sd, 1.140175425099138, 1e-14), "{b:?}");
        assert!(close(b.loa[0], 0.6 - 1.96 * 1.140175425099138, 1e-14));
        let half = 2.7764451051977934 * 1.140175425099138 / 5f64.sqrt();
        assert!(close(b.bias_ci[0], 0.6 - half, 1e-10) && close(b.bias_ci[1], 0.6 + half, 1e-10), "{b:?}");
        assert_eq!(bland_altman(&[1.0], &[2.0]).unwrap_err().to_string(), "Bland–Altman needs 2 or more values, got 1");
    }

    #[test]
    fn mean_and_median_reject_empty_and_nan() {
        assert_eq!(mean(&[1.0, 2.0, 6.0]), Ok(3.0));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Ok(2.5));
        assert!(matches!(median(&[]), Err(StatisticsError::TooFew { min: 1, len: 0, .. })));
        assert_eq!(mean(&[f64::NAN]).unwrap_err().to_string(), "values[0] is NaN: only finite values are accepted");
    }
}
