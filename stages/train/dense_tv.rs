//! `[train] model = "dense_tv"`: the attenuation field as a dense N³ lattice of σ (no factors),
//! fitted to the three views' optical depths under a smoothed 3-D total variation.
//!
//! Optical depths are line integrals, so the projection is linear in σ: `τ̂ = A σ`, with `A` the
//! renderer's own midpoint samples and trilinear weights (times `s·δ`). The fit minimises
//!
//! `E(σ) = 1/(2B) Σ_rays (τ̂ − τ)² + λ/N³ Σ_nodes √(|∇σ|² + ε²)`,  `σ ≥ 0`,
//!
//! (B rays that meet the box, `∇` forward differences in lattice steps) by FISTA: a projected
//! gradient step of `1/L`, `L` bounding E's curvature, with Nesterov momentum. E is convex,
//! the start is σ = 0 and nothing is random: the seed plays no part.
//!
//! Why: the VM factorisation explains each view with products of planes and lines, and those
//! products cross everywhere as streaks; a dense lattice with TV is the classic few-view CT
//! reconstruction, whose cheapest explanation of a blob seen in three views is one compact blob.

use super::fit::{psnr_db, LogRow, Views};
use super::params::TrainParams;
use super::render::{trilinear_weights, Ray, Renderer, MIN_INTENSITY};
use rayon::prelude::*;
use std::time::Instant;

/// A sparse matrix in compressed rows: row `r`'s entries are `index/weight[offsets[r]..offsets[r + 1]]`.
pub struct Csr {
    pub offsets: Vec<usize>,
    pub index: Vec<u32>,
    pub weight: Vec<f64>,
}

impl Csr {
    /// `M x`, each row summed in column order (bit-identical whatever the thread count).
    fn times(&self, x: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.offsets.len() - 1];
        self.times_into(x, &mut out);
        out
    }

    /// [`Csr::times`] into `out`.
    fn times_into(&self, x: &[f64], out: &mut [f64]) {
        out.par_iter_mut().zip(self.offsets.par_windows(2)).for_each(|(o, w)| {
            *o = (w[0]..w[1]).map(|k| self.weight[k] * x[self.index[k] as usize]).sum();
        });
    }

    /// The transpose (`columns` of them), its rows in ascending row order of `self`.
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

/// The linear projection `τ̂ = A σ` of the rays that meet the box, and its transpose.
pub struct Projector {
    /// `A`: a row per ray.
    pub rows: Csr,
    /// `Aᵀ`: a row per node.
    pub columns: Csr,
}

impl Projector {
    /// `A` for `rays` (each a row, even a ray that misses the box: an empty one), sampled as
    /// the renderer samples them for evaluation: midpoints, `s·δ` per sample, clamped to the
    /// lattice as the walk clamps.
    pub fn new(renderer: &Renderer, rays: &[Ray]) -> Projector {
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
                // One entry per node: sorted, equal nodes summed in sample order.
                entries.sort_by_key(|&(node, _)| node);
                entries.dedup_by(|later, kept| {
                    let same = later.0 == kept.0;
                    if same {
                        kept.1 += later.1;
                    }
                    same
                });
                // Eight entries a sample were reserved, about four times what is left: at 256³
                // the spare capacity alone would hold 7 GB until the matrix is assembled.
                entries.shrink_to_fit();
                entries
            })
            .collect();
        let mut offsets = Vec::with_capacity(rays.len() + 1);
        offsets.push(0);
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
        Projector { rows, columns }
    }

    /// The optical depth of every ray through `sigma`.
    pub fn depths(&self, sigma: &[f64]) -> Vec<f64> {
        self.rows.times(sigma)
    }

    /// `Aᵀ r`: each ray's residual spread back over the nodes it samples.
    pub fn back(&self, residual: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.columns.offsets.len() - 1];
        self.back_into(residual, &mut out);
        out
    }

    /// [`Projector::back`] into `out` (one value per node).
    pub fn back_into(&self, residual: &[f64], out: &mut [f64]) {
        self.columns.times_into(residual, out)
    }
}

/// The lower corner cell of the continuous node index `q` (clamped to the lattice, as the
/// renderer's walk clamps it) and the trilinear weights of its eight corners.
fn cell_and_weights(q: [f64; 3], n: usize) -> (usize, [f64; 8]) {
    let mut base = [0usize; 3];
    let mut frac = [0.0; 3];
    for a in 0..3 {
        let x = q[a].clamp(0.0, (n - 1) as f64);
        base[a] = (x.min((n - 2) as f64)) as usize;
        frac[a] = x - base[a] as f64;
    }
    (base[0] + n * (base[1] + n * base[2]), trilinear_weights(frac))
}

/// `Σ √(|∇σ|² + ε²)` over the nodes of an `n³` lattice (index `x + n·(y + n·z)`), forward
/// differences with none across the far faces, and its gradient.
pub fn smoothed_tv(sigma: &[f64], n: usize, epsilon: f64) -> (f64, Vec<f64>) {
    let (magnitudes, p): (Vec<f64>, Vec<[f64; 3]>) =
        (0..sigma.len()).into_par_iter().map(|i| normalised_difference(sigma, n, epsilon, i)).unzip();
    let gradient = (0..sigma.len()).into_par_iter().map(|i| tv_gradient_at(&p, n, i)).collect();
    (magnitudes.iter().sum(), gradient)
}

/// Node `i`'s `m = √(|∇σ|² + ε²)` and normalised difference vector `p = ∇σ / m`.
fn normalised_difference(sigma: &[f64], n: usize, epsilon: f64, i: usize) -> (f64, [f64; 3]) {
    let (c, strides) = ([i % n, (i / n) % n, i / (n * n)], [1, n, n * n]);
    let d: [f64; 3] = std::array::from_fn(|a| if c[a] + 1 < n { sigma[i + strides[a]] - sigma[i] } else { 0.0 });
    let m = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + epsilon * epsilon).sqrt();
    (m, d.map(|v| v / m))
}

/// `∂TV/∂σ_i = Σ_a p_a(i − e_a) − p_a(i)`: minus the backward divergence of `p`.
fn tv_gradient_at(p: &[[f64; 3]], n: usize, i: usize) -> f64 {
    let (c, strides) = ([i % n, (i / n) % n, i / (n * n)], [1, n, n * n]);
    (0..3).map(|a| if c[a] > 0 { p[i - strides[a]][a] } else { 0.0 } - p[i][a]).sum()
}

/// The fitted lattice (σ at the nodes, index `x + N·(y + N·z)`) and its log.
pub struct DenseFitted {
    pub sigma: Vec<f32>,
    pub log: Vec<LogRow>,
}

/// The terms of E at one σ.
struct Evaluation {
    /// `1/(2B) Σ (τ̂ − τ)²`.
    data: f64,
    /// `1/N³ Σ √(|∇σ|² + ε²)`, before λ.
    tv: f64,
    depths: Vec<f64>,
}

/// What every solver of E shares: `A` and `Aᵀ`, which rays meet the box, the measured depths,
/// E's weights and FISTA's step `1/L`. The GPU's solver uploads it (`gpu::dense_fit`).
pub struct DenseProblem {
    /// The lattice's nodes per side, N.
    pub n: usize,
    pub projector: Projector,
    /// Whether each ray meets the box (a row of `A` with entries).
    pub seen: Vec<bool>,
    /// B, the rays that meet the box (at least 1).
    pub rays_seen: f64,
    /// `τ = −ln I` of every ray.
    pub measured: Vec<f64>,
    pub lambda: f64,
    pub epsilon: f64,
    /// FISTA's step, `1/L`.
    pub step: f64,
}

impl DenseProblem {
    pub fn new(params: &TrainParams, rays: &[Ray], renderer: &Renderer) -> DenseProblem {
        let n = params.grid;
        let projector = Projector::new(renderer, rays);
        let seen: Vec<bool> = projector.rows.offsets.windows(2).map(|w| w[1] > w[0]).collect();
        let rays_seen = seen.iter().filter(|&&s| s).count().max(1) as f64;
        let measured = rays.iter().map(|r| -r.target.max(MIN_INTENSITY).ln()).collect();
        let (lambda, epsilon) = (params.dense_tv.lambda, params.dense_tv.epsilon);
        let step = 1.0 / lipschitz(&projector, n * n * n, rays_seen, lambda, epsilon);
        DenseProblem { n, projector, seen, rays_seen, measured, lambda, epsilon, step }
    }

    pub fn nodes(&self) -> usize {
        self.n * self.n * self.n
    }

    /// τ̂ − τ on the rays that meet the box (0 on the others).
    fn residual(&self, depths: &[f64], target: &[f64]) -> Vec<f64> {
        depths.iter().zip(target).zip(&self.seen).map(|((d, m), &s)| if s { d - m } else { 0.0 }).collect()
    }

    /// The log row of an evaluation: E's terms and each view's PSNR.
    fn log_row(&self, per_view: &[Vec<Ray>], iteration: usize, e: &Evaluation, seconds: f64) -> LogRow {
        LogRow {
            iteration,
            loss: e.data + self.lambda * e.tv,
            photo: e.data,
            l1: 0.0,
            tv: 0.0,
            tv3d: e.tv,
            psnr_db: view_mse(per_view, &e.depths).into_iter().map(psnr_db).collect(),
            lr: self.step,
            seconds,
        }
    }

    fn evaluate(&self, sigma: &[f64]) -> Evaluation {
        let depths = self.projector.depths(sigma);
        let data = self.residual(&depths, &self.measured).iter().map(|r| r * r).sum::<f64>() / (2.0 * self.rays_seen);
        let (tv_sum, _) = smoothed_tv(sigma, self.n, self.epsilon);
        Evaluation { data, tv: tv_sum / self.nodes() as f64, depths }
    }
}

/// FISTA on E toward given depths: [`CpuFista`] here, or the device's loop (`gpu::dense_fit`).
pub trait FistaSolver {
    /// Runs `steps` FISTA steps on `problem` from `sigma` toward the depths `target`, and
    /// leaves the last iterate in `sigma`. After each step `k` (from 1) for which
    /// `wants(k)`, it hands σ to `checkpoint`.
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f64],
        target: &[f64],
        steps: usize,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f64]),
    ) -> anyhow::Result<()>;
}

/// FISTA's momentum weight after the step that takes `t` to the returned `t'`: `(t − 1)/t'`.
pub fn next_momentum(t: f64) -> (f64, f64) {
    let t_next = (1.0 + (1.0 + 4.0 * t * t).sqrt()) / 2.0;
    (t_next, (t - 1.0) / t_next)
}

/// The solver on the CPU, in f64 with rayon.
pub struct CpuFista {
    // The step's buffers, reused: at 128³ each is 16 MB, and fresh ones cost their page faults.
    gradient: Vec<f64>,
    next: Vec<f64>,
    p: Vec<[f64; 3]>,
}

impl CpuFista {
    pub fn new(problem: &DenseProblem) -> CpuFista {
        let nodes = problem.nodes();
        CpuFista { gradient: vec![0.0; nodes], next: vec![0.0; nodes], p: vec![[0.0; 3]; nodes] }
    }
}

impl FistaSolver for CpuFista {
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f64],
        target: &[f64],
        steps: usize,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f64]),
    ) -> anyhow::Result<()> {
        let (n, b, step, epsilon) = (problem.n, problem.rays_seen, problem.step, problem.epsilon);
        let w = problem.lambda / problem.nodes() as f64;
        let (gradient, next, p) = (&mut self.gradient, &mut self.next, &mut self.p);
        let (mut ahead, mut t) = (sigma.to_vec(), 1.0f64);
        for it in 0..steps {
            // ∇E = Aᵀ(Aσ − τ)/B + λ/N³ ∇TV, at the look-ahead point.
            problem.projector.back_into(&problem.residual(&problem.projector.depths(&ahead), target), gradient);
            p.par_iter_mut().enumerate().for_each(|(i, p)| *p = normalised_difference(&ahead, n, epsilon, i).1);
            gradient.par_iter_mut().enumerate().for_each(|(i, g)| *g = *g / b + w * tv_gradient_at(p, n, i));
            next.par_iter_mut().zip(&ahead).zip(&*gradient).for_each(|((x, a), g)| *x = (a - step * g).max(0.0));
            let (t_next, momentum) = next_momentum(t);
            ahead.par_iter_mut().zip(&*next).zip(&*sigma).for_each(|((a, x), old)| *a = x + momentum * (x - old));
            sigma.copy_from_slice(next);
            t = t_next;
            if wants(it + 1) {
                checkpoint(it + 1, sigma);
            }
        }
        Ok(())
    }
}

/// Fits σ to `views` on the CPU; see [`fit_with`].
pub fn fit(params: &TrainParams, views: &Views, renderer: &Renderer, on_log: impl FnMut(&LogRow)) -> DenseFitted {
    fit_with(params, views, renderer, |problem| Ok(CpuFista::new(problem)), on_log)
        .expect("the CPU solver does not fail")
}

/// Fits σ to `views` as the module describes, `params.dense_tv.iterations` FISTA steps by the
/// solver `solver_for` makes, logging as the VM fit logs (`photo` is the data term, `tv3d` the
/// smoothed TV, `lr` the step `1/L`; every row evaluated here, in f64, whatever the solver).
pub fn fit_with<S: FistaSolver>(
    params: &TrainParams,
    views: &Views,
    renderer: &Renderer,
    solver_for: impl FnOnce(&DenseProblem) -> anyhow::Result<S>,
    mut on_log: impl FnMut(&LogRow),
) -> anyhow::Result<DenseFitted> {
    let started = Instant::now();
    let per_view = views.rays();
    let rays: Vec<Ray> = per_view.iter().flatten().copied().collect();
    let problem = DenseProblem::new(params, &rays, renderer);
    let mut log = Vec::new();
    let mut record = |iteration: usize, e: &Evaluation| {
        let row = problem.log_row(&per_view, iteration, e, started.elapsed().as_secs_f64());
        on_log(&row);
        log.push(row);
    };
    let mut sigma = vec![0.0; problem.nodes()];
    record(0, &problem.evaluate(&sigma));
    let mut solver = solver_for(&problem)?;
    let wants = |k: usize| params.logs_after(k);
    solver.solve(&problem, &mut sigma, &problem.measured, params.dense_tv.iterations, &wants, &mut |k, sigma| {
        record(k, &problem.evaluate(sigma))
    })?;
    Ok(DenseFitted { sigma: sigma.iter().map(|&v| v as f32).collect(), log })
}

/// How closely a given σ on the lattice reproduces `views`, as the row a fit logs: E's terms
/// under `params`' TV and each view's PSNR (`[train] model = "truth"` logs its one row so).
pub fn evaluate_views(params: &TrainParams, views: &Views, renderer: &Renderer, sigma: &[f32]) -> LogRow {
    let started = Instant::now();
    let per_view = views.rays();
    let rays: Vec<Ray> = per_view.iter().flatten().copied().collect();
    let problem = DenseProblem::new(params, &rays, renderer);
    let sigma: Vec<f64> = sigma.iter().map(|&v| f64::from(v)).collect();
    problem.log_row(&per_view, 0, &problem.evaluate(&sigma), started.elapsed().as_secs_f64())
}

/// A bound on the curvature of E: the largest eigenvalue of `AᵀA/B` by power iteration (from
/// all ones: A is non-negative, so its leading vector is too), with 5 % to spare, plus the
/// smoothed TV's `λ/N³ · 12/ε` (the squared norm of the 3-D forward difference is at most 12).
fn lipschitz(projector: &Projector, nodes: usize, b: f64, lambda: f64, epsilon: f64) -> f64 {
    let mut x = vec![1.0 / (nodes as f64).sqrt(); nodes];
    let mut eigenvalue = 0.0;
    for _ in 0..30 {
        let y = projector.back(&projector.depths(&x));
        eigenvalue = y.iter().map(|v| v * v).sum::<f64>().sqrt();
        if eigenvalue == 0.0 {
            break;
        }
        x = y.iter().map(|v| v / eigenvalue).collect();
    }
    1.05 * eigenvalue / b + lambda / nodes as f64 * 12.0 / epsilon
}

/// Each view's intensity MSE over all its pixels, `Î = exp(−τ̂)` (1 where a ray misses the box).
fn view_mse(per_view: &[Vec<Ray>], depths: &[f64]) -> Vec<f64> {
    let mut start = 0;
    per_view
        .iter()
        .map(|rays| {
            let view = &depths[start..start + rays.len()];
            start += rays.len();
            let sum: f64 = rays.iter().zip(view).map(|(r, d)| ((-d).exp() - r.target).powi(2)).sum();
            sum / rays.len().max(1) as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Aabb;
    use crate::train::render::{Lattice, PhotoLoss};
    use glam::DVec3;

    fn renderer(n: usize) -> Renderer {
        let aabb = Aabb { min: [-1.0, -0.8, -0.6], max: [1.0, 0.8, 0.6] };
        Renderer { lattice: Lattice { n, aabb }, shift: 0.0, scale: 1.3, step: 0.05, loss: PhotoLoss::Log }
    }

    fn rays() -> Vec<Ray> {
        // Oblique rays through the box from several sides, and one that misses it.
        let mut rays: Vec<Ray> = (0..40)
            .map(|i| {
                let a = i as f64 * 0.37;
                let origin = DVec3::new(3.0 * a.cos(), 2.5 * a.sin(), 0.4 * (a * 1.7).sin());
                let dir = (DVec3::new(0.1 * (a * 3.1).sin(), 0.05, -0.2 * a.cos()) - origin).normalize();
                Ray { origin, dir, target: 0.5 }
            })
            .collect();
        rays.push(Ray { origin: DVec3::new(0.0, 5.0, 0.0), dir: DVec3::X, target: 1.0 });
        rays
    }

    #[test]
    fn the_projection_is_the_renderers_optical_depth() {
        let (renderer, rays) = (renderer(6), rays());
        let sigma: Vec<f64> = (0..216).map(|i| ((i * 37) % 11) as f64 * 0.1).collect();
        let depths = Projector::new(&renderer, &rays).depths(&sigma);
        assert!(depths.iter().filter(|&&d| d > 0.0).count() >= 30, "most rays cross the box: {depths:?}");
        assert_eq!(depths.last(), Some(&0.0), "the last ray misses it");
        for (ray, depth) in rays.iter().zip(depths) {
            let rendered = renderer.render_ray(&sigma, None, ray, renderer.step / 2.0);
            assert!((rendered - (-depth).exp()).abs() < 1e-12, "{rendered} against {}", (-depth).exp());
        }
    }

    /// A sparse matrix's rows as (column, weight) lists.
    type Rows = Vec<Vec<(u32, f64)>>;

    /// `A` and `Aᵀ` as the plainest code builds them: a map per ray, summed in sample order.
    fn plain_projector(renderer: &Renderer, rays: &[Ray]) -> (Rows, Rows) {
        let n = renderer.lattice.n;
        let rows: Rows = rays
            .iter()
            .map(|ray| {
                let (q0, dq, count) = renderer.samples(ray, renderer.step / 2.0);
                let mut row = std::collections::BTreeMap::new();
                for k in 0..count {
                    let q: [f64; 3] = std::array::from_fn(|a| q0[a] + k as f64 * dq[a]);
                    let (cell, weights) = cell_and_weights(q, n);
                    let corners = [0, 1, n, n + 1, n * n, n * n + 1, n * n + n, n * n + n + 1];
                    for (offset, w) in corners.iter().zip(weights) {
                        let w = w * (renderer.scale * renderer.step);
                        row.entry((cell + offset) as u32).and_modify(|sum| *sum += w).or_insert(w);
                    }
                }
                row.into_iter().collect()
            })
            .collect();
        let mut columns = vec![vec![]; n * n * n];
        for (r, row) in rows.iter().enumerate() {
            for &(c, w) in row {
                columns[c as usize].push((r as u32, w));
            }
        }
        (rows, columns)
    }

    fn entries(m: &Csr) -> Rows {
        m.offsets.windows(2).map(|w| (w[0]..w[1]).map(|k| (m.index[k], m.weight[k])).collect()).collect()
    }

    #[test]
    fn the_projector_is_the_plain_sums_bit_for_bit_on_any_thread_count() {
        let (renderer, rays) = (renderer(7), rays());
        let (rows, columns) = plain_projector(&renderer, &rays);
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let projector = pool.install(|| Projector::new(&renderer, &rays));
            assert!(entries(&projector.rows) == rows, "A on {threads} threads");
            assert!(entries(&projector.columns) == columns, "Aᵀ on {threads} threads");
        }
    }

    #[test]
    fn the_back_projection_is_the_transpose() {
        let (renderer, rays) = (renderer(5), rays());
        let projector = Projector::new(&renderer, &rays);
        let x: Vec<f64> = (0..125).map(|i| ((i * 13) % 7) as f64 - 3.0).collect();
        let r: Vec<f64> = (0..rays.len()).map(|i| ((i * 5) % 9) as f64 * 0.25 - 1.0).collect();
        let left: f64 = projector.depths(&x).iter().zip(&r).map(|(a, b)| a * b).sum();
        let right: f64 = projector.back(&r).iter().zip(&x).map(|(a, b)| a * b).sum();
        assert!((left - right).abs() < 1e-9 * left.abs().max(1.0), "{left} against {right}");
    }

    #[test]
    fn the_tv_gradient_matches_finite_differences() {
        let n = 4;
        let sigma: Vec<f64> = (0..64).map(|i| ((i * 29) % 13) as f64 * 0.07).collect();
        let (_, gradient) = smoothed_tv(&sigma, n, 0.05);
        for i in [0, 5, 21, 42, 63] {
            let h = 1e-6;
            let (mut up, mut down) = (sigma.clone(), sigma.clone());
            up[i] += h;
            down[i] -= h;
            let numeric = (smoothed_tv(&up, n, 0.05).0 - smoothed_tv(&down, n, 0.05).0) / (2.0 * h);
            assert!((numeric - gradient[i]).abs() < 1e-6, "node {i}: {numeric} against {}", gradient[i]);
        }
    }
}
