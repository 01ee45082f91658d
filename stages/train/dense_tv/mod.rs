//! `[train] model = "dense_tv"`: the attenuation field as a dense N³ lattice of σ (no factors),
//! fitted to the three views' optical depths under a smoothed 3-D total variation.
//!
//! Optical depths are line integrals, so the projection is linear in σ: `τ̂ = A σ`, with `A`
//! the matrix-free projector of [`super::projector`]. The fit minimises
//!
//! `E(σ) = 1/(2B) Σ_rays (τ̂ − τ)² + λ/N³ Σ_nodes √(|∇σ|² + ε²)`,  `σ ≥ 0`,
//!
//! (B rays that meet the box, `∇` forward differences in lattice steps) by FISTA: projected
//! gradient steps, each node's step the inverse of a diagonal bound on the curvature of a
//! quadratic majoriser of E at the look-ahead point (`AᵀA ≤ diag(AᵀA·1)` as `A ≥ 0`; the TV's
//! majoriser `|∇σ|²/(2m)` with `m = √(|∇σ|² + ε²)` frozen, whose curvature is `6/m` and `2/m`
//! a neighbour, at most the smoothed TV's `12/ε`), with Nesterov momentum restarted whenever
//! it points uphill. It stops when a step whose look-ahead carries momentum changes σ by at most
//! `tolerance` of its norm, or after `iterations` steps. It starts from the same fit, to a looser
//! tolerance, on a lattice of half the nodes a side, trilinearly enlarged. E is convex and
//! nothing is random: the seed plays no part.
//!
//! Why: the VM factorisation explains each view with products of planes and lines, and those
//! products cross everywhere as streaks; a dense lattice with TV is the classic few-view CT
//! reconstruction, whose cheapest explanation of a blob seen in three views is one compact blob.

mod cpu;
pub mod tv;

pub use cpu::CpuFista;

use super::fit::{psnr_db, LogRow, Views};
use super::params::TrainParams;
use super::projector::Projector;
use super::render::{Lattice, Ray, Renderer, MIN_INTENSITY};
use rayon::prelude::*;
use std::time::Instant;
use tv::PlaneDirections;

/// The smallest lattice that starts from a coarser fit (nodes a side).
const SMALLEST_WARM_STARTED: usize = 32;
/// The coarse fit's tolerance over the fit's own: the coarse fit only gives the start.
const COARSE_TOLERANCE: f64 = 20.0;

/// The fitted lattice (σ at the nodes, index `x + N·(y + N·z)`), its log, and the steps
/// taken on the coarse lattice and on the lattice itself.
pub struct DenseFitted {
    pub sigma: Vec<f32>,
    pub log: Vec<LogRow>,
    pub steps: [usize; 2],
}

/// The terms of E at one σ.
pub struct Evaluation {
    /// `1/(2B) Σ (τ̂ − τ)²`.
    pub data: f64,
    /// `1/N³ Σ √(|∇σ|² + ε²)`, before λ.
    pub tv: f64,
    pub depths: Vec<f64>,
}

impl Evaluation {
    /// E itself.
    pub fn energy(&self, lambda: f64) -> f64 {
        self.data + lambda * self.tv
    }
}

/// When a solve stops: after `steps` steps, or sooner once a step whose look-ahead carries
/// momentum changes σ by at most `tolerance` of its norm.
#[derive(Debug, Clone, Copy)]
pub struct Stop {
    pub steps: usize,
    pub tolerance: f64,
}

/// What every solver of E shares: the projector, which rays meet the box, the measured
/// depths, E's weights and each node's step. The GPU's solver uploads it (`gpu::dense_fit`).
pub struct DenseProblem {
    /// The lattice's nodes per side, N.
    pub n: usize,
    pub projector: Projector,
    /// Whether each ray meets the box.
    pub seen: Vec<bool>,
    /// B, the rays that meet the box (at least 1).
    pub rays_seen: f64,
    /// `τ = −ln I` of every ray.
    pub measured: Vec<f64>,
    pub lambda: f64,
    pub epsilon: f64,
    /// Each node's bound on the data term's curvature, `(AᵀA·1)/B`.
    pub data_curvature: Vec<f32>,
}

impl DenseProblem {
    /// E on `lattice` for `rays` (whose views are runs of `(rays, pixels a row)` in order),
    /// `scale` being the renderer's `s`.
    pub fn new(
        lattice: &Lattice,
        scale: f64,
        lambda: f64,
        epsilon: f64,
        rays: &[Ray],
        views: &[(usize, usize)],
    ) -> DenseProblem {
        let n = lattice.n;
        let projector = Projector::new(lattice, scale, rays, views);
        let mut seen = vec![false; rays.len()];
        for row in projector.lines() {
            seen[row as usize] = true;
        }
        let rays_seen = seen.iter().filter(|&&s| s).count().max(1) as f64;
        let measured = rays.iter().map(|r| -r.target.max(MIN_INTENSITY).ln()).collect();
        let nodes = n * n * n;
        let mut row_sums = vec![0.0; rays.len()];
        projector.project(&vec![1.0; nodes], &mut row_sums);
        let mut curvature = vec![0.0f32; nodes];
        projector.back_project(&row_sums, &mut curvature);
        let data_curvature = curvature.par_iter().map(|&c| (f64::from(c) / rays_seen) as f32).collect();
        DenseProblem { n, projector, seen, rays_seen, measured, lambda, epsilon, data_curvature }
    }

    pub fn nodes(&self) -> usize {
        self.n * self.n * self.n
    }

    /// τ̂ − τ on the rays that meet the box (0 on the others), into `out`.
    pub fn residual_into(&self, depths: &[f64], out: &mut [f64]) {
        out.par_iter_mut().zip(depths).zip(&self.measured).zip(&self.seen).for_each(|(((o, d), m), &s)| {
            *o = if s { d - m } else { 0.0 };
        });
    }

    /// The log row of an evaluation: E's terms and each view's PSNR (`lr`: the mean step that
    /// E's curvature bound allows, `1/((AᵀA·1)/B + 12 λ/(N³ ε))`; the steps taken are longer).
    fn log_row(&self, per_view: &[Vec<Ray>], iteration: usize, e: &Evaluation, seconds: f64) -> LogRow {
        let tv_bound = self.lambda / self.nodes() as f64 * 12.0 / self.epsilon;
        let mean_step =
            self.data_curvature.iter().map(|&c| 1.0 / (f64::from(c) + tv_bound)).sum::<f64>() / self.nodes() as f64;
        LogRow {
            iteration,
            loss: e.energy(self.lambda),
            photo: e.data,
            l1: 0.0,
            tv: 0.0,
            tv3d: e.tv,
            psnr_db: view_mse(per_view, &e.depths).into_iter().map(psnr_db).collect(),
            lr: mean_step,
            seconds,
        }
    }

    /// E's terms at `sigma`, in f64.
    pub fn evaluate(&self, sigma: &[f32]) -> Evaluation {
        let mut depths = vec![0.0; self.projector.rays];
        self.projector.project(sigma, &mut depths);
        let mut residual = vec![0.0; depths.len()];
        self.residual_into(&depths, &mut residual);
        let data = residual.iter().map(|r| r * r).sum::<f64>() / (2.0 * self.rays_seen);
        let (n, epsilon) = (self.n, self.epsilon as f32);
        let per_plane: Vec<f64> = (0..n)
            .into_par_iter()
            .map_init(
                || PlaneDirections::new(n),
                |p, z| {
                    p.compute(sigma, n, z, epsilon);
                    p.smoothed_sum()
                },
            )
            .collect();
        Evaluation { data, tv: per_plane.iter().sum::<f64>() / self.nodes() as f64, depths }
    }
}

/// FISTA on E: [`CpuFista`] here, or the device's loop (`gpu::dense_fit`).
pub trait FistaSolver {
    /// Runs FISTA steps on `problem` from `sigma` until `stop`, and leaves the last iterate in
    /// `sigma`. After each step `k` (from 1) for which `wants(k)`, and after the last, it hands
    /// σ to `checkpoint`. Returns the steps taken.
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f32],
        stop: Stop,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f32]),
    ) -> anyhow::Result<usize>;
}

impl FistaSolver for Box<dyn FistaSolver> {
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f32],
        stop: Stop,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f32]),
    ) -> anyhow::Result<usize> {
        (**self).solve(problem, sigma, stop, wants, checkpoint)
    }
}

/// FISTA's momentum weight after the step that takes `t` to the returned `t'`: `(t − 1)/t'`.
pub fn next_momentum(t: f64) -> (f64, f64) {
    let t_next = (1.0 + (1.0 + 4.0 * t * t).sqrt()) / 2.0;
    (t_next, (t - 1.0) / t_next)
}

/// Fits σ to `views` on the CPU; see [`fit_with`].
pub fn fit(params: &TrainParams, views: &Views, renderer: &Renderer, on_log: impl FnMut(&LogRow)) -> DenseFitted {
    fit_with(params, views, renderer, |problem| Ok(CpuFista::new(problem)), on_log)
        .expect("the CPU solver does not fail")
}

/// The problem of `params` on `lattice` for the rays of `per_view`.
fn problem(params: &TrainParams, views: &Views, lattice: Lattice, scale: f64, rays: &[Ray]) -> DenseProblem {
    let spans: Vec<(usize, usize)> = views.cameras.iter().map(|c| (c.width * c.height, c.width)).collect();
    // λ and ε are per lattice step: on a coarser lattice the same field's TV is per longer step.
    let ratio = params.grid as f64 / lattice.n as f64;
    let (lambda, epsilon) = (params.dense_tv.lambda / ratio, params.dense_tv.epsilon * ratio);
    DenseProblem::new(&lattice, scale, lambda, epsilon, rays, &spans)
}

/// Fits σ to `views` as the module describes, by the solver `solver_for` makes for each
/// lattice, logging as the VM fit logs (`photo` is the data term, `tv3d` the smoothed TV, `lr`
/// the mean step; every row evaluated here, in f64, whatever the solver). Row 0 is the coarse
/// fit's start on the lattice.
pub fn fit_with<S: FistaSolver>(
    params: &TrainParams,
    views: &Views,
    renderer: &Renderer,
    mut solver_for: impl FnMut(&DenseProblem) -> anyhow::Result<S>,
    mut on_log: impl FnMut(&LogRow),
) -> anyhow::Result<DenseFitted> {
    let started = Instant::now();
    let per_view = views.rays();
    let rays: Vec<Ray> = per_view.iter().flatten().copied().collect();
    let stop = Stop { steps: params.dense_tv.iterations, tolerance: params.dense_tv.tolerance };
    let lattice = renderer.lattice;
    let (mut sigma, coarse_steps) = if lattice.n >= SMALLEST_WARM_STARTED {
        let coarse = Lattice { n: lattice.n / 2, ..lattice };
        let problem = problem(params, views, coarse, renderer.scale, &rays);
        let mut sigma = vec![0.0; problem.nodes()];
        let coarse_stop = Stop { tolerance: (stop.tolerance * COARSE_TOLERANCE).min(0.5), ..stop };
        let steps = solver_for(&problem)?.solve(&problem, &mut sigma, coarse_stop, &|_| false, &mut |_, _| {})?;
        (enlarge(&sigma, coarse.n, lattice.n), steps)
    } else {
        (vec![0.0; lattice.n.pow(3)], 0)
    };
    let problem = problem(params, views, lattice, renderer.scale, &rays);
    let mut log = Vec::new();
    let mut record = |iteration: usize, sigma: &[f32]| {
        let row = problem.log_row(&per_view, iteration, &problem.evaluate(sigma), started.elapsed().as_secs_f64());
        on_log(&row);
        log.push(row);
    };
    record(0, &sigma);
    let wants = |k: usize| params.logs_after(k);
    let steps = solver_for(&problem)?.solve(&problem, &mut sigma, stop, &wants, &mut record)?;
    Ok(DenseFitted { sigma, log, steps: [coarse_steps, steps] })
}

/// σ on an `n³` lattice from σ on a `coarse³` one over the same box, trilinear between the
/// coarse nodes and constant beyond the outermost ones.
pub fn enlarge(sigma: &[f32], coarse: usize, n: usize) -> Vec<f32> {
    let ratio = coarse as f64 / n as f64;
    // Each fine index's coarse cell and weight along an axis.
    let along: Vec<(usize, f32)> = (0..n)
        .map(|i| {
            let c = ((i as f64 + 0.5) * ratio - 0.5).clamp(0.0, (coarse - 1) as f64);
            let base = (c as usize).min(coarse.saturating_sub(2));
            (base, (c - base as f64) as f32)
        })
        .collect();
    let at = |x: usize, y: usize, z: usize| sigma[x + coarse * (y + coarse * z)];
    let lerp = |a: f32, b: f32, f: f32| a + f * (b - a);
    let mut out = vec![0.0f32; n * n * n];
    out.par_chunks_mut(n * n).enumerate().for_each(|(z, plane)| {
        let (z0, fz) = along[z];
        let z1 = (z0 + 1).min(coarse - 1);
        for y in 0..n {
            let (y0, fy) = along[y];
            let y1 = (y0 + 1).min(coarse - 1);
            for x in 0..n {
                let (x0, fx) = along[x];
                let x1 = (x0 + 1).min(coarse - 1);
                let face =
                    |z: usize| lerp(lerp(at(x0, y0, z), at(x1, y0, z), fx), lerp(at(x0, y1, z), at(x1, y1, z), fx), fy);
                plane[x + n * y] = lerp(face(z0), face(z1), fz);
            }
        }
    });
    out
}

/// How closely a given σ on the lattice reproduces `views`, as the row a fit logs: E's terms
/// under `params`' TV and each view's PSNR (`[train] model = "truth"` logs its one row so).
pub fn evaluate_views(params: &TrainParams, views: &Views, renderer: &Renderer, sigma: &[f32]) -> LogRow {
    let started = Instant::now();
    let per_view = views.rays();
    let rays: Vec<Ray> = per_view.iter().flatten().copied().collect();
    let problem = problem(params, views, renderer.lattice, renderer.scale, &rays);
    problem.log_row(&per_view, 0, &problem.evaluate(sigma), started.elapsed().as_secs_f64())
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

/// A 6³ lattice in the box [−1, 1]³ and 30 rays at it from a ring around it, each measuring
/// `target` (I/I₀): a small problem for the solvers' tests.
#[cfg(test)]
fn ring_of_rays(target: f64) -> (Lattice, Vec<Ray>) {
    let lattice = Lattice { n: 6, aabb: crate::geometry::Aabb { min: [-1.0; 3], max: [1.0; 3] } };
    let rays = (0..30)
        .map(|i| {
            let a = i as f64 * 0.41;
            let origin = glam::DVec3::new(4.0 * a.cos(), 3.0 * a.sin(), 0.5 * (2.0 * a).sin());
            Ray { origin, dir: (-origin).normalize(), target }
        })
        .collect();
    (lattice, rays)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn enlarging_keeps_a_linear_field_inside_and_a_constant_one_everywhere() {
        let (coarse, n) = (5, 10);
        let flat = enlarge(&vec![0.7; coarse * coarse * coarse], coarse, n);
        assert!(flat.iter().all(|&v| (v - 0.7).abs() < 1e-6));
        // σ = x (coarse index) is σ = (x_f + 0.5)/2 − 0.5 on the fine lattice, where inside.
        let ramp: Vec<f32> = (0..coarse.pow(3)).map(|i| (i % coarse) as f32).collect();
        let fine = enlarge(&ramp, coarse, n);
        for x in 1..n - 1 {
            let expected = (x as f32 + 0.5) / 2.0 - 0.5;
            assert!((fine[x + n * (3 + n * 4)] - expected).abs() < 1e-5, "x = {x}");
        }
    }

    #[test]
    fn each_nodes_data_curvature_bounds_a_change_there() {
        // For a unit change δ at one node, E's data term grows by ½ |A δ|²/B ≤ ½ δ² (AᵀA·1)/B.
        let (lattice, rays) = ring_of_rays(0.5);
        let problem = DenseProblem::new(&lattice, 1.0, 0.0, 1.0, &rays, &[(30, 30)]);
        for node in 0..problem.nodes() {
            let mut delta = vec![0.0f32; problem.nodes()];
            delta[node] = 1.0;
            let mut depths = vec![0.0; rays.len()];
            problem.projector.project(&delta, &mut depths);
            let curvature = depths.iter().map(|d| d * d).sum::<f64>() / problem.rays_seen;
            assert!(curvature <= f64::from(problem.data_curvature[node]) * (1.0 + 1e-5), "node {node}");
        }
    }
}
