//! Adam (TensoRF's settings: β = (0.9, 0.99), ε = 1e-8) with the learning rate decaying
//! exponentially to `decay_ratio ×` its start over the run (TensoRF's default schedule).

use super::field::VmField;
use crate::kernels::wide::with_avx2;
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

/// The scalars of one update: its learning rate, the bias-corrected step `lr / (1 − β1^t)` and
/// `√(1 − β2^t)` (t the 1-based update count). The GPU backend's Adam kernel takes these too.
#[derive(Debug, Clone, Copy)]
pub struct AdamStep {
    pub lr: f64,
    pub lr_t: f64,
    pub sqrt_bias2: f64,
}

impl AdamParams {
    /// The scalars of update `step` (0-based).
    pub fn step(&self, step: usize) -> AdamStep {
        let lr = self.lr * self.decay_ratio.powf(step as f64 / self.iterations.max(1) as f64);
        let t = (step + 1) as i32;
        AdamStep { lr, lr_t: lr / (1.0 - self.beta1.powi(t)), sqrt_bias2: (1.0 - self.beta2.powi(t)).sqrt() }
    }
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
        self.params.step(step).lr
    }

    /// One update of `field` by `grad`; returns the learning rate used.
    pub fn update(&mut self, field: &mut VmField<T>, grad: &VmField<T>) -> f64 {
        let (lr, update, m, v) = self.begin_update();
        // Every factor's chunks in one parallel pass (one pass per factor cost more in the
        // workers' hand-offs than the update itself).
        let chunks: Vec<_> = field
            .params_mut()
            .zip(grad.params())
            .zip(m.params_mut())
            .zip(v.params_mut())
            .flat_map(|(((x, g), m), v)| {
                x.chunks_mut(CHUNK).zip(g.chunks(CHUNK)).zip(m.chunks_mut(CHUNK)).zip(v.chunks_mut(CHUNK))
            })
            .collect();
        chunks.into_par_iter().for_each(|(((x, g), m), v)| {
            with_avx2(
                #[inline(always)]
                || update.apply(x, g, m, v),
            )
        });
        lr
    }

    /// Starts the next update for a caller that applies it piece by piece: its learning rate,
    /// the update, and the first and second moments (laid out as the field).
    pub fn begin_update(&mut self) -> (f64, Update<T>, &mut VmField<T>, &mut VmField<T>) {
        let AdamStep { lr, lr_t, sqrt_bias2 } = self.params.step(self.step);
        self.step += 1;
        let p = self.params;
        let c = |x: f64| T::from(x).expect("finite");
        let update = Update { b1: c(p.beta1), b2: c(p.beta2), lr_t: c(lr_t), eps: c(p.eps), sqrt_bias2: c(sqrt_bias2) };
        (lr, update, &mut self.m, &mut self.v)
    }
}

/// One Adam update's scalars, in the field's precision.
#[derive(Debug, Clone, Copy)]
pub struct Update<T> {
    b1: T,
    b2: T,
    lr_t: T,
    eps: T,
    sqrt_bias2: T,
}

impl<T: Float> Update<T> {
    /// Updates the entries `x` by their gradient `g` and moments `m`, `v` (elementwise: how a
    /// caller splits the field cannot change any result). Inline it into an AVX2 copy
    /// ([`with_avx2`]), as [`Adam::update`] does.
    #[inline(always)]
    pub fn apply(&self, x: &mut [T], g: &[T], m: &mut [T], v: &mut [T]) {
        let Update { b1, b2, lr_t, eps, sqrt_bias2 } = *self;
        let (g, m, v) = (&g[..x.len()], &mut m[..x.len()], &mut v[..x.len()]);
        for i in 0..x.len() {
            m[i] = b1 * m[i] + (T::one() - b1) * g[i];
            v[i] = b2 * v[i] + (T::one() - b2) * g[i] * g[i];
            x[i] = x[i] - lr_t * m[i] / (v[i].sqrt() / sqrt_bias2 + eps);
        }
    }
}
