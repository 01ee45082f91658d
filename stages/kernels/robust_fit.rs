//! Bounded, robust nonlinear least squares: minimise Σ ρ(rᵢ(x)) over a box of parameters, with
//! the soft-L1 loss ρ(r) = 2s²(√(1 + (r/s)²) − 1) (scipy's `loss="soft_l1"`, `f_scale = s`):
//! quadratic for |r| ≪ s, linear beyond, so a few pixels that another structure crosses do not
//! pull the fit.
//!
//! Levenberg–Marquardt on the reweighted problem (each step solves the Gauss–Newton system with
//! weights ρ'(rᵢ²) = 1/√(1 + (rᵢ/s)²)), a central-difference Jacobian, and steps projected onto
//! the bounds; the normal equations skip each column's zeros before its first and after its last
//! non-zero entry. Deterministic: the same inputs give the same bits.

use std::ops::Range;

/// The solution and how it was reached.
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    pub x: Vec<f64>,
    /// Σ ρ(rᵢ) at `x`.
    pub cost: f64,
    /// Accepted steps.
    pub iterations: usize,
}

/// What to minimise: `residuals(x, r)` writes the `residual_count` residuals at `x` into `r`.
pub struct Problem<'a> {
    pub residuals: &'a (dyn Fn(&[f64], &mut [f64]) + Sync),
    pub residual_count: usize,
    /// Lower and upper bounds of each parameter (±∞ where free).
    pub lower: Vec<f64>,
    pub upper: Vec<f64>,
    /// The loss's scale s: residuals much larger than it count linearly.
    pub loss_scale: f64,
}

const MAX_ITERATIONS: usize = 200;
/// Relative finite-difference step (scaled by max(1, |xⱼ|)); large enough to step across a
/// pixel's worth of a sharp-edged model, small against the parameters' own scale.
const DIFF_STEP: f64 = 1e-3;

/// Minimises `problem` from `x0` (clamped into the bounds).
pub fn fit_soft_l1(problem: &Problem, x0: &[f64]) -> Fit {
    let n = x0.len();
    assert!(problem.lower.len() == n && problem.upper.len() == n, "one bound per parameter");
    let clamp = |x: &mut [f64]| {
        for ((v, lo), hi) in x.iter_mut().zip(&problem.lower).zip(&problem.upper) {
            *v = v.clamp(*lo, *hi);
        }
    };
    let s2 = problem.loss_scale * problem.loss_scale;
    let eval = |x: &[f64], r: &mut [f64]| -> f64 {
        (problem.residuals)(x, r);
        r.iter().map(|ri| 2.0 * s2 * ((1.0 + ri * ri / s2).sqrt() - 1.0)).sum()
    };
    let m = problem.residual_count;
    let mut x = x0.to_vec();
    clamp(&mut x);
    let mut r = vec![0.0; m];
    let mut cost = eval(&x, &mut r);
    let mut damping = 1e-3;
    let mut iterations = 0;
    let (mut trial, mut r_trial) = (vec![0.0; n], vec![0.0; m]);
    let mut jacobian = vec![vec![0.0; m]; n]; // column j: ∂r/∂xⱼ
    while iterations < MAX_ITERATIONS {
        for (j, column) in jacobian.iter_mut().enumerate() {
            // Central differences where both sides lie inside the box, else one-sided inwards.
            let h = DIFF_STEP * x[j].abs().max(1.0);
            let (back, ahead) = (x[j] - h >= problem.lower[j], x[j] + h <= problem.upper[j]);
            let (lo, hi) = match (back, ahead) {
                (true, true) | (false, false) => (x[j] - h, x[j] + h),
                (true, false) => (x[j] - h, x[j]),
                (false, true) => (x[j], x[j] + h),
            };
            trial.copy_from_slice(&x);
            trial[j] = hi;
            (problem.residuals)(&trial, column);
            trial[j] = lo;
            (problem.residuals)(&trial, &mut r_trial);
            for (c, low) in column.iter_mut().zip(&r_trial) {
                *c = (*c - low) / (hi - lo);
            }
        }
        let weights: Vec<f64> = r.iter().map(|ri| 1.0 / (1.0 + ri * ri / s2).sqrt()).collect();
        // Each column's non-zero span: the products outside it add zeros.
        let support: Vec<(usize, usize)> = jacobian
            .iter()
            .map(|c| match c.iter().position(|&v| v != 0.0) {
                Some(first) => (first, c.iter().rposition(|&v| v != 0.0).expect("one is non-zero") + 1),
                None => (0, 0),
            })
            .collect();
        // Normal equations of the reweighted problem: (JᵀWJ) δ = −JᵀW r.
        let mut normal = vec![vec![0.0; n]; n];
        let mut gradient = vec![0.0; n];
        for a in 0..n {
            gradient[a] = (support[a].0..support[a].1).map(|i| jacobian[a][i] * weights[i] * r[i]).sum();
            let span_with = |b: usize| support[a].0.max(support[b].0)..support[a].1.min(support[b].1);
            let mut b = 0;
            while b <= a {
                // Up to four columns over the same span in one pass, each sum still in index order.
                let span = span_with(b);
                let mut end = b + 1;
                while end <= a && end - b < 4 && span_with(end) == span {
                    end += 1;
                }
                let column = |k: usize| &jacobian[b + k][..];
                let sums = match end - b {
                    1 => products(&jacobian[a], &weights, [column(0)], span).to_vec(),
                    2 => products(&jacobian[a], &weights, [column(0), column(1)], span).to_vec(),
                    3 => products(&jacobian[a], &weights, [column(0), column(1), column(2)], span).to_vec(),
                    _ => products(&jacobian[a], &weights, [column(0), column(1), column(2), column(3)], span).to_vec(),
                };
                for (k, v) in sums.into_iter().enumerate() {
                    normal[a][b + k] = v;
                    normal[b + k][a] = v;
                }
                b = end;
            }
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut damped = normal.clone();
            for (a, row) in damped.iter_mut().enumerate() {
                row[a] += damping * normal[a][a].max(1e-12);
            }
            let Some(step) = solve_spd(damped, gradient.iter().map(|g| -g).collect()) else {
                damping *= 10.0;
                continue;
            };
            for j in 0..n {
                trial[j] = x[j] + step[j];
            }
            clamp(&mut trial);
            let trial_cost = eval(&trial, &mut r_trial);
            if trial_cost < cost {
                let moved = (0..n).map(|j| (trial[j] - x[j]).abs() / x[j].abs().max(1.0)).fold(0.0, f64::max);
                let gain = (cost - trial_cost) / cost.max(f64::MIN_POSITIVE);
                std::mem::swap(&mut x, &mut trial);
                std::mem::swap(&mut r, &mut r_trial);
                cost = trial_cost;
                damping = (damping / 3.0).max(1e-9);
                improved = gain > 1e-10 && moved > 1e-10;
                iterations += 1;
                break;
            }
            damping *= 4.0;
        }
        if !improved {
            break;
        }
    }
    Fit { x, cost, iterations }
}

/// `Σᵢ (a[i]·w[i])·c[i]` over `span` for each column `c` of `columns`: each sum adds its terms in
/// index order from the empty sum's value, as `Iterator::sum` does, so the bits are the same as
/// one sum at a time; side by side, the sums do not wait on each other's additions.
fn products<const K: usize>(a: &[f64], w: &[f64], columns: [&[f64]; K], span: Range<usize>) -> [f64; K] {
    let zero: f64 = std::iter::empty::<f64>().sum();
    let mut sums = [zero; K];
    if span.is_empty() {
        return sums; // disjoint supports (the range may run backwards)
    }
    let (a, w) = (&a[span.clone()], &w[span.clone()]);
    let columns = columns.map(|c| &c[span.clone()]);
    for i in 0..a.len() {
        let weighted = a[i] * w[i];
        for (sum, c) in sums.iter_mut().zip(&columns) {
            *sum += weighted * c[i];
        }
    }
    sums
}

/// Solves `a x = b` for symmetric positive-definite `a` by Cholesky; `None` when it is not.
fn solve_spd(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    for j in 0..n {
        let d = a[j][j] - (0..j).map(|k| a[j][k] * a[j][k]).sum::<f64>();
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        a[j][j] = d.sqrt();
        for i in j + 1..n {
            a[i][j] = (a[i][j] - (0..j).map(|k| a[i][k] * a[j][k]).sum::<f64>()) / a[j][j];
        }
    }
    for i in 0..n {
        b[i] = (b[i] - (0..i).map(|k| a[i][k] * b[k]).sum::<f64>()) / a[i][i];
    }
    for i in (0..n).rev() {
        b[i] = (b[i] - (i + 1..n).map(|k| a[k][i] * b[k]).sum::<f64>()) / a[i][i];
    }
    Some(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// y = a·exp(−b·t) + c, sampled exactly, with three gross outliers.
    fn decay(outliers: bool) -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..40).map(|i| i as f64 * 0.1).collect();
        let mut y: Vec<f64> = t.iter().map(|t| 2.0 * (-1.3 * t).exp() + 0.5).collect();
        if outliers {
            for i in [5, 17, 31] {
                y[i] += 3.0;
            }
        }
        (t, y)
    }

    fn fit_decay(t: &[f64], y: &[f64], lower: Vec<f64>, upper: Vec<f64>) -> Fit {
        let residuals = |x: &[f64], r: &mut [f64]| {
            for i in 0..t.len() {
                r[i] = x[0] * (-x[1] * t[i]).exp() + x[2] - y[i];
            }
        };
        let problem = Problem { residuals: &residuals, residual_count: t.len(), lower, upper, loss_scale: 0.01 };
        fit_soft_l1(&problem, &[1.0, 0.5, 0.0])
    }

    #[test]
    fn recovers_a_decay_through_gross_outliers() {
        let (t, y) = decay(true);
        let inf = f64::INFINITY;
        let fit = fit_decay(&t, &y, vec![-inf; 3], vec![inf; 3]);
        // Plain least squares would lift the offset by about 0.2; each outlier pulls the robust
        // fit by at most the loss's scale.
        for (got, want) in fit.x.iter().zip([2.0, 1.3, 0.5]) {
            assert!((got - want).abs() < 5e-3, "{:?}", fit.x);
        }
    }

    #[test]
    fn stays_inside_its_bounds() {
        let (t, y) = decay(false);
        let fit = fit_decay(&t, &y, vec![0.0, 0.0, -1.0], vec![10.0, 1.0, 1.0]);
        assert_eq!(fit.x[1], 1.0, "the rate is held at its upper bound: {:?}", fit.x);
        assert!(fit.x.iter().zip([0.0, 0.0, -1.0]).all(|(x, lo)| *x >= lo));
    }

    #[test]
    fn solves_a_small_spd_system() {
        let a = vec![vec![4.0, 1.0, 0.0], vec![1.0, 3.0, 1.0], vec![0.0, 1.0, 2.0]];
        let x = solve_spd(a.clone(), vec![1.0, 2.0, 3.0]).unwrap();
        for i in 0..3 {
            let ax: f64 = (0..3).map(|k| a[i][k] * x[k]).sum();
            assert!((ax - [1.0, 2.0, 3.0][i]).abs() < 1e-12);
        }
        assert!(solve_spd(vec![vec![1.0, 2.0], vec![2.0, 1.0]], vec![1.0, 1.0]).is_none());
    }
}
