//! The training loop on the device (mirrors `train::fit::fit`): the factors, Adam's moments,
//! the dense field, its gradient and the alpha mask live on the GPU for the whole fit. Per
//! iteration the host draws the batch from the same seeded [`Schedule`] as the CPU, uploads
//! its rays and Adam's step scalars, and submits compose → render + scatter → dF to f32 →
//! 3-D TV → contract → L1 → TV → Adam; nothing comes back except at logged iterations (the batch
//! predictions, the three full views and the regularisers' partial sums) and at the end
//! (factors, mask).

use super::adam::{self, Adam};
use super::alpha_mask::{self, AlphaMask as AlphaMaskKernel};
use super::buffers;
use super::compose::{self, Compose};
use super::contract_lines;
use super::contract_planes;
use super::device::InFlight;
use super::grad_from_fixed::{self, GradFromFixed};
use super::kernel::{Bound, ItemKernel};
use super::l1;
use super::render::{self, RaySamples, Render};
use super::tv;
use super::tv_dense;
use super::Gpu;
use crate::train::adam::AdamParams;
use crate::train::field::VmField;
use crate::train::fit::{self as cpu, log_row, ray_pool, renderer, Fitted, LogRow, Schedule, Step, Views};
use crate::train::params::TrainParams;
use crate::train::params::VmParams;
use crate::train::render::{AlphaMask, PhotoLoss, Ray, Renderer};
use std::time::Instant;

/// Submitted iterations the host may run ahead of the device before it waits for the oldest
/// (bounds the staging memory of the per-iteration uploads; no data comes back).
const IN_FLIGHT: usize = 8;

/// Every training kernel, compiled once per device ([`Gpu::train_kernels`]).
pub struct Kernels {
    compose: Compose,
    render: Render,
    grad_from_fixed: GradFromFixed,
    contract_planes: ItemKernel,
    contract_lines: ItemKernel,
    l1: ItemKernel,
    tv: ItemKernel,
    tv_dense: ItemKernel,
    adam: Adam,
    alpha_mask: AlphaMaskKernel,
}

impl Kernels {
    pub fn new(gpu: &Gpu) -> anyhow::Result<Kernels> {
        Ok(Kernels {
            compose: Compose::new(gpu)?,
            render: Render::new(gpu)?,
            grad_from_fixed: GradFromFixed::new(gpu)?,
            contract_planes: contract_planes::kernel(gpu)?,
            contract_lines: contract_lines::kernel(gpu)?,
            l1: l1::kernel(gpu)?,
            tv: tv::kernel(gpu)?,
            tv_dense: tv_dense::kernel(gpu)?,
            adam: Adam::new(gpu)?,
            alpha_mask: AlphaMaskKernel::new(gpu)?,
        })
    }
}

/// Fails, naming the option, when `params` asks for something the shaders do not compute (since
/// the dense model gained its shaders, nothing).
///
/// The destructuring lists every `[train]` and `[train.vm]` key on purpose: a new option does
/// not compile here until someone decides whether the GPU backend covers it (and, if not,
/// refuses it below) — the GPU must never silently train a different loss than the CPU would.
/// The dense fit's keys are all its solver's, which runs on either backend.
pub fn check_supported(params: &TrainParams) -> anyhow::Result<()> {
    let TrainParams { model: _, grid: _, scale: _, log_every: _, backend: _, threads: _, dense_tv: _, vm } = params;
    let VmParams {
        rank: _,
        shift: _,
        iterations: _,
        batch_rays: _,
        lr: _,
        lr_decay_ratio: _,
        lambda_l1: _,
        lambda_tv: _,
        tv_norm: _,
        lambda_tv3d: _,
        loss: _,
        init_scale: _,
        alpha_mask_iterations: _,
        alpha_threshold: _,
        seed: _,
    } = vm;
    Ok(())
}

/// Fits a field to `views` on `gpu`: the same batches, jitter, schedule and log as
/// `train::fit::fit`, in f32 on the device. `on_log` sees every logged row as it is made.
pub fn fit(gpu: &Gpu, params: &TrainParams, views: &Views, mut on_log: impl FnMut(&LogRow)) -> anyhow::Result<Fitted> {
    check_supported(params)?;
    if !params.model.is_vm() {
        anyhow::bail!("gpu::fit::fit fits the VM factors; model = \"dense_tv\" fits through gpu::dense_fit::fit");
    }
    let started = Instant::now();
    let renderer = renderer(params, views.aabb);
    let per_view = views.rays();
    let pool = ray_pool(&per_view, &views.aabb);
    let (field, mut schedule) = Schedule::start(params, pool.len());
    let batch_len = params.vm.batch_rays.min(pool.len());
    let mut device = DeviceFit::new(gpu, params, &renderer, &field, batch_len, &per_view)?;
    let mut log = Vec::new();
    // Row 0: the initial field (its "photo" is the full-view MSE), regularisers at weight 0.
    let initial = device.initial_terms()?;
    let photo = initial.view_loss;
    let seconds = started.elapsed().as_secs_f64();
    let terms = cpu::Terms { photo, l1: initial.l1, tv: initial.tv, tv3d: initial.tv3d };
    let row = log_row(params, 0, terms, &initial.view_mse, params.vm.lr, seconds);
    on_log(&row);
    log.push(row);
    let mut batch = Vec::with_capacity(batch_len);
    let mut offsets = Vec::with_capacity(batch_len);
    for it in 0..params.vm.iterations {
        schedule.next_rays(&pool, params.vm.batch_rays, renderer.step, &mut batch, &mut offsets);
        let lr = device.iterate(&batch, &offsets)?;
        if params.vm.remasks_after(it + 1) {
            device.remask()?;
        }
        if params.logs_after(it + 1) {
            let terms = device.logged_terms()?;
            let seconds = started.elapsed().as_secs_f64();
            let row = log_row(params, it + 1, terms.loss_terms(), &terms.view_mse, lr, seconds);
            on_log(&row);
            log.push(row);
        }
    }
    Ok(Fitted { field: device.field()?, log, mask: device.mask()?, renderer, step_seconds: Vec::new() })
}

/// What a logged row needs from the device.
pub struct Terms {
    /// The photometric loss of the last batch (its predictions against its targets).
    pub batch_loss: f64,
    /// Before their λ: the regularisers of the field the last gradient was taken at.
    pub l1: f64,
    pub tv: f64,
    pub tv3d: f64,
    /// Full-view MSE of each view, midpoint samples, the current field and mask.
    pub view_mse: Vec<f64>,
    /// The photometric loss of the same, averaged over the views.
    pub view_loss: f64,
}

impl Terms {
    /// The row's loss terms (the batch's as the photometric one).
    pub fn loss_terms(&self) -> cpu::Terms {
        cpu::Terms { photo: self.batch_loss, l1: self.l1, tv: self.tv, tv3d: self.tv3d }
    }
}

/// A field being trained on the device: its buffers and the kernels bound to them.
pub struct DeviceFit<'g> {
    gpu: &'g Gpu,
    kernels: std::sync::Arc<Kernels>,
    renderer: Renderer,
    adam_params: AdamParams,
    n: usize,
    rank: usize,
    entries: usize,
    updates: usize,
    masked: bool,
    factors: wgpu::Buffer,
    grad: wgpu::Buffer,
    dense_grad_fixed: wgpu::Buffer,
    mask_nodes: wgpu::Buffer,
    batch_rays: wgpu::Buffer,
    batch_predicted: wgpu::Buffer,
    batch_targets: Vec<f64>,
    eval_predicted: wgpu::Buffer,
    eval_targets: Vec<Vec<f64>>,
    l1_partials: (wgpu::Buffer, usize),
    tv_partials: (wgpu::Buffer, usize),
    tv_dense_partials: (wgpu::Buffer, usize),
    l1_uniforms: (wgpu::Buffer, l1::Uniforms),
    tv_uniforms: (wgpu::Buffer, tv::Uniforms),
    tv_dense_uniforms: (wgpu::Buffer, tv_dense::Uniforms),
    render_batch_uniforms: (wgpu::Buffer, render::Uniforms),
    render_eval_uniforms: (wgpu::Buffer, render::Uniforms),
    adam_uniforms: wgpu::Buffer,
    compose_b: Bound,
    render_batch_b: Bound,
    render_eval_b: Bound,
    grad_from_fixed_b: Bound,
    planes_b: Bound,
    lines_b: Bound,
    l1_b: Bound,
    tv_b: Bound,
    tv_dense_b: Bound,
    adam_b: Bound,
    alpha_b: Bound,
    in_flight: InFlight,
}

impl<'g> DeviceFit<'g> {
    /// Uploads `field` (Adam's moments zero, no mask yet), room for batches of `batch_len`
    /// rays, and every ray of `per_view` for the logged full-view evaluations.
    pub fn new(
        gpu: &'g Gpu,
        params: &TrainParams,
        renderer: &Renderer,
        field: &VmField<f32>,
        batch_len: usize,
        per_view: &[Vec<Ray>],
    ) -> anyhow::Result<DeviceFit<'g>> {
        let most = grad_from_fixed::max_batch_rays(renderer);
        if batch_len > most {
            anyhow::bail!(
                "[train.vm] batch_rays = {} gives batches of {batch_len} rays, more than the GPU backend sums \
                 exactly ({most} rays at this lattice's sample step: a node's integer sum takes at most 65,536 \
                 addends a batch); set batch_rays to {most} or fewer, or [train] backend = \"cpu\"",
                params.vm.batch_rays
            );
        }
        let kernels = gpu.compiled(Kernels::new)?;
        let (n, rank) = (field.n, field.rank);
        let nodes = n * n * n;
        let flat: Vec<f32> = field.params().flatten().copied().collect();
        let entries = flat.len();
        let bytes = |count: usize| 4 * count as u64;
        let factors = buffers::storage(gpu, "factors", &flat)?;
        let grad = buffers::zeroed(gpu, "factor gradient", bytes(entries))?;
        let moments =
            [buffers::zeroed(gpu, "adam m", bytes(entries))?, buffers::zeroed(gpu, "adam v", bytes(entries))?];
        let dense = buffers::zeroed(gpu, "dense field (lattice of [train] grid³ nodes)", bytes(nodes))?;
        let dense_grad = buffers::zeroed(gpu, "dense gradient", bytes(nodes))?;
        let dense_grad_fixed =
            buffers::zeroed(gpu, "dense gradient (fixed point)", grad_from_fixed::fixed_bytes(nodes))?;
        let mask_nodes = buffers::zeroed(gpu, "alpha mask", bytes(nodes))?;
        let batch_rays = buffers::zeroed(gpu, "batch rays", (std::mem::size_of::<RaySamples>() * batch_len) as u64)?;
        let batch_predicted = buffers::zeroed(gpu, "batch predictions", bytes(batch_len))?;
        let eval: Vec<RaySamples> =
            per_view.iter().flatten().map(|r| RaySamples::new(renderer, r, renderer.step / 2.0)).collect();
        let eval_rays = buffers::storage(gpu, "view rays", &eval)?;
        let eval_predicted = buffers::zeroed(gpu, "view predictions", bytes(eval.len()))?;
        let eval_targets = per_view.iter().map(|v| v.iter().map(|r| r.target).collect()).collect();

        let k = &kernels;
        let compose_shape = compose::Shape { n: n as u32, rank: rank as u32, nodes: nodes as u32, _pad: 0 };
        let compose_u = buffers::uniform(gpu, "compose shape", &compose_shape);
        let compose_b = k.compose.bind(gpu, &compose_u, &factors, &dense, nodes as u32)?;
        let render_batch = render::Uniforms::new(renderer, batch_len, true, false);
        let render_eval = render::Uniforms::new(renderer, eval.len(), false, false);
        let render_batch_u = buffers::uniform(gpu, "render batch", &render_batch);
        let render_eval_u = buffers::uniform(gpu, "render views", &render_eval);
        let r = &k.render;
        let render_batch_b = r.bind(
            gpu,
            &render_batch_u,
            &dense,
            &mask_nodes,
            &batch_rays,
            &batch_predicted,
            &dense_grad_fixed,
            batch_len,
        )?;
        let render_eval_b = r.bind(
            gpu,
            &render_eval_u,
            &dense,
            &mask_nodes,
            &eval_rays,
            &eval_predicted,
            &dense_grad_fixed,
            eval.len(),
        )?;
        let fixed_shape = grad_from_fixed::Shape { nodes: nodes as u32, _pad: [0; 3] };
        let fixed_u = buffers::uniform(gpu, "dense gradient from fixed point", &fixed_shape);
        let grad_from_fixed_b = k.grad_from_fixed.bind(gpu, &fixed_u, &dense_grad_fixed, &dense_grad, nodes)?;
        let planes =
            contract_planes::Shape { n: n as u32, rank: rank as u32, entries: (3 * rank * n * n) as u32, _pad: 0 };
        let planes_u = buffers::uniform(gpu, "contract planes", &planes);
        let planes_b = k.contract_planes.bind(gpu, &planes_u, [&factors, &dense_grad, &grad], planes.entries)?;
        let lines = contract_lines::Shape { n: n as u32, rank: rank as u32, entries: (3 * rank * n) as u32, _pad: 0 };
        let lines_u = buffers::uniform(gpu, "contract lines", &lines);
        let lines_b = k.contract_lines.bind(gpu, &lines_u, [&factors, &dense_grad, &grad], lines.entries)?;
        let l1_values = l1::Uniforms::new(n, rank, params.vm.lambda_l1);
        let l1_u = buffers::uniform(gpu, "l1", &l1_values);
        let l1_count = l1::partials(gpu, l1_values.entries)?;
        let l1_partials = buffers::zeroed(gpu, "l1 partials", bytes(l1_count))?;
        let l1_b = k.l1.bind(gpu, &l1_u, [&factors, &grad, &l1_partials], l1_values.entries)?;
        let tv_values = tv::Uniforms::new(n, rank, params.vm.tv_norm, params.vm.lambda_tv);
        let tv_u = buffers::uniform(gpu, "tv", &tv_values);
        let tv_count = l1::partials(gpu, tv_values.entries)?;
        let tv_partials = buffers::zeroed(gpu, "tv partials", bytes(tv_count))?;
        let tv_b = k.tv.bind(gpu, &tv_u, [&factors, &grad, &tv_partials], tv_values.entries)?;
        let tv_dense_values = tv_dense::Uniforms::new(n, params.vm.lambda_tv3d);
        let tv_dense_u = buffers::uniform(gpu, "tv dense", &tv_dense_values);
        let tv_dense_count = l1::partials(gpu, tv_dense_values.nodes)?;
        let tv_dense_partials = buffers::zeroed(gpu, "tv dense partials", bytes(tv_dense_count))?;
        let tv_dense_b =
            k.tv_dense.bind(gpu, &tv_dense_u, [&dense, &dense_grad, &tv_dense_partials], tv_dense_values.nodes)?;
        let adam_params = params.vm.adam();
        let adam_u = buffers::uniform(gpu, "adam", &adam::Uniforms::new(entries, &adam_params, &adam_params.step(0)));
        let adam_b = k.adam.bind(gpu, &adam_u, &grad, &factors, [&moments[0], &moments[1]], entries)?;
        let alpha_values = alpha_mask::Uniforms::new(renderer, params.vm.alpha_threshold);
        let alpha_u = buffers::uniform(gpu, "alpha mask", &alpha_values);
        let alpha_b = k.alpha_mask.bind(gpu, (&alpha_u, alpha_values), &dense, &mask_nodes)?;
        gpu.check()?;
        Ok(DeviceFit {
            gpu,
            kernels,
            renderer: *renderer,
            adam_params,
            n,
            rank,
            entries,
            updates: 0,
            masked: false,
            factors,
            grad,
            dense_grad_fixed,
            mask_nodes,
            batch_rays,
            batch_predicted,
            batch_targets: Vec::new(),
            eval_predicted,
            eval_targets,
            l1_partials: (l1_partials, l1_count),
            tv_partials: (tv_partials, tv_count),
            tv_dense_partials: (tv_dense_partials, tv_dense_count),
            l1_uniforms: (l1_u, l1_values),
            tv_uniforms: (tv_u, tv_values),
            tv_dense_uniforms: (tv_dense_u, tv_dense_values),
            render_batch_uniforms: (render_batch_u, render_batch),
            render_eval_uniforms: (render_eval_u, render_eval),
            adam_uniforms: adam_u,
            compose_b,
            render_batch_b,
            render_eval_b,
            grad_from_fixed_b,
            planes_b,
            lines_b,
            l1_b,
            tv_b,
            tv_dense_b,
            adam_b,
            alpha_b,
            in_flight: InFlight::new(IN_FLIGHT),
        })
    }

    fn encoder(&self) -> wgpu::CommandEncoder {
        self.gpu.device.create_command_encoder(&Default::default())
    }

    fn submit(&mut self, encoder: wgpu::CommandEncoder) -> anyhow::Result<()> {
        self.in_flight.submit(self.gpu, encoder)
    }

    /// Uploads a batch: its rays with their jitter, walked as the CPU walks them.
    fn upload_batch(&mut self, rays: &[Ray], offsets: &[f64]) -> anyhow::Result<()> {
        let capacity = self.render_batch_uniforms.1.rays as usize;
        if rays.len() != capacity {
            anyhow::bail!("a batch of {} rays on a device fit made for {capacity}", rays.len());
        }
        let samples: Vec<RaySamples> =
            rays.iter().zip(offsets).map(|(r, &o)| RaySamples::new(&self.renderer, r, o)).collect();
        if !samples.is_empty() {
            self.gpu.queue.write_buffer(&self.batch_rays, 0, bytemuck::cast_slice(&samples));
        }
        self.batch_targets = rays.iter().map(|r| r.target).collect();
        Ok(())
    }

    /// compose → clear the integer sums → render + scatter → dF to f32 → 3-D TV → contract →
    /// L1 → TV: the loss gradient in `grad`. (The 3-D TV runs at weight 0 too: its value is
    /// logged, as on the CPU.)
    fn record_gradient(&self, encoder: &mut wgpu::CommandEncoder) {
        let k = &self.kernels;
        k.compose.record(encoder, &self.compose_b);
        self.record_scatter(encoder);
        k.tv_dense.record(encoder, &self.tv_dense_b);
        k.contract_planes.record(encoder, &self.planes_b);
        k.contract_lines.record(encoder, &self.lines_b);
        k.l1.record(encoder, &self.l1_b);
        k.tv.record(encoder, &self.tv_b);
    }

    /// The batch's `dL/dF` in `dense_grad`: cleared fixed-point sums, the render's scatter
    /// into them, and their conversion to f32.
    fn record_scatter(&self, encoder: &mut wgpu::CommandEncoder) {
        let k = &self.kernels;
        encoder.clear_buffer(&self.dense_grad_fixed, 0, None);
        k.render.record(encoder, &self.render_batch_b);
        k.grad_from_fixed.record(encoder, &self.grad_from_fixed_b);
    }

    /// One training iteration on `rays` with jitter `offsets` (submitted, not waited for);
    /// returns the learning rate it used.
    pub fn iterate(&mut self, rays: &[Ray], offsets: &[f64]) -> anyhow::Result<f64> {
        self.upload_batch(rays, offsets)?;
        let step = self.adam_params.step(self.updates);
        self.updates += 1;
        let uniforms = adam::Uniforms::new(self.entries, &self.adam_params, &step);
        self.gpu.queue.write_buffer(&self.adam_uniforms, 0, bytemuck::bytes_of(&uniforms));
        let mut encoder = self.encoder();
        self.record_gradient(&mut encoder);
        self.kernels.adam.record(&mut encoder, &self.adam_b);
        self.submit(encoder)?;
        Ok(step.lr)
    }

    /// One iteration's gradient and loss terms on `rays`, read back, without updating: what
    /// the agreement tests compare with `train::fit::gradient`.
    pub fn gradient(&mut self, rays: &[Ray], offsets: &[f64]) -> anyhow::Result<Step> {
        self.upload_batch(rays, offsets)?;
        let mut encoder = self.encoder();
        self.record_gradient(&mut encoder);
        self.submit(encoder)?;
        let [grad, predicted, l1, tv, tv3d] = self.read([
            (&self.grad, self.entries),
            (&self.batch_predicted, self.batch_targets.len()),
            (&self.l1_partials.0, self.l1_partials.1),
            (&self.tv_partials.0, self.tv_partials.1),
            (&self.tv_dense_partials.0, self.tv_dense_partials.1),
        ])?;
        let mut field = VmField::zeros(self.n, self.rank);
        let mut rest = grad.as_slice();
        for factor in field.params_mut() {
            let (head, tail) = rest.split_at(factor.len());
            factor.copy_from_slice(head);
            rest = tail;
        }
        let terms = cpu::Terms {
            photo: mean_error(self.renderer.loss, &predicted, &self.batch_targets),
            l1: sum(&l1),
            tv: sum(&tv),
            tv3d: sum(&tv3d),
        };
        Ok(Step { grad: field, terms })
    }

    /// Median wall time (ms) of each kernel of one iteration on `rays`, each submitted alone
    /// and waited for `repeats` times (includes the submission overhead: what a real GPU pays
    /// per kernel too). The factors are left as they were, bar Adam's moments.
    pub fn profile(
        &mut self,
        rays: &[Ray],
        offsets: &[f64],
        repeats: usize,
    ) -> anyhow::Result<Vec<(&'static str, f64)>> {
        self.upload_batch(rays, offsets)?;
        let k = self.kernels.clone();
        type Record<'a> = &'a dyn Fn(&mut wgpu::CommandEncoder);
        let rows: [(&'static str, Record); 10] = [
            ("compose", &|e| k.compose.record(e, &self.compose_b)),
            ("render + scatter", &|e| self.record_scatter(e)),
            ("contract planes", &|e| k.contract_planes.record(e, &self.planes_b)),
            ("contract lines", &|e| k.contract_lines.record(e, &self.lines_b)),
            ("L1", &|e| k.l1.record(e, &self.l1_b)),
            ("TV", &|e| k.tv.record(e, &self.tv_b)),
            ("3-D TV", &|e| k.tv_dense.record(e, &self.tv_dense_b)),
            ("alpha mask", &|e| k.alpha_mask.record(e, &self.alpha_b)),
            ("render 3 views", &|e| k.render.record(e, &self.render_eval_b)),
            ("whole iteration", &|e| {
                self.record_gradient(e);
            }),
        ];
        let mut out = Vec::new();
        for (name, record) in rows {
            let mut ms = Vec::with_capacity(repeats);
            for _ in 0..repeats.max(1) {
                let t = Instant::now();
                let mut encoder = self.encoder();
                record(&mut encoder);
                self.gpu.queue.submit([encoder.finish()]);
                self.gpu.wait()?;
                ms.push(t.elapsed().as_secs_f64() * 1e3);
            }
            ms.sort_by(f64::total_cmp);
            out.push((name, ms[ms.len() / 2]));
        }
        Ok(out)
    }

    /// Computes the alpha mask from the current factors; later samples need a kept node.
    pub fn remask(&mut self) -> anyhow::Result<()> {
        let mut encoder = self.encoder();
        self.kernels.compose.record(&mut encoder, &self.compose_b);
        self.kernels.alpha_mask.record(&mut encoder, &self.alpha_b);
        if !self.masked {
            self.masked = true;
            for (buffer, uniforms) in [&mut self.render_batch_uniforms, &mut self.render_eval_uniforms] {
                uniforms.masked = 1;
                self.gpu.queue.write_buffer(buffer, 0, bytemuck::bytes_of(uniforms));
            }
        }
        self.submit(encoder)
    }

    /// The terms of the initial row: the full views and the regularisers (at weight 0: the
    /// gradient they add goes to a scratch that the first iteration overwrites).
    fn initial_terms(&mut self) -> anyhow::Result<Terms> {
        let (mut l1, mut tv, mut tv3d) = (self.l1_uniforms.1, self.tv_uniforms.1, self.tv_dense_uniforms.1);
        (l1.weight, tv.scale, tv3d.scale) = (0.0, 0.0, 0.0);
        self.gpu.queue.write_buffer(&self.l1_uniforms.0, 0, bytemuck::bytes_of(&l1));
        self.gpu.queue.write_buffer(&self.tv_uniforms.0, 0, bytemuck::bytes_of(&tv));
        self.gpu.queue.write_buffer(&self.tv_dense_uniforms.0, 0, bytemuck::bytes_of(&tv3d));
        let mut encoder = self.encoder();
        self.kernels.l1.record(&mut encoder, &self.l1_b);
        self.kernels.tv.record(&mut encoder, &self.tv_b);
        self.kernels.compose.record(&mut encoder, &self.compose_b);
        self.kernels.tv_dense.record(&mut encoder, &self.tv_dense_b);
        self.submit(encoder)?;
        let terms = self.logged_terms()?;
        let (l1, tv, tv3d) = (self.l1_uniforms.1, self.tv_uniforms.1, self.tv_dense_uniforms.1);
        self.gpu.queue.write_buffer(&self.l1_uniforms.0, 0, bytemuck::bytes_of(&l1));
        self.gpu.queue.write_buffer(&self.tv_uniforms.0, 0, bytemuck::bytes_of(&tv));
        self.gpu.queue.write_buffer(&self.tv_dense_uniforms.0, 0, bytemuck::bytes_of(&tv3d));
        Ok(terms)
    }

    /// Renders the three views with the current field and mask, and reads them back with the
    /// last batch's predictions and the regularisers' partial sums.
    pub fn logged_terms(&mut self) -> anyhow::Result<Terms> {
        let mut encoder = self.encoder();
        self.kernels.compose.record(&mut encoder, &self.compose_b);
        self.kernels.render.record(&mut encoder, &self.render_eval_b);
        self.submit(encoder)?;
        let eval_len = self.render_eval_uniforms.1.rays as usize;
        let [predicted, views, l1, tv, tv3d] = self.read([
            (&self.batch_predicted, self.batch_targets.len()),
            (&self.eval_predicted, eval_len),
            (&self.l1_partials.0, self.l1_partials.1),
            (&self.tv_partials.0, self.tv_partials.1),
            (&self.tv_dense_partials.0, self.tv_dense_partials.1),
        ])?;
        let mut view_mse = Vec::with_capacity(self.eval_targets.len());
        let mut view_loss = 0.0;
        let mut rest = views.as_slice();
        for targets in &self.eval_targets {
            let (head, tail) = rest.split_at(targets.len());
            view_mse.push(mean_error(PhotoLoss::Intensity, head, targets));
            view_loss += mean_error(self.renderer.loss, head, targets) / self.eval_targets.len() as f64;
            rest = tail;
        }
        Ok(Terms {
            batch_loss: mean_error(self.renderer.loss, &predicted, &self.batch_targets),
            l1: sum(&l1),
            tv: sum(&tv),
            tv3d: sum(&tv3d),
            view_mse,
            view_loss,
        })
    }

    /// Waits for everything submitted, then copies `sources` back.
    fn read<const K: usize>(&self, sources: [(&wgpu::Buffer, usize); K]) -> anyhow::Result<[Vec<f32>; K]> {
        let out = buffers::read::<f32>(self.gpu, &sources)?;
        Ok(out.try_into().expect("one vector per source"))
    }

    /// The current factors.
    pub fn field(&mut self) -> anyhow::Result<VmField<f32>> {
        let [flat] = self.read([(&self.factors, self.entries)])?;
        let mut field = VmField::zeros(self.n, self.rank);
        let mut rest = flat.as_slice();
        for factor in field.params_mut() {
            let (head, tail) = rest.split_at(factor.len());
            factor.copy_from_slice(head);
            rest = tail;
        }
        Ok(field)
    }

    /// The alpha mask, once computed.
    pub fn mask(&mut self) -> anyhow::Result<Option<AlphaMask>> {
        if !self.masked {
            return Ok(None);
        }
        let nodes = self.n * self.n * self.n;
        let flags: Vec<u32> = buffers::read::<u32>(self.gpu, &[(&self.mask_nodes, nodes)])?.remove(0);
        Ok(Some(AlphaMask::from_nodes(flags.iter().map(|&k| k != 0).collect(), self.n)))
    }
}

/// The mean of `kind`'s error of f32 predictions against f64 targets, summed in f64 (as the CPU).
fn mean_error(kind: PhotoLoss, predicted: &[f32], targets: &[f64]) -> f64 {
    let sum: f64 = predicted.iter().zip(targets).map(|(&p, &t)| kind.error(f64::from(p), t)).sum();
    sum / targets.len() as f64
}

/// The regularisers' workgroup partials, summed in f64.
fn sum(partials: &[f32]) -> f64 {
    partials.iter().map(|&p| f64::from(p)).sum()
}
