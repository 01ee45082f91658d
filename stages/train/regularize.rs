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
        let len = T::from(factor.len()).expect("length");
        value += factor.iter().map(|x| x.abs().to_f64().expect("finite")).sum::<f64>() / factor.len() as f64;
        for (gi, &x) in g.iter_mut().zip(factor) {
            *gi = *gi + weight * sign(x) / len;
        }
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
    let mut value = T::zero();
    for (plane, g) in field.planes.iter().zip(grad.planes.iter_mut()) {
        // Differences along u (stride 1) and along v (stride n) within each component.
        for r in 0..rank {
            let base = r * n * n;
            for v in 0..n {
                for u in 0..n {
                    let i = base + u + n * v;
                    for (ok, j) in [(u + 1 < n, i + 1), (v + 1 < n, i + n)] {
                        if !ok {
                            continue;
                        }
                        let d = plane[j] - plane[i];
                        let (val, dd) = match norm {
                            TvNorm::L1 => (d.abs(), sign(d)),
                            TvNorm::L2 => (d * d, d + d),
                        };
                        value = value + val;
                        let step = weight * dd / count;
                        g[j] = g[j] + step;
                        g[i] = g[i] - step;
                    }
                }
            }
        }
    }
    (value / count).to_f64().expect("finite")
}
