//! Host of `shaders/fista_step.wgsl`: one FISTA step of the dense fit at every lattice node
//! (the pass of `train::dense_tv::cpu::CpuFista`), after the back-projection and the TV
//! direction, with each workgroup's three sums for `fista_state`.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/fista_step.wgsl");

/// `struct FistaStep` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub nodes: u32,
    pub _pad: [u32; 2],
    pub per_ray: f32,
    pub tv_weight: f32,
    pub _pad2: [u32; 2],
}

/// `shaders/fista_solve_state.wgsl`, which the FISTA kernels' hosts append to their shader: its
/// `struct State`, [`State`] on the device.
pub const SOLVE_STATE: &str = include_str!("../../shaders/fista_solve_state.wgsl");

/// `struct State` of the shaders: the solve's momentum, restart, count and stop, on the device.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct State {
    pub t: f32,
    pub momentum: f32,
    pub restarted: u32,
    pub settled: u32,
    pub steps: u32,
    pub tolerance: f32,
    /// Whether the next step's look-ahead carries momentum (1) or is σ itself (0).
    pub coasting: u32,
    pub _pad: u32,
}

pub struct FistaStep {
    kernel: Kernel,
}

/// The step's buffers in the shader's order: back-projection, direction, data curvature, state
/// (read), look-ahead, σ, partials (written).
pub struct StepBuffers<'a> {
    pub back: &'a wgpu::Buffer,
    pub direction: &'a wgpu::Buffer,
    pub data_curvature: &'a wgpu::Buffer,
    pub state: &'a wgpu::Buffer,
    pub ahead: &'a wgpu::Buffer,
    pub sigma: &'a wgpu::Buffer,
    pub partials: &'a wgpu::Buffer,
}

impl FistaStep {
    pub fn new(gpu: &Gpu) -> anyhow::Result<FistaStep> {
        let (read, write) = (Binding::Storage { read_only: true }, Binding::Storage { read_only: false });
        let bindings = [Binding::Uniform, read, read, read, read, write, write, write];
        Ok(FistaStep { kernel: Kernel::new(gpu, "fista_step", &[SOURCE, SOLVE_STATE].concat(), &bindings)? })
    }

    /// Workgroups of a step over `nodes`: each writes three partial sums.
    pub fn workgroups(gpu: &Gpu, nodes: usize) -> anyhow::Result<usize> {
        let [x, y, _] = groups(gpu, nodes as u64, WORKGROUP)?;
        Ok(x as usize * y as usize)
    }

    pub fn bind(&self, gpu: &Gpu, uniforms: &wgpu::Buffer, b: StepBuffers, nodes: usize) -> anyhow::Result<Bound> {
        let resources = [
            whole(uniforms),
            whole(b.back),
            whole(b.direction),
            whole(b.data_curvature),
            whole(b.state),
            whole(b.ahead),
            whole(b.sigma),
            whole(b.partials),
        ];
        let group = self.kernel.bind(gpu, &resources);
        Ok(Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
