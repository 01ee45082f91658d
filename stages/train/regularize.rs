//! The regularisers of the loss (SPEC §3 train; paper eq. 7–8) and their gradients.
//!
//! L1 = Σ over the three planes and three lines of the mean |value|. TV = Σ over the three
//! density planes of the mean absolute horizontal plus the mean absolute vertical finite
//! difference (`tv_norm = "l1"`, as the paper writes it), or of their squares (`"l2"`, as
//! TensoRF's own TV). At a kink (|0|) the subgradient 0 is used.

use super::field::VmField;
use num_traits::Float;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TvNorm {
    L1,
    L2,
}

fn sign<T: Float>(x: T) -> T {
    if x > T::zero() {
        T::one()
    } else if x < T::zero() {
        -T::one()
    } else {
        T::zero()
    }
}

/// L1 and its gradient (added to `grad` scaled by `weight`).
pub fn l1<T: Float + Send + Sync>(field: &VmField<T>, weight: T, grad: &mut VmField<T>) -> f64 {
    let mut value = 0.0;
    for (factor, g) in field.params().zip(grad.params_mut()) {
        let per_entry = weight / T::from(factor.len()).expect("length");
        let mut sum = T::zero();
        for (gi, &x) in g.iter_mut().zip(factor) {
            sum = sum + x.abs();
            *gi = *gi + per_entry * sign(x);
        }
        value += sum.to_f64().expect("finite") / factor.len() as f64;
    }
    value
}

/// TV of the three density planes and its gradient (added to `grad` scaled by `weight`).
pub fn tv<T: Float + Send + Sync>(field: &VmField<T>, norm: TvNorm, weight: T, grad: &mut VmField<T>) -> f64 {
    let (n, rank) = (field.n, field.rank);
    if n < 2 {
        return 0.0;
    }
    let count = T::from(rank * n * (n - 1)).expect("count");
    let scale = weight / count;
    let mut value = T::zero();
    let mut step = vec![T::zero(); n * (n - 1)];
    // Each difference d_k = b_k − a_k adds |d| (or d²); ∂/∂d_k, scaled, goes to b_k with + and to
    // a_k with −. Differences are taken between contiguous slices (a row and itself shifted by
    // one; the plane and itself shifted by one row), then applied in two passes.
    // One monomorphic loop per norm; the value sums in eight lanes so the loop vectorises.
    let mut diff = |a: &[T], b: &[T], step: &mut [T]| {
        let mut lanes = [T::zero(); 8];
        match norm {
            TvNorm::L1 => {
                for (k, ((&x, &y), s)) in a.iter().zip(b).zip(step.iter_mut()).enumerate() {
                    let d = y - x;
                    lanes[k % 8] = lanes[k % 8] + d.abs();
                    *s = scale * sign(d);
                }
            }
            TvNorm::L2 => {
                for (k, ((&x, &y), s)) in a.iter().zip(b).zip(step.iter_mut()).enumerate() {
                    let d = y - x;
                    lanes[k % 8] = lanes[k % 8] + d * d;
                    *s = scale * (d + d);
                }
            }
        }
        value = lanes.iter().fold(value, |acc, &l| acc + l);
    };
    let apply = |g: &mut [T], shift: usize, step: &[T]| {
        for (gi, &s) in g.iter_mut().zip(step) {
            *gi = *gi - s;
        }
        for (gi, &s) in g[shift..].iter_mut().zip(step) {
            *gi = *gi + s;
        }
    };
    for (plane, g) in field.planes.iter().zip(grad.planes.iter_mut()) {
        for (comp, gcomp) in plane.chunks_exact(n * n).zip(g.chunks_exact_mut(n * n)) {
            for (row, grow) in comp.chunks_exact(n).zip(gcomp.chunks_exact_mut(n)) {
                diff(&row[..n - 1], &row[1..], &mut step[..n - 1]);
                apply(grow, 1, &step[..n - 1]);
            }
            diff(&comp[..n * (n - 1)], &comp[n..], &mut step);
            apply(gcomp, n, &step);
        }
    }
    (value / count).to_f64().expect("finite")
}
