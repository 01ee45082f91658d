//! Rendering a ray batch through the composed field, its photometric loss, and the scatter of
//! `dL/dF` back onto the lattice (SPEC §3 train, Rendering and Loss).
//!
//! Samples lie at `t0 + offset + k·step` inside the box (`offset` ∈ [0, step): one random
//! offset per ray while training — TensoRF's `sample_ray` — and `step/2` when evaluating),
//! each weighing `δ = step`. `σ = ReLU(F + Δ)` with `F` trilinear between nodes and clamped
//! beyond the outermost ones, and `Î = exp(−s · Σ σ_k δ)`, the DRR's Beer–Lambert model. An
//! alpha mask, when given, silences samples none of whose 8 neighbour nodes is kept.

use crate::geometry::Aabb;
use crate::kernels::trilinear;
use glam::DVec3;
use num_traits::Float;
use rayon::prelude::*;

/// The node lattice: N nodes per axis at the cell centres of the box.
#[derive(Debug, Clone, Copy)]
pub struct Lattice {
    pub n: usize,
    pub aabb: Aabb,
}

impl Lattice {
    /// Continuous node index of the ray point `origin + t·dir` is `a + t·b` (before clamping).
    fn index_line(&self, origin: DVec3, dir: DVec3) -> ([f64; 3], [f64; 3]) {
        let cell: [f64; 3] = std::array::from_fn(|k| (self.aabb.max[k] - self.aabb.min[k]) / self.n as f64);
        (
            std::array::from_fn(|k| (origin[k] - self.aabb.min[k]) / cell[k] - 0.5),
            std::array::from_fn(|k| dir[k] / cell[k]),
        )
    }

    fn dims(&self) -> [usize; 3] {
        [self.n; 3]
    }

    /// The cell holding lattice point `q`: its lower corner node and fractional offsets.
    fn cell_of(&self, q: [f64; 3]) -> (usize, [f64; 3]) {
        trilinear::cell(q, self.dims())
    }

    /// The 8 corner nodes of the cell at `origin` and their trilinear weights for `frac`.
    fn corners(&self, origin: usize, frac: [f64; 3]) -> [(usize, f64); 8] {
        trilinear::corners(origin, frac, self.dims())
    }
}

/// A sample that passed the mask with a positive activation: where its gradient goes.
#[derive(Debug, Clone, Copy)]
struct Active {
    cell: usize,
    frac: [f64; 3],
}

/// A training ray: origin, unit direction, and the measured pixel `I/I0`.
#[derive(Debug, Clone, Copy)]
pub struct Ray {
    pub origin: DVec3,
    pub dir: DVec3,
    pub target: f64,
}

/// Rendering constants: `Δ` (`shift`), `s` (`scale`) and the sample spacing.
#[derive(Debug, Clone, Copy)]
pub struct Renderer {
    pub lattice: Lattice,
    pub shift: f64,
    pub scale: f64,
    pub step: f64,
}

/// A batch's predictions and its mean squared error.
pub struct BatchResult<T> {
    pub predicted: Vec<T>,
    pub mse: f64,
}

impl Renderer {
    /// The continuous lattice index of each sample of `ray` with offset `offset` ∈ [0, step).
    fn samples(&self, ray: &Ray, offset: f64) -> impl Iterator<Item = [f64; 3]> {
        let (t0, t1) = self.lattice.aabb.intersect(ray.origin, ray.dir).unwrap_or((0.0, 0.0));
        let (a, b) = self.lattice.index_line(ray.origin, ray.dir);
        let step = self.step;
        (0..)
            .map(move |k| t0 + offset + k as f64 * step)
            .take_while(move |&t| t < t1)
            .map(move |t| std::array::from_fn(|k| a[k] + t * b[k]))
    }

    /// `Î` of one ray; with `active`, also records the samples whose σ is positive (their
    /// gradient is non-zero) for the backward pass.
    fn trace<T: Float>(
        &self,
        dense: &[T],
        mask: Option<&[bool]>,
        ray: &Ray,
        offset: f64,
        mut active: Option<&mut Vec<Active>>,
    ) -> f64 {
        let mut optical_depth = 0.0;
        for q in self.samples(ray, offset) {
            let (cell, frac) = self.lattice.cell_of(q);
            let corners = self.lattice.corners(cell, frac);
            if let Some(keep) = mask {
                if !corners.iter().any(|&(i, _)| keep[i]) {
                    continue;
                }
            }
            let f: f64 = corners.iter().map(|&(i, w)| dense[i].to_f64().expect("finite") * w).sum();
            if f + self.shift > 0.0 {
                optical_depth += (f + self.shift) * self.step;
                if let Some(list) = active.as_deref_mut() {
                    list.push(Active { cell, frac });
                }
            }
        }
        (-self.scale * optical_depth).exp()
    }

    /// `Î` of one ray.
    pub fn render_ray<T: Float>(&self, dense: &[T], mask: Option<&[bool]>, ray: &Ray, offset: f64) -> f64 {
        self.trace(dense, mask, ray, offset, None)
    }

    /// Renders `rays` (with their per-ray `offsets`), returns predictions and MSE, and when
    /// `grad` is given adds `dMSE/dF` to it. Rays trace in parallel, each recording its active
    /// samples; the scatter then runs in ray order, so the gradient is bit-identical whatever
    /// the thread count.
    pub fn batch<T: Float + Send + Sync>(
        &self,
        dense: &[T],
        mask: Option<&[bool]>,
        rays: &[Ray],
        offsets: &[f64],
        grad: Option<&mut [T]>,
    ) -> BatchResult<T> {
        let want_grad = grad.is_some();
        let traced: Vec<(f64, Vec<Active>)> = rays
            .par_iter()
            .zip(offsets)
            .map(|(ray, &off)| {
                let mut active = Vec::new();
                let pred = self.trace(dense, mask, ray, off, want_grad.then_some(&mut active));
                (pred, active)
            })
            .collect();
        let b = rays.len() as f64;
        let mse = rays.iter().zip(&traced).map(|(r, (p, _))| (p - r.target).powi(2)).sum::<f64>() / b;
        if let Some(grad) = grad {
            for (ray, (pred, active)) in rays.iter().zip(&traced) {
                // dL/dÎ = 2(Î − I)/B;  dÎ/dσ_k = −s·δ·Î;  dσ/dF = 1[F + Δ > 0] (the active samples).
                let d_sigma = 2.0 * (pred - ray.target) / b * (-self.scale * self.step * pred);
                if d_sigma == 0.0 {
                    continue;
                }
                for a in active {
                    for (i, w) in self.lattice.corners(a.cell, a.frac) {
                        grad[i] = grad[i] + T::from(d_sigma * w).expect("finite");
                    }
                }
            }
        }
        let predicted = traced.into_iter().map(|(p, _)| T::from(p).expect("finite")).collect();
        BatchResult { predicted, mse }
    }

    /// The alpha mask on the lattice: `alpha = 1 − exp(−σ·step·s)` at each node, dilated by a
    /// 3×3×3 max, kept where above `threshold`.
    pub fn alpha_mask<T: Float>(&self, dense: &[T], threshold: f64) -> Vec<bool> {
        let n = self.lattice.n;
        let alpha: Vec<f64> = dense
            .iter()
            .map(|&f| 1.0 - (-(f.to_f64().expect("finite") + self.shift).max(0.0) * self.step * self.scale).exp())
            .collect();
        let mut keep = vec![false; alpha.len()];
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let range = |c: usize| c.saturating_sub(1)..=(c + 1).min(n - 1);
                    let max = range(z)
                        .flat_map(|zz| range(y).flat_map(move |yy| range(x).map(move |xx| xx + n * (yy + n * zz))))
                        .map(|i| alpha[i])
                        .fold(0.0, f64::max);
                    keep[x + n * (y + n * z)] = max > threshold;
                }
            }
        }
        keep
    }
}
