//! The dense fit's FISTA loop on the device (mirrors `train::dense_tv::CpuFista`): σ, the
//! look-ahead point, the residual, the back-projection, the TV's directions and the solve's
//! state live on the GPU for a whole solve. Per step the host submits project → back-project
//! → TV direction → step → state → restart; it reads σ and the state back only at logged steps,
//! every [`POLL`] steps (to stop once settled) and at the end. Everything else — the
//! projector's tables, each node's data curvature and every log row — is `train::dense_tv`'s
//! own, on the host. The device runs the projector's path for views along the lattice axes;
//! views at an angle are solved on the CPU ([`fit`] says so).

use super::buffers;
use super::device::InFlight;
use super::fista_restart::FistaRestart;
use super::fista_state::FistaState;
use super::fista_step::{self, FistaStep, State, StepBuffers};
use super::kernel::Bound;
use super::sheet_back::SheetBack;
use super::sheet_project::{DeviceSheet, SheetProject};
use super::tv_direction::TvDirection;
use super::Gpu;
use crate::train::dense_tv::{self, CpuFista, DenseFitted, DenseProblem, FistaSolver, Stop};
use crate::train::fit::{LogRow, Views};
use crate::train::params::TrainParams;
use crate::train::render::Renderer;
use std::sync::Arc;

/// Steps the host may submit ahead of the device before it waits for the oldest.
const IN_FLIGHT: usize = 8;
/// Steps between two reads of the solve's state, to stop once it has settled.
const POLL: usize = 16;

/// The dense fit's kernels, compiled once per device ([`Gpu::compiled`]).
pub struct DenseKernels {
    project: SheetProject,
    back: SheetBack,
    tv_direction: TvDirection,
    step: FistaStep,
    state: FistaState,
    restart: FistaRestart,
}

impl DenseKernels {
    pub fn new(gpu: &Gpu) -> anyhow::Result<DenseKernels> {
        Ok(DenseKernels {
            project: SheetProject::new(gpu)?,
            back: SheetBack::new(gpu)?,
            tv_direction: TvDirection::new(gpu)?,
            step: FistaStep::new(gpu)?,
            state: FistaState::new(gpu)?,
            restart: FistaRestart::new(gpu)?,
        })
    }
}

/// Fits σ to `views` with the FISTA steps on `gpu` (`train::dense_tv::fit_with`), or on the
/// CPU where the views are at an angle to the lattice (the device has no path for those).
pub fn fit(
    gpu: &Arc<Gpu>,
    params: &TrainParams,
    views: &Views,
    renderer: &Renderer,
    on_log: impl FnMut(&LogRow),
) -> anyhow::Result<DenseFitted> {
    dense_tv::fit_with(
        params,
        views,
        renderer,
        |problem| -> anyhow::Result<Box<dyn FistaSolver>> {
            if problem.projector.aligned() {
                Ok(Box::new(DeviceFista::new(gpu.clone(), problem)?))
            } else {
                Ok(Box::new(CpuFista::new(problem)))
            }
        },
        on_log,
    )
}

/// One problem's buffers and bindings on the device.
pub struct DeviceFista {
    gpu: Arc<Gpu>,
    kernels: Arc<DenseKernels>,
    nodes: usize,
    target: wgpu::Buffer,
    ahead: wgpu::Buffer,
    sigma: wgpu::Buffer,
    state: wgpu::Buffer,
    /// In order of recording: each view's projection, each view's back-projection, TV
    /// direction, step, state, restart.
    passes: Vec<Bound>,
    /// What the bindings hold on to: the views' tables and the uniform buffers.
    _held: (Vec<DeviceSheet>, Vec<wgpu::Buffer>),
    in_flight: InFlight,
}

impl DeviceFista {
    /// Uploads `problem`'s tables and allocates the solve's buffers. The views must be along
    /// the lattice's axes.
    pub fn new(gpu: Arc<Gpu>, problem: &DenseProblem) -> anyhow::Result<DeviceFista> {
        let projector = &problem.projector;
        anyhow::ensure!(projector.aligned(), "the GPU's dense fit reads views along the lattice axes only");
        let kernels = gpu.compiled(DenseKernels::new)?;
        let (n, nodes, rays) = (problem.n, problem.nodes(), projector.rays);
        let f32s = |count: usize| (count * std::mem::size_of::<f32>()) as u64;
        let sheets: Vec<DeviceSheet> = projector
            .sheets
            .iter()
            .enumerate()
            .map(|(i, sheet)| DeviceSheet::upload(&gpu, sheet, n, i == 0))
            .collect::<anyhow::Result<_>>()?;
        let target = buffers::zeroed(&gpu, "target depths", f32s(rays))?;
        let residual = buffers::zeroed(&gpu, "residual", f32s(rays))?;
        let back = buffers::zeroed(&gpu, "back-projection", f32s(nodes))?;
        let direction = buffers::zeroed(&gpu, "TV direction", f32s(4 * nodes))?;
        let data_curvature = buffers::storage(&gpu, "data curvature", &problem.data_curvature)?;
        let ahead = buffers::zeroed(&gpu, "look-ahead σ", f32s(nodes))?;
        let sigma = buffers::zeroed(&gpu, "σ", f32s(nodes))?;
        let state = buffers::zeroed(&gpu, "FISTA state", std::mem::size_of::<State>() as u64)?;
        let workgroups = FistaStep::workgroups(&gpu, nodes)?;
        let partials = buffers::zeroed(&gpu, "FISTA partial sums", f32s(3 * workgroups))?;
        let step_values = fista_step::Uniforms {
            n: n as u32,
            nodes: nodes as u32,
            _pad: [0; 2],
            per_ray: (1.0 / problem.rays_seen) as f32,
            tv_weight: (problem.lambda / nodes as f64) as f32,
            _pad2: [0; 2],
        };
        let step_uniforms = buffers::uniform(&gpu, "fista_step", &step_values);
        let k = &kernels;
        let mut passes = Vec::new();
        for sheet in &sheets {
            passes.push(k.project.bind(&gpu, sheet, &ahead, &target, &residual)?);
        }
        for sheet in &sheets {
            passes.push(k.back.bind(&gpu, sheet, &residual, &back, nodes)?);
        }
        let (tv, tv_uniforms) = k.tv_direction.bind(&gpu, n, problem.epsilon, &ahead, &direction)?;
        passes.push(tv);
        let buffers = StepBuffers {
            back: &back,
            direction: &direction,
            data_curvature: &data_curvature,
            state: &state,
            ahead: &ahead,
            sigma: &sigma,
            partials: &partials,
        };
        passes.push(k.step.bind(&gpu, &step_uniforms, buffers, nodes)?);
        let (update, state_uniforms) = k.state.bind(&gpu, &partials, workgroups, &state);
        passes.push(update);
        let (restart, restart_uniforms) = k.restart.bind(&gpu, &state, &sigma, &ahead, nodes)?;
        passes.push(restart);
        gpu.check()?;
        let uniforms = vec![tv_uniforms, step_uniforms, state_uniforms, restart_uniforms];
        let held = (sheets, [uniforms, vec![residual, back, direction, data_curvature, partials]].concat());
        Ok(DeviceFista {
            gpu,
            kernels,
            nodes,
            target,
            ahead,
            sigma,
            state,
            passes,
            _held: held,
            in_flight: InFlight::new(IN_FLIGHT),
        })
    }

    /// σ as it stands after everything submitted.
    fn read_sigma(&self) -> anyhow::Result<Vec<f32>> {
        Ok(buffers::read::<f32>(&self.gpu, &[(&self.sigma, self.nodes)])?.swap_remove(0))
    }

    /// The solve's state after everything submitted.
    fn read_state(&self) -> anyhow::Result<State> {
        Ok(buffers::read::<State>(&self.gpu, &[(&self.state, 1)])?[0][0])
    }

    /// Submits one step, waiting for the oldest when too many are in flight.
    fn submit_step(&mut self) -> anyhow::Result<()> {
        let mut encoder = self.gpu.device.create_command_encoder(&Default::default());
        let k = &self.kernels;
        let views = (self.passes.len() - 4) / 2;
        for (i, bound) in self.passes.iter().enumerate() {
            match i {
                _ if i < views => k.project.record(&mut encoder, bound),
                _ if i < 2 * views => k.back.record(&mut encoder, bound),
                _ => match i - 2 * views {
                    0 => k.tv_direction.record(&mut encoder, bound),
                    1 => k.step.record(&mut encoder, bound),
                    2 => k.state.record(&mut encoder, bound),
                    _ => k.restart.record(&mut encoder, bound),
                },
            }
        }
        self.in_flight.submit(&self.gpu, encoder)
    }
}

impl FistaSolver for DeviceFista {
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f32],
        stop: Stop,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f32]),
    ) -> anyhow::Result<usize> {
        let target: Vec<f32> = problem.measured.iter().map(|&v| v as f32).collect();
        let queue = &self.gpu.queue;
        for buffer in [&self.sigma, &self.ahead] {
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(sigma));
        }
        queue.write_buffer(&self.target, 0, bytemuck::cast_slice(&target));
        let start = State {
            t: 1.0,
            momentum: 0.0,
            restarted: 0,
            settled: 0,
            steps: 0,
            tolerance: stop.tolerance as f32,
            coasting: 0,
            _pad: 0,
        };
        queue.write_buffer(&self.state, 0, bytemuck::bytes_of(&start));
        for step in 1..=stop.steps {
            self.submit_step()?;
            let logged = wants(step);
            if !(logged || step % POLL == 0 || step == stop.steps) {
                continue;
            }
            let state = self.read_state()?;
            let taken = state.steps as usize;
            if state.settled != 0 || step == stop.steps {
                sigma.copy_from_slice(&self.read_sigma()?);
                checkpoint(taken, sigma);
                return Ok(taken);
            }
            if logged {
                checkpoint(step, &self.read_sigma()?);
            }
        }
        Ok(stop.steps)
    }
}
