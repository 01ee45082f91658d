//! The dense fit's FISTA loop on the device (mirrors `train::dense_tv::CpuFista`): `A`, `Aᵀ`,
//! σ, the look-ahead point, the residual, the back-projection and the TV's normalised
//! differences live on the GPU for a whole solve. Per step the host writes the momentum and
//! submits project → back-project → TV direction → step; σ comes back only at logged steps
//! and at the end of the solve. Everything else — building `A`, the step `1/L` and every log
//! row — is `train::dense_tv`'s own, in f64 on the host.

use super::buffers;
use super::csr_times::{CsrTimes, DeviceCsr};
use super::device::InFlight;
use super::fista_step::{self, FistaStep};
use super::kernel::Bound;
use super::tv_direction::TvDirection;
use super::Gpu;
use crate::train::dense_tv::{self, next_momentum, DenseFitted, DenseProblem, FistaSolver};
use crate::train::fit::{LogRow, Views};
use crate::train::params::TrainParams;
use crate::train::render::Renderer;
use std::sync::Arc;

/// Steps the host may submit ahead of the device before it waits for the oldest.
const IN_FLIGHT: usize = 8;

/// The dense fit's kernels, compiled once per device ([`Gpu::dense_kernels`]).
pub struct DenseKernels {
    csr_times: CsrTimes,
    tv_direction: TvDirection,
    fista_step: FistaStep,
}

impl DenseKernels {
    pub fn new(gpu: &Gpu) -> anyhow::Result<DenseKernels> {
        Ok(DenseKernels {
            csr_times: CsrTimes::new(gpu)?,
            tv_direction: TvDirection::new(gpu)?,
            fista_step: FistaStep::new(gpu)?,
        })
    }
}

/// Fits σ to `views` with the FISTA steps on `gpu` (`train::dense_tv::fit_with`).
pub fn fit(
    gpu: &Arc<Gpu>,
    params: &TrainParams,
    views: &Views,
    renderer: &Renderer,
    on_log: impl FnMut(&LogRow),
) -> anyhow::Result<DenseFitted> {
    dense_tv::fit_with(params, views, renderer, |problem| DeviceFista::new(gpu.clone(), problem), on_log)
}

/// One problem's buffers and bindings on the device.
pub struct DeviceFista {
    gpu: Arc<Gpu>,
    kernels: Arc<DenseKernels>,
    nodes: usize,
    target: wgpu::Buffer,
    ahead: wgpu::Buffer,
    sigma: wgpu::Buffer,
    step_uniforms: wgpu::Buffer,
    step_values: fista_step::Uniforms,
    /// Project, back-project, TV direction, step.
    passes: [Bound; 4],
    /// The uniform buffers the first three passes bind.
    _pass_uniforms: [wgpu::Buffer; 3],
    in_flight: InFlight,
}

impl DeviceFista {
    /// Uploads `problem`'s matrices and allocates the solve's buffers.
    pub fn new(gpu: Arc<Gpu>, problem: &DenseProblem) -> anyhow::Result<DeviceFista> {
        let kernels = gpu.compiled(DenseKernels::new)?;
        let (n, nodes) = (problem.n, problem.nodes());
        let rays = problem.seen.len();
        let rows = DeviceCsr::upload(&gpu, "the projection A", &problem.projector.rows)?;
        let columns = DeviceCsr::upload(&gpu, "the back-projection Aᵀ", &problem.projector.columns)?;
        let f32s = |count: usize| (count * std::mem::size_of::<f32>()) as u64;
        let target = buffers::zeroed(&gpu, "target depths", f32s(rays))?;
        let residual = buffers::zeroed(&gpu, "residual", f32s(rays))?;
        let back = buffers::zeroed(&gpu, "back-projection", f32s(nodes))?;
        let direction = buffers::zeroed(&gpu, "TV direction", f32s(3 * nodes))?;
        let ahead = buffers::zeroed(&gpu, "look-ahead σ", f32s(nodes))?;
        let sigma = buffers::zeroed(&gpu, "σ", f32s(nodes))?;
        let step_values = fista_step::Uniforms {
            n: n as u32,
            nodes: nodes as u32,
            _pad: [0; 2],
            per_ray: (1.0 / problem.rays_seen) as f32,
            tv_weight: (problem.lambda / nodes as f64) as f32,
            step: problem.step as f32,
            momentum: 0.0,
        };
        let step_uniforms = buffers::uniform(&gpu, "fista_step", &step_values);
        let (project, project_u) = kernels.csr_times.bind(&gpu, &rows, &ahead, Some(&target), &residual)?;
        let (back_project, back_u) = kernels.csr_times.bind(&gpu, &columns, &residual, None, &back)?;
        let (tv, tv_u) = kernels.tv_direction.bind(&gpu, n, problem.epsilon, &ahead, &direction)?;
        let step = kernels.fista_step.bind(&gpu, &step_uniforms, [&back, &direction, &ahead, &sigma], nodes)?;
        gpu.check()?;
        Ok(DeviceFista {
            gpu,
            kernels,
            nodes,
            target,
            ahead,
            sigma,
            step_uniforms,
            step_values,
            passes: [project, back_project, tv, step],
            _pass_uniforms: [project_u, back_u, tv_u],
            in_flight: InFlight::new(IN_FLIGHT),
        })
    }

    /// σ as it stands after everything submitted.
    fn read_sigma(&self) -> anyhow::Result<Vec<f64>> {
        let sigma = buffers::read::<f32>(&self.gpu, &[(&self.sigma, self.nodes)])?.swap_remove(0);
        Ok(sigma.into_iter().map(f64::from).collect())
    }

    /// Submits one step with `momentum`, waiting for the oldest when too many are in flight.
    fn submit_step(&mut self, momentum: f64) -> anyhow::Result<()> {
        let gpu = &self.gpu;
        self.step_values.momentum = momentum as f32;
        gpu.queue.write_buffer(&self.step_uniforms, 0, bytemuck::bytes_of(&self.step_values));
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        let [project, back_project, tv, step] = &self.passes;
        let k = &self.kernels;
        k.csr_times.record(&mut encoder, project);
        k.csr_times.record(&mut encoder, back_project);
        k.tv_direction.record(&mut encoder, tv);
        k.fista_step.record(&mut encoder, step);
        self.in_flight.submit(gpu, encoder)
    }
}

impl FistaSolver for DeviceFista {
    fn solve(
        &mut self,
        _problem: &DenseProblem,
        sigma: &mut [f64],
        target: &[f64],
        steps: usize,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f64]),
    ) -> anyhow::Result<()> {
        let start: Vec<f32> = sigma.iter().map(|&v| v as f32).collect();
        let target: Vec<f32> = target.iter().map(|&v| v as f32).collect();
        let queue = &self.gpu.queue;
        for buffer in [&self.sigma, &self.ahead] {
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(&start));
        }
        queue.write_buffer(&self.target, 0, bytemuck::cast_slice(&target));
        let mut t = 1.0f64;
        for it in 0..steps {
            let (t_next, momentum) = next_momentum(t);
            self.submit_step(momentum)?;
            t = t_next;
            if wants(it + 1) {
                checkpoint(it + 1, &self.read_sigma()?);
            }
        }
        sigma.copy_from_slice(&self.read_sigma()?);
        Ok(())
    }
}
