//! The training loop: Adam on MSE + λ1·L1 + λ2·TV over seeded ray batches (SPEC §3 train).

use super::adam::{Adam, AdamParams};
use super::field::VmField;
use super::regularize::{self, TvNorm};
use super::render::{AlphaMask, Lattice, Ray, Renderer, MAX_GRID};
use crate::geometry::{Aabb, Camera};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::time::Instant;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainParams {
    /// Lattice nodes per axis (N); planes are N×N, lines N.
    pub grid: usize,
    /// Components per plane/line pair (R).
    pub rank: usize,
    /// Δ in σ = ReLU(f + Δ).
    pub shift: f64,
    /// s in Î = exp(−s · Σ σ δ).
    pub scale: f64,
    pub iterations: usize,
    pub batch_rays: usize,
    pub lr: f64,
    /// Learning rate at the end over at the start (exponential decay).
    pub lr_decay_ratio: f64,
    pub lambda_l1: f64,
    pub lambda_tv: f64,
    pub tv_norm: TvNorm,
    /// Weight of the 3-D TV of the composed field F (0: off, as in the paper).
    pub lambda_tv3d: f64,
    /// Factors start as `init_scale · N(0, 1)`.
    pub init_scale: f64,
    /// Iterations after which the alpha mask is (re)computed.
    pub alpha_mask_iterations: Vec<usize>,
    pub alpha_threshold: f64,
    /// Evaluate and log every this many iterations (and at the last).
    pub log_every: usize,
    pub seed: u64,
    /// Where the fit runs (part of the cache key: backends differ in rounding).
    pub backend: Backend,
    /// Worker threads (0: all cores). Results do not depend on it: not part of the cache key.
    pub threads: usize,
}

/// Where the training runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Cpu,
    Gpu,
    /// The GPU when an adapter exists, else the CPU.
    Auto,
}

impl TrainParams {
    pub fn check(&self) -> anyhow::Result<()> {
        if self.grid < 2 || self.grid > MAX_GRID || self.rank == 0 || self.iterations == 0 || self.batch_rays == 0 {
            anyhow::bail!("[train] grid must be in [2, {MAX_GRID}] and rank, iterations, batch_rays ≥ 1");
        }
        for (key, v) in [("scale", self.scale), ("lr", self.lr), ("lr_decay_ratio", self.lr_decay_ratio)] {
            if !(v.is_finite() && v > 0.0) {
                anyhow::bail!("[train] {key} must be positive (got {v})");
            }
        }
        Ok(())
    }
}

impl Default for TrainParams {
    fn default() -> Self {
        TrainParams {
            grid: 64,
            rank: 16,
            shift: 0.0,
            scale: 1.0,
            iterations: 3000,
            batch_rays: 2048,
            lr: 0.02,
            lr_decay_ratio: 0.1,
            lambda_l1: 1e-4,
            lambda_tv: 1e-5,
            tv_norm: TvNorm::L1,
            lambda_tv3d: 1e-4,
            init_scale: 0.1,
            alpha_mask_iterations: vec![1500, 2500],
            alpha_threshold: 1e-3,
            log_every: 100,
            seed: 0,
            backend: Backend::Cpu,
            threads: 0,
        }
    }
}

/// One logged iteration.
#[derive(Debug, Clone, Serialize)]
pub struct LogRow {
    pub iteration: usize,
    pub loss: f64,
    pub photo: f64,
    pub l1: f64,
    pub tv: f64,
    /// 3-D TV of the composed field (before its weight).
    pub tv3d: f64,
    /// PSNR (dB) of each view rendered in full with midpoint samples, in camera order.
    /// (`photo` is the batch MSE, except at iteration 0: the mean full-view MSE.)
    pub psnr_db: Vec<f64>,
    pub lr: f64,
    pub seconds: f64,
}

/// The three (or more) training images with their cameras.
pub struct Views<'a> {
    pub cameras: &'a [Camera],
    /// `I/I0` per pixel, row-major, one image per camera.
    pub images: &'a [Vec<f32>],
    pub aabb: Aabb,
}

impl Views<'_> {
    /// Every pixel's ray, per view, keeping only rays that meet the box (TensoRF's filtering).
    pub fn rays(&self) -> Vec<Vec<Ray>> {
        self.cameras
            .iter()
            .zip(self.images)
            .map(|(cam, img)| {
                let mut rays = Vec::with_capacity(img.len());
                for j in 0..cam.height {
                    for i in 0..cam.width {
                        let (origin, dir) = (cam.eye(), cam.ray_dir(i, j));
                        let target = f64::from(img[i + cam.width * j]);
                        rays.push(Ray { origin, dir, target });
                    }
                }
                rays
            })
            .collect()
    }
}

/// The trained field, its log, and the final alpha mask (if one was computed).
pub struct Fitted {
    pub field: VmField<f32>,
    pub log: Vec<LogRow>,
    pub mask: Option<AlphaMask>,
    pub renderer: Renderer,
}

/// The renderer of `params` on `aabb`: samples every half mean voxel.
pub fn renderer(params: &TrainParams, aabb: Aabb) -> Renderer {
    let mean_voxel = (0..3).map(|a| (aabb.max[a] - aabb.min[a]) / params.grid as f64).sum::<f64>() / 3.0;
    Renderer {
        lattice: Lattice { n: params.grid, aabb },
        shift: params.shift,
        scale: params.scale,
        step: 0.5 * mean_voxel,
    }
}

/// Fits a field to `views`. `on_log` sees every logged row as it is made.
pub fn fit(params: &TrainParams, views: &Views, mut on_log: impl FnMut(&LogRow)) -> Fitted {
    let started = Instant::now();
    let renderer = renderer(params, views.aabb);
    let per_view = views.rays();
    let hits = |r: &Ray| views.aabb.intersect(r.origin, r.dir).is_some();
    let pool: Vec<Ray> = per_view.iter().flatten().copied().filter(hits).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    let mut field: VmField<f32> = VmField::random(params.grid, params.rank, params.init_scale, rng.gen());
    let adam_params = AdamParams {
        lr: params.lr,
        beta1: 0.9,
        beta2: 0.99,
        eps: 1e-8,
        decay_ratio: params.lr_decay_ratio,
        iterations: params.iterations,
    };
    let mut adam = Adam::new(adam_params, &field);
    let mut order: Vec<usize> = (0..pool.len()).collect();
    let mut cursor = order.len(); // reshuffle on first use
    let mut mask: Option<AlphaMask> = None;
    let mut log = Vec::new();
    // Row 0: the initial field, before any update (its "photo" is the full-view MSE).
    let initial_mse = view_mse(&renderer, &field, None, &per_view);
    let photo = initial_mse.iter().sum::<f64>() / initial_mse.len() as f64;
    let mut scratch = VmField::zeros(field.n, field.rank);
    let (l1, tv) =
        (regularize::l1(&field, 0.0, &mut scratch), regularize::tv(&field, params.tv_norm, 0.0, &mut scratch));
    let tv3d = tv_dense_value(&field.compose(), field.n);
    let initial = LogRow {
        iteration: 0,
        loss: photo + params.lambda_l1 * l1 + params.lambda_tv * tv + params.lambda_tv3d * tv3d,
        photo,
        l1,
        tv,
        tv3d,
        psnr_db: initial_mse.iter().map(|&m| psnr_db(m)).collect(),
        lr: params.lr,
        seconds: started.elapsed().as_secs_f64(),
    };
    on_log(&initial);
    log.push(initial);
    let mut batch = Vec::with_capacity(params.batch_rays);
    let mut offsets = Vec::with_capacity(params.batch_rays);
    let mut drawn: Vec<(usize, f64)> = Vec::with_capacity(params.batch_rays);
    for it in 0..params.iterations {
        drawn.clear();
        while drawn.len() < params.batch_rays.min(pool.len()) {
            if cursor == order.len() {
                order.shuffle(&mut rng);
                cursor = 0;
            }
            drawn.push((order[cursor], rng.gen::<f64>() * renderer.step));
            cursor += 1;
        }
        // Trace in pool order (view, then pixel row): neighbouring rays share lattice cells,
        // so they hit the cache. The drawn set and offsets are unchanged.
        drawn.sort_unstable_by_key(|&(i, _)| i);
        batch.clear();
        offsets.clear();
        batch.extend(drawn.iter().map(|&(i, _)| pool[i]));
        offsets.extend(drawn.iter().map(|&(_, o)| o));
        let dense = field.compose();
        let mut grad_dense = vec![0f32; dense.len()];
        let result = renderer.batch(&dense, mask.as_ref(), &batch, &offsets, Some(&mut grad_dense));
        // The 3-D TV acts on F itself: its gradient joins dL/dF before the contraction.
        let tv3d = (params.lambda_tv3d > 0.0)
            .then(|| regularize::tv_dense(&dense, field.n, params.lambda_tv3d as f32, &mut grad_dense));
        let mut grad = field.contract(&grad_dense);
        let l1 = regularize::l1(&field, params.lambda_l1 as f32, &mut grad);
        let tv = regularize::tv(&field, params.tv_norm, params.lambda_tv as f32, &mut grad);
        let lr = adam.update(&mut field, &grad);
        if params.alpha_mask_iterations.contains(&(it + 1)) {
            mask = Some(renderer.alpha_mask(&field.compose(), params.alpha_threshold));
        }
        if (it + 1) % params.log_every.max(1) == 0 || it + 1 == params.iterations {
            // F before this update, as the other terms; computed here only when it is not trained.
            let tv3d = tv3d.unwrap_or_else(|| tv_dense_value(&dense, field.n));
            let row = LogRow {
                iteration: it + 1,
                loss: result.mse + params.lambda_l1 * l1 + params.lambda_tv * tv + params.lambda_tv3d * tv3d,
                photo: result.mse,
                l1,
                tv,
                tv3d,
                psnr_db: view_mse(&renderer, &field, mask.as_ref(), &per_view).into_iter().map(psnr_db).collect(),
                lr,
                seconds: started.elapsed().as_secs_f64(),
            };
            on_log(&row);
            log.push(row);
        }
    }
    Fitted { field, log, mask, renderer }
}

/// The 3-D TV of a composed F, unweighted.
fn tv_dense_value(dense: &[f32], n: usize) -> f64 {
    regularize::tv_dense(dense, n, 0.0, &mut vec![0.0; dense.len()])
}

/// Mean squared error of each view rendered in full with midpoint samples.
pub fn view_mse(
    renderer: &Renderer,
    field: &VmField<f32>,
    mask: Option<&AlphaMask>,
    per_view: &[Vec<Ray>],
) -> Vec<f64> {
    let dense = field.compose();
    per_view
        .iter()
        .map(|rays| {
            let offsets = vec![renderer.step / 2.0; rays.len()];
            renderer.batch(&dense, mask, rays, &offsets, None).mse
        })
        .collect()
}

/// PSNR (dB) of a mean squared error, peak 1.
pub fn psnr_db(mse: f64) -> f64 {
    10.0 * (1.0 / mse.max(1e-20)).log10()
}
