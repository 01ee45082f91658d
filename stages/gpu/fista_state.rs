//! Host of `shaders/fista_state.wgsl`: after each FISTA step, one workgroup adds the step's
//! partial sums in a fixed order and updates the solve's [`State`](super::fista_step::State)
//! (`CpuFista::solve` between its passes).

use super::buffers;
use super::fista_step::SOLVE_STATE;
use super::kernel::{whole, Binding, Bound, Kernel};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/fista_state.wgsl");

/// `struct Partials` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub count: u32,
    pub _pad: [u32; 3],
}

pub struct FistaState {
    kernel: Kernel,
}

impl FistaState {
    pub fn new(gpu: &Gpu) -> anyhow::Result<FistaState> {
        let bindings = [Binding::Uniform, Binding::Storage { read_only: true }, Binding::Storage { read_only: false }];
        Ok(FistaState { kernel: Kernel::new(gpu, "fista_state", &[SOURCE, SOLVE_STATE].concat(), &bindings)? })
    }

    /// Binds the update of `state` from `workgroups` triples of `partials`. The returned
    /// uniform buffer must live as long as the binding.
    pub fn bind(
        &self,
        gpu: &Gpu,
        partials: &wgpu::Buffer,
        workgroups: usize,
        state: &wgpu::Buffer,
    ) -> (Bound, wgpu::Buffer) {
        let uniforms = buffers::uniform(gpu, "fista_state", &Uniforms { count: workgroups as u32, _pad: [0; 3] });
        let group = self.kernel.bind(gpu, &[whole(&uniforms), whole(partials), whole(state)]);
        (Bound { group, groups: [1, 1, 1] }, uniforms)
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
