//! The dense fit as the tool solved it before its matrix-free projector, kept here only as the
//! benchmark's reference: an explicit sparse `A` (the renderer's midpoint samples, trilinear
//! weights times `s·δ`, f64) built per ray with a sort, its transpose, `1/L` from 30 power
//! iterations, and 500 FISTA steps in f64 from σ = 0.

use aret_pipe::train::render::{Ray, Renderer, MIN_INTENSITY};
use rayon::prelude::*;

/// A sparse matrix in compressed rows.
pub struct Csr {
    pub offsets: Vec<usize>,
    pub index: Vec<u32>,
    pub weight: Vec<f64>,
}

impl Csr {
    fn times(&self, x: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.offsets.len() - 1];
        self.times_into(x, &mut out);
        out
    }

    fn times_into(&self, x: &[f64], out: &mut [f64]) {
        out.par_iter_mut().zip(self.offsets.par_windows(2)).for_each(|(o, w)| {
            *o = (w[0]..w[1]).map(|k| self.weight[k] * x[self.index[k] as usize]).sum();
        });
    }

    fn transpose(&self, columns: usize) -> Csr {
        let mut offsets = vec![0usize; columns + 1];
        for &c in &self.index {
            offsets[c as usize + 1] += 1;
        }
        for c in 0..columns {
            offsets[c + 1] += offsets[c];
        }
        let mut next = offsets.clone();
        let (mut index, mut weight) = (vec![0u32; self.index.len()], vec![0.0; self.index.len()]);
        for r in 0..self.offsets.len() - 1 {
            for k in self.offsets[r]..self.offsets[r + 1] {
                let slot = &mut next[self.index[k] as usize];
                (index[*slot], weight[*slot]) = (r as u32, self.weight[k]);
                *slot += 1;
            }
        }
        Csr { offsets, index, weight }
    }
}

/// The old problem: `A`, `Aᵀ`, the measured depths and the step `1/L`.
pub struct CsrProblem {
    pub n: usize,
    pub rows: Csr,
    pub columns: Csr,
    pub seen: Vec<bool>,
    pub rays_seen: f64,
    pub measured: Vec<f64>,
    pub lambda: f64,
    pub epsilon: f64,
    pub step: f64,
}

impl CsrProblem {
    pub fn new(renderer: &Renderer, rays: &[Ray], lambda: f64, epsilon: f64) -> CsrProblem {
        let n = renderer.lattice.n;
        let depth_per_sample = renderer.scale * renderer.step;
        let per_ray: Vec<Vec<(u32, f64)>> = rays
            .par_iter()
            .map(|ray| {
                let (q0, dq, count) = renderer.samples(ray, renderer.step / 2.0);
                let mut entries: Vec<(u32, f64)> = Vec::with_capacity(8 * count);
                for k in 0..count {
                    let q: [f64; 3] = std::array::from_fn(|a| q0[a] + k as f64 * dq[a]);
                    let (cell, weights) = cell_and_weights(q, n);
                    let corners = [0, 1, n, n + 1, n * n, n * n + 1, n * n + n, n * n + n + 1];
                    for (offset, w) in corners.iter().zip(weights) {
                        entries.push(((cell + offset) as u32, w * depth_per_sample));
                    }
                }
                entries.sort_by_key(|&(node, _)| node);
                entries.dedup_by(|later, kept| {
                    let same = later.0 == kept.0;
                    if same {
                        kept.1 += later.1;
                    }
                    same
                });
                entries.shrink_to_fit();
                entries
            })
            .collect();
        let mut offsets = vec![0];
        let (mut index, mut weight) = (Vec::new(), Vec::new());
        for entries in per_ray {
            for (node, w) in entries {
                index.push(node);
                weight.push(w);
            }
            offsets.push(index.len());
        }
        let rows = Csr { offsets, index, weight };
        let columns = rows.transpose(n * n * n);
        let seen: Vec<bool> = rows.offsets.windows(2).map(|w| w[1] > w[0]).collect();
        let rays_seen = seen.iter().filter(|&&s| s).count().max(1) as f64;
        let measured = rays.iter().map(|r| -r.target.max(MIN_INTENSITY).ln()).collect();
        let mut problem = CsrProblem { n, rows, columns, seen, rays_seen, measured, lambda, epsilon, step: 0.0 };
        problem.step = 1.0 / problem.lipschitz();
        problem
    }

    pub fn nodes(&self) -> usize {
        self.n * self.n * self.n
    }

    fn residual(&self, depths: &[f64]) -> Vec<f64> {
        depths.iter().zip(&self.measured).zip(&self.seen).map(|((d, m), &s)| if s { d - m } else { 0.0 }).collect()
    }

    fn lipschitz(&self) -> f64 {
        let nodes = self.nodes();
        let mut x = vec![1.0 / (nodes as f64).sqrt(); nodes];
        let mut eigenvalue = 0.0;
        for _ in 0..30 {
            let y = self.columns.times(&self.rows.times(&x));
            eigenvalue = y.iter().map(|v| v * v).sum::<f64>().sqrt();
            if eigenvalue == 0.0 {
                break;
            }
            x = y.iter().map(|v| v / eigenvalue).collect();
        }
        1.05 * eigenvalue / self.rays_seen + self.lambda / nodes as f64 * 12.0 / self.epsilon
    }

    /// E at `sigma` under this problem's `A`.
    pub fn energy(&self, sigma: &[f64]) -> f64 {
        let r = self.residual(&self.rows.times(sigma));
        let data = r.iter().map(|r| r * r).sum::<f64>() / (2.0 * self.rays_seen);
        let tv: f64 =
            (0..sigma.len()).into_par_iter().map(|i| normalised_difference(sigma, self.n, self.epsilon, i).0).sum();
        data + self.lambda * tv / self.nodes() as f64
    }

    /// `steps` FISTA steps from σ = 0.
    pub fn solve(&self, steps: usize, mut checkpoint: impl FnMut(usize, &[f64])) -> Vec<f64> {
        let (n, b, step, epsilon) = (self.n, self.rays_seen, self.step, self.epsilon);
        let w = self.lambda / self.nodes() as f64;
        let nodes = self.nodes();
        let (mut gradient, mut next, mut p) = (vec![0.0; nodes], vec![0.0; nodes], vec![[0.0; 3]; nodes]);
        let mut sigma = vec![0.0; nodes];
        let (mut ahead, mut t) = (sigma.clone(), 1.0f64);
        for done in 0..steps {
            self.columns.times_into(&self.residual(&self.rows.times(&ahead)), &mut gradient);
            p.par_iter_mut().enumerate().for_each(|(i, p)| *p = normalised_difference(&ahead, n, epsilon, i).1);
            gradient.par_iter_mut().enumerate().for_each(|(i, g)| *g = *g / b + w * tv_gradient_at(&p, n, i));
            next.par_iter_mut().zip(&ahead).zip(&gradient).for_each(|((x, a), g)| *x = (a - step * g).max(0.0));
            let t_next = (1.0 + (1.0 + 4.0 * t * t).sqrt()) / 2.0;
            let momentum = (t - 1.0) / t_next;
            ahead.par_iter_mut().zip(&next).zip(&sigma).for_each(|((a, x), old)| *a = x + momentum * (x - old));
            sigma.copy_from_slice(&next);
            t = t_next;
            checkpoint(done + 1, &sigma);
        }
        sigma
    }
}

fn cell_and_weights(q: [f64; 3], n: usize) -> (usize, [f64; 8]) {
    let mut base = [0usize; 3];
    let mut frac = [0.0; 3];
    for a in 0..3 {
        let x = q[a].clamp(0.0, (n - 1) as f64);
        base[a] = (x.min((n - 2) as f64)) as usize;
        frac[a] = x - base[a] as f64;
    }
    let [fx, fy, fz] = frac;
    let (gx, gy, gz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    let face = [gx * gy, fx * gy, gx * fy, fx * fy];
    let weights = [
        face[0] * gz,
        face[1] * gz,
        face[2] * gz,
        face[3] * gz,
        face[0] * fz,
        face[1] * fz,
        face[2] * fz,
        face[3] * fz,
    ];
    (base[0] + n * (base[1] + n * base[2]), weights)
}

fn normalised_difference(sigma: &[f64], n: usize, epsilon: f64, i: usize) -> (f64, [f64; 3]) {
    let (c, strides) = ([i % n, (i / n) % n, i / (n * n)], [1, n, n * n]);
    let d: [f64; 3] = std::array::from_fn(|a| if c[a] + 1 < n { sigma[i + strides[a]] - sigma[i] } else { 0.0 });
    let m = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + epsilon * epsilon).sqrt();
    (m, d.map(|v| v / m))
}

fn tv_gradient_at(p: &[[f64; 3]], n: usize, i: usize) -> f64 {
    let (c, strides) = ([i % n, (i / n) % n, i / (n * n)], [1, n, n * n]);
    (0..3).map(|a| if c[a] > 0 { p[i - strides[a]][a] } else { 0.0 } - p[i][a]).sum()
}
