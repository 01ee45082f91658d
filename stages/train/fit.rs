//! The training loop: Adam on MSE + λ1·L1 + λ2·TV over seeded ray batches (SPEC §3 train).

use super::adam::Adam;
use super::field::VmField;
use super::huge_pages::HugePageBuffer;
use super::params::{FieldModel, TrainParams};
use super::regularize::{self, Penalties, TvNorm};
use super::render::{AlphaMask, BatchResult, Lattice, PhotoLoss, Ray, Renderer};
use crate::geometry::{Aabb, Camera};
use crate::kernels::wide::with_avx2;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

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
    /// Each iteration's wall time in seconds: its gradient and update, without evaluations,
    /// logging or re-masking (what a per-iteration benchmark compares). Empty where the steps
    /// run asynchronously (the GPU backend queues them).
    pub step_seconds: Vec<f64>,
}

/// The renderer of `params` on `aabb`: samples every half mean voxel. Only the VM field has a
/// shift and a choice of photometric loss; a lattice of σ renders σ itself.
pub fn renderer(params: &TrainParams, aabb: Aabb) -> Renderer {
    let mean_voxel = (0..3).map(|a| (aabb.max[a] - aabb.min[a]) / params.grid as f64).sum::<f64>() / 3.0;
    let (shift, loss) = match params.model {
        FieldModel::Vm => (params.vm.shift, params.vm.loss),
        _ => (0.0, PhotoLoss::Intensity),
    };
    Renderer { lattice: Lattice { n: params.grid, aabb }, shift, scale: params.scale, step: 0.5 * mean_voxel, loss }
}

/// The rays training draws from: those of `per_view` that meet the box (TensoRF's filtering).
pub fn ray_pool(per_view: &[Vec<Ray>], aabb: &Aabb) -> Vec<Ray> {
    per_view.iter().flatten().copied().filter(|r| aabb.intersect(r.origin, r.dir).is_some()).collect()
}

/// The seeded randomness of a fit, in the order it is drawn: the initial factors, then per
/// iteration a batch (a seeded permutation of the pool, reshuffled each epoch) with one jitter
/// offset per ray. Both backends draw from it, so they train on the same batches.
pub struct Schedule {
    rng: ChaCha8Rng,
    order: Vec<usize>,
    cursor: usize,
    drawn: Vec<(usize, f64)>,
    /// Scratch for putting a batch in pool order: a bit per pool ray, and each drawn ray's
    /// offset by pool index.
    in_batch: Vec<u64>,
    offset_of: Vec<f64>,
}

impl Schedule {
    /// The initial field of `params` and the batch schedule over a pool of `pool_len` rays.
    pub fn start(params: &TrainParams, pool_len: usize) -> (VmField<f32>, Schedule) {
        let mut rng = ChaCha8Rng::seed_from_u64(params.vm.seed);
        let field = VmField::random(params.grid, params.vm.rank, params.vm.init_scale, rng.gen());
        (field, Schedule::over(rng, pool_len, params.vm.batch_rays))
    }

    /// The batches of a pool of `pool_len` rays drawn from `rng`.
    fn over(rng: ChaCha8Rng, pool_len: usize, batch_rays: usize) -> Schedule {
        Schedule {
            rng,
            order: (0..pool_len).collect(),
            cursor: pool_len, // reshuffle on first use
            drawn: Vec::with_capacity(batch_rays),
            in_batch: vec![0; pool_len.div_ceil(64)],
            offset_of: vec![0.0; pool_len],
        }
    }

    /// The next batch: (pool index, offset in [0, step)) per ray, in pool order — neighbouring
    /// rays share lattice cells, so tracing them in that order hits the cache. The drawn set
    /// and its offsets do not depend on the sort.
    pub fn next_batch(&mut self, batch_rays: usize, step: f64) -> &[(usize, f64)] {
        self.drawn.clear();
        // A batch that runs into the next epoch's permutation may hold a ray twice.
        let mut may_repeat = false;
        while self.drawn.len() < batch_rays.min(self.order.len()) {
            if self.cursor == self.order.len() {
                self.order.shuffle(&mut self.rng);
                self.cursor = 0;
                may_repeat |= !self.drawn.is_empty();
            }
            self.drawn.push((self.order[self.cursor], self.rng.gen::<f64>() * step));
            self.cursor += 1;
        }
        if may_repeat {
            self.drawn.sort_unstable_by_key(|&(i, _)| i);
        } else {
            self.sort_distinct();
        }
        &self.drawn
    }

    /// Puts `drawn`, whose pool indices are distinct, in pool order, as sorting it would: its
    /// rays are marked in a bitmap of the pool, which is then read in order. (Sorting 2048
    /// random indices took 40 µs a batch, this 20 µs: ≈ 0.5 % of a step, as the draw shares a
    /// core with Adam.)
    fn sort_distinct(&mut self) {
        for &(i, offset) in &self.drawn {
            self.in_batch[i / 64] |= 1 << (i % 64);
            self.offset_of[i] = offset;
        }
        self.drawn.clear();
        for (w, word) in self.in_batch.iter_mut().enumerate() {
            // Reading a word clears it for the next batch.
            let mut bits = std::mem::take(word);
            while bits != 0 {
                let i = 64 * w + bits.trailing_zeros() as usize;
                self.drawn.push((i, self.offset_of[i]));
                bits &= bits - 1;
            }
        }
    }

    /// The next batch as rays of `pool` into `batch` and their offsets into `offsets` (both
    /// overwritten).
    pub fn next_rays(
        &mut self,
        pool: &[Ray],
        batch_rays: usize,
        step: f64,
        batch: &mut Vec<Ray>,
        offsets: &mut Vec<f64>,
    ) {
        let drawn = self.next_batch(batch_rays, step);
        batch.clear();
        offsets.clear();
        batch.extend(drawn.iter().map(|&(i, _)| pool[i]));
        offsets.extend(drawn.iter().map(|&(_, o)| o));
    }
}

/// The loss terms of one iteration, each before its weight.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Terms {
    /// The batch MSE (the full-view MSE at iteration 0).
    pub photo: f64,
    pub l1: f64,
    pub tv: f64,
    pub tv3d: f64,
}

impl Terms {
    /// The weighted sum: the loss.
    pub fn loss(&self, params: &TrainParams) -> f64 {
        self.photo + params.vm.lambda_l1 * self.l1 + params.vm.lambda_tv * self.tv + params.vm.lambda_tv3d * self.tv3d
    }
}

/// One iteration's loss terms and the gradient of the loss (before the optimiser).
pub struct Step {
    pub grad: VmField<f32>,
    pub terms: Terms,
}

/// The buffers of one CPU step, kept across iterations: allocating the megabyte-sized dense
/// field and its gradient every step made the allocator return them to the OS and fault them
/// in again (about 670 page faults per iteration). Both are read and written at random, so
/// they live on huge pages.
pub struct StepBuffers {
    dense: HugePageBuffer<f32>,
    grad_dense: HugePageBuffer<f32>,
    /// The factor gradient of the last [`gradient`].
    pub grad: VmField<f32>,
}

impl StepBuffers {
    pub fn new(n: usize, rank: usize) -> StepBuffers {
        let dense = || HugePageBuffer::filled(n * n * n, 0f32);
        StepBuffers { dense: dense(), grad_dense: dense(), grad: VmField::zeros(n, rank) }
    }
}

/// One iteration's batch on the CPU: the rays and their jitter offsets, traced through
/// `field` (masked by `mask`) with `renderer`; `logged` when the iteration writes a log row.
#[derive(Clone, Copy)]
pub struct BatchStep<'a> {
    pub renderer: &'a Renderer,
    pub field: &'a VmField<f32>,
    pub mask: Option<&'a AlphaMask>,
    pub rays: &'a [Ray],
    pub offsets: &'a [f64],
    pub logged: bool,
}

/// The CPU's gradient of one iteration into `buffers.grad`: compose, render and scatter,
/// 3-D TV, contract, regularisers. Returns the loss terms; the 3-D TV's value is computed
/// when it is trained or `logged` (else 0).
pub fn gradient(params: &TrainParams, step: BatchStep, buffers: &mut StepBuffers) -> Terms {
    let mut terms = photometric_gradient(params, step, buffers);
    (terms.l1, terms.tv) =
        regularize::l1_and_tv(step.field, Some(params.vm.lambda_l1 as f32), tv_weight(params), &mut buffers.grad);
    terms
}

/// [`gradient`] without the factors' regularisers (L1, TV), which [`regularize_and_update`]
/// adds; their terms are left 0.
fn photometric_gradient(params: &TrainParams, step: BatchStep, buffers: &mut StepBuffers) -> Terms {
    let BatchStep { renderer, field, mask, rays, offsets, logged } = step;
    let StepBuffers { dense, grad_dense, grad } = buffers;
    field.compose_into(dense);
    // The contraction's transposes of the factors, made beside the tracing: they fill the
    // workers' idle moments there instead of taking a parallel pass of their own.
    let (result, prepared) =
        rayon::join(|| renderer.batch(dense, mask, rays, offsets, Some(grad_dense)), || field.prepare_contraction());
    // The 3-D TV acts on F itself: its gradient joins dL/dF before the contraction.
    let tv3d = if params.vm.lambda_tv3d > 0.0 {
        regularize::tv_dense(dense, field.n, params.vm.lambda_tv3d as f32, grad_dense)
    } else if logged {
        tv_dense_value(dense, field.n)
    } else {
        0.0
    };
    field.contract_prepared(grad_dense, grad, prepared);
    Terms { photo: result.loss, l1: 0.0, tv: 0.0, tv3d }
}

/// The planes' TV norm and weight.
fn tv_weight(params: &TrainParams) -> Option<(TvNorm, f32)> {
    Some((params.vm.tv_norm, params.vm.lambda_tv as f32))
}

/// Adds the L1 and TV gradients to `grad` and updates `field` by Adam, in one parallel pass
/// of one task per factor component: the component, its gradient and moments stay in cache
/// from the regularisers to the update. The result is that of `l1_and_tv` then
/// `Adam::update`, bit for bit (both work entry by entry within a component). Returns the
/// learning rate and, when `logged`, the unweighted (L1, TV) of `field` before the update
/// (else (0, 0): the sums are left out, the update is the same).
pub fn regularize_and_update(
    params: &TrainParams,
    field: &mut VmField<f32>,
    grad: &mut VmField<f32>,
    adam: &mut Adam<f32>,
    logged: bool,
) -> (f64, (f64, f64)) {
    let penalties = Penalties::new(field, Some(params.vm.lambda_l1 as f32), tv_weight(params));
    let penalties = if logged { penalties } else { penalties.gradient_only() };
    let (lr, update, m, v) = adam.begin_update();
    let tasks: Vec<_> = field
        .components_mut()
        .zip(grad.components_mut())
        .zip(m.components_mut().zip(v.components_mut()))
        .map(|(((factor, x), (_, g)), ((_, m), (_, v)))| (factor, x, g, m, v))
        .collect();
    let partials: Vec<(f32, f32)> = tasks
        .into_par_iter()
        .map(|(factor, x, g, m, v)| {
            with_avx2(
                #[inline(always)]
                || {
                    let sums = penalties.add_gradient(factor, &*x, g);
                    update.apply(x, g, m, v);
                    sums
                },
            )
        })
        .collect();
    (lr, penalties.values(field, &partials))
}

/// The unweighted loss terms of `field` with `photo` as the photometric term (the initial row).
pub fn terms_of(params: &TrainParams, field: &VmField<f32>, photo: f64) -> Terms {
    let mut scratch = VmField::zeros(field.n, field.rank);
    Terms {
        photo,
        l1: regularize::l1(field, 0.0, &mut scratch),
        tv: regularize::tv(field, params.vm.tv_norm, 0.0, &mut scratch),
        tv3d: tv_dense_value(&field.compose(), field.n),
    }
}

/// The 3-D TV of a composed F, unweighted.
pub fn tv_dense_value(dense: &[f32], n: usize) -> f64 {
    regularize::tv_dense(dense, n, 0.0, &mut vec![0.0; dense.len()])
}

/// The log row after `iteration` iterations; `view_mse` is the full views' MSE.
pub fn log_row(
    params: &TrainParams,
    iteration: usize,
    terms: Terms,
    view_mse: &[f64],
    lr: f64,
    seconds: f64,
) -> LogRow {
    LogRow {
        iteration,
        loss: terms.loss(params),
        photo: terms.photo,
        l1: terms.l1,
        tv: terms.tv,
        tv3d: terms.tv3d,
        psnr_db: view_mse.iter().map(|&m| psnr_db(m)).collect(),
        lr,
        seconds,
    }
}

/// Fits a field to `views` on the CPU. `on_log` sees every logged row as it is made.
pub fn fit(params: &TrainParams, views: &Views, mut on_log: impl FnMut(&LogRow)) -> Fitted {
    let started = Instant::now();
    let renderer = renderer(params, views.aabb);
    let per_view = views.rays();
    // The batch draw reads 2048 rays at random from megabytes of them: on huge pages.
    let pool = HugePageBuffer::from_slice(&ray_pool(&per_view, &views.aabb));
    let (mut field, mut schedule) = Schedule::start(params, pool.len());
    let mut adam = Adam::new(params.vm.adam(), &field);
    let mut mask: Option<AlphaMask> = None;
    let mut log = Vec::new();
    // Row 0: the initial field, before any update (its "photo" is the full views' loss).
    let (initial_mse, photo) = view_errors(&renderer, &field, None, &per_view);
    let terms = terms_of(params, &field, photo);
    let initial = log_row(params, 0, terms, &initial_mse, params.vm.lr, started.elapsed().as_secs_f64());
    on_log(&initial);
    log.push(initial);
    let (mut batch, mut offsets) = (Vec::with_capacity(params.vm.batch_rays), Vec::with_capacity(params.vm.batch_rays));
    let mut draw = |batch: &mut Vec<Ray>, offsets: &mut Vec<f64>| {
        schedule.next_rays(&pool, params.vm.batch_rays, renderer.step, batch, offsets)
    };
    if params.vm.iterations > 0 {
        draw(&mut batch, &mut offsets);
    }
    let mut buffers = StepBuffers::new(field.n, field.rank);
    let mut step_seconds = Vec::with_capacity(params.vm.iterations);
    for it in 0..params.vm.iterations {
        let logged = params.logs_after(it + 1);
        let step_start = Instant::now();
        let step = BatchStep {
            renderer: &renderer,
            field: &field,
            mask: mask.as_ref(),
            rays: &batch,
            offsets: &offsets,
            logged,
        };
        let mut terms = photometric_gradient(params, step, &mut buffers);
        // The next batch does not depend on the field: it is drawn (on the single-threaded
        // random stream) while the regularisers and Adam update, so neither core waits for it.
        let ((lr, (l1, tv)), ()) = rayon::join(
            || regularize_and_update(params, &mut field, &mut buffers.grad, &mut adam, logged),
            || {
                if it + 1 < params.vm.iterations {
                    draw(&mut batch, &mut offsets);
                }
            },
        );
        (terms.l1, terms.tv) = (l1, tv);
        step_seconds.push(step_start.elapsed().as_secs_f64());
        if params.vm.remasks_after(it + 1) {
            mask = Some(renderer.alpha_mask(&field.compose(), params.vm.alpha_threshold));
        }
        if logged {
            let views_mse = view_mse(&renderer, &field, mask.as_ref(), &per_view);
            let seconds = started.elapsed().as_secs_f64();
            let row = log_row(params, it + 1, terms, &views_mse, lr, seconds);
            on_log(&row);
            log.push(row);
        }
    }
    Fitted { field, log, mask, renderer, step_seconds }
}

/// Mean squared error of each view rendered in full with midpoint samples.
pub fn view_mse(
    renderer: &Renderer,
    field: &VmField<f32>,
    mask: Option<&AlphaMask>,
    per_view: &[Vec<Ray>],
) -> Vec<f64> {
    view_errors(renderer, field, mask, per_view).0
}

/// [`view_mse`], and the renderer's loss averaged over the views.
pub fn view_errors(
    renderer: &Renderer,
    field: &VmField<f32>,
    mask: Option<&AlphaMask>,
    per_view: &[Vec<Ray>],
) -> (Vec<f64>, f64) {
    let dense = field.compose();
    let results: Vec<BatchResult<f32>> = per_view
        .iter()
        .map(|rays| renderer.batch(&dense, mask, rays, &vec![renderer.step / 2.0; rays.len()], None))
        .collect();
    let loss = results.iter().map(|r| r.loss).sum::<f64>() / results.len().max(1) as f64;
    (results.iter().map(|r| r.mse).collect(), loss)
}

/// PSNR (dB) of a mean squared error, peak 1.
pub fn psnr_db(mse: f64) -> f64 {
    10.0 * (1.0 / mse.max(1e-20)).log10()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_come_in_pool_order_as_sorting_puts_them() {
        // Pools whose epochs hold whole batches, and pools where batches run into the next
        // epoch (and may repeat a ray).
        for (pool_len, batch_rays) in [(1200, 300), (1000, 300), (130, 64), (50, 64)] {
            let mut schedule = Schedule::over(ChaCha8Rng::seed_from_u64(5), pool_len, batch_rays);
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let (mut order, mut cursor): (Vec<usize>, usize) = ((0..pool_len).collect(), pool_len);
            for _ in 0..20 {
                let mut expected = Vec::new();
                while expected.len() < batch_rays.min(pool_len) {
                    if cursor == pool_len {
                        order.shuffle(&mut rng);
                        cursor = 0;
                    }
                    expected.push((order[cursor], rng.gen::<f64>() * 0.5));
                    cursor += 1;
                }
                expected.sort_unstable_by_key(|&(i, _)| i);
                let drawn = schedule.next_batch(batch_rays, 0.5);
                assert_eq!(drawn.len(), expected.len());
                for (a, b) in drawn.iter().zip(&expected) {
                    assert_eq!((a.0, a.1.to_bits()), (b.0, b.1.to_bits()), "pool {pool_len}, batch {batch_rays}");
                }
            }
        }
    }
}
