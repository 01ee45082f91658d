//! Host of `shaders/fista_restart.wgsl`: where `fista_state` restarted the momentum, the
//! look-ahead point becomes σ, one invocation per node.

use super::buffers;
use super::fista_step::SOLVE_STATE;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/fista_restart.wgsl");

/// `struct Nodes` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub nodes: u32,
    pub _pad: [u32; 3],
}

pub struct FistaRestart {
    kernel: Kernel,
}

impl FistaRestart {
    pub fn new(gpu: &Gpu) -> anyhow::Result<FistaRestart> {
        let read = Binding::Storage { read_only: true };
        let bindings = [Binding::Uniform, read, read, Binding::Storage { read_only: false }];
        Ok(FistaRestart { kernel: Kernel::new(gpu, "fista_restart", &[SOURCE, SOLVE_STATE].concat(), &bindings)? })
    }

    /// Binds the restart over `nodes`; the returned uniform buffer must outlive the binding.
    pub fn bind(
        &self,
        gpu: &Gpu,
        state: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        ahead: &wgpu::Buffer,
        nodes: usize,
    ) -> anyhow::Result<(Bound, wgpu::Buffer)> {
        let uniforms = buffers::uniform(gpu, "fista_restart", &Uniforms { nodes: nodes as u32, _pad: [0; 3] });
        let group = self.kernel.bind(gpu, &[whole(&uniforms), whole(state), whole(sigma), whole(ahead)]);
        Ok((Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? }, uniforms))
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
