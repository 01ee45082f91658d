//! Adam (TensoRF's settings: β = (0.9, 0.99), ε = 1e-8) with the learning rate decaying
//! exponentially to `decay_ratio ×` its start over the run (TensoRF's default schedule).

use super::field::VmField;
use num_traits::Float;
use rayon::prelude::*;

/// Entries per parallel task (elementwise: the split cannot change any result).
const CHUNK: usize = 8192;

#[derive(Debug, Clone, Copy)]
pub struct AdamParams {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// `lr` at the last iteration over `lr` at the first.
    pub decay_ratio: f64,
    pub iterations: usize,
}

pub struct Adam<T> {
    params: AdamParams,
    m: VmField<T>,
    v: VmField<T>,
    step: usize,
}

impl<T: Float + Send + Sync> Adam<T> {
    pub fn new(params: AdamParams, like: &VmField<T>) -> Self {
        Adam { params, m: VmField::zeros(like.n, like.rank), v: VmField::zeros(like.n, like.rank), step: 0 }
    }

    /// The learning rate of iteration `step` (0-based).
    pub fn lr(&self, step: usize) -> f64 {
        let p = &self.params;
        p.lr * p.decay_ratio.powf(step as f64 / p.iterations.max(1) as f64)
    }

    /// One update of `field` by `grad`; returns the learning rate used.
    pub fn update(&mut self, field: &mut VmField<T>, grad: &VmField<T>) -> f64 {
        let lr = self.lr(self.step);
        self.step += 1;
        let p = self.params;
        let c = |x: f64| T::from(x).expect("finite");
        let (b1, b2) = (c(p.beta1), c(p.beta2));
        let bias1 = 1.0 - p.beta1.powi(self.step as i32);
        let bias2 = 1.0 - p.beta2.powi(self.step as i32);
        let (lr_t, eps) = (c(lr / bias1), c(p.eps));
        let sqrt_bias2 = c(bias2.sqrt());
        for (((x, g), m), v) in field.params_mut().zip(grad.params()).zip(self.m.params_mut()).zip(self.v.params_mut())
        {
            let chunks = x.par_chunks_mut(CHUNK).zip(m.par_chunks_mut(CHUNK)).zip(v.par_chunks_mut(CHUNK));
            chunks.zip(g.par_chunks(CHUNK)).for_each(|(((x, m), v), g)| {
                for i in 0..x.len() {
                    m[i] = b1 * m[i] + (T::one() - b1) * g[i];
                    v[i] = b2 * v[i] + (T::one() - b2) * g[i] * g[i];
                    x[i] = x[i] - lr_t * m[i] / (v[i].sqrt() / sqrt_bias2 + eps);
                }
            });
        }
        lr
    }
}
