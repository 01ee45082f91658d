//! Host of `shaders/fista_step.wgsl`: one FISTA step of the dense fit at every lattice node
//! (the step of `train::dense_tv::CpuFista`), after the back-projection and the TV direction.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/fista_step.wgsl");

/// `struct FistaStep` of the shader; the host rewrites `momentum` before every step.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub nodes: u32,
    pub _pad: [u32; 2],
    pub per_ray: f32,
    pub tv_weight: f32,
    pub step: f32,
    pub momentum: f32,
}

pub struct FistaStep {
    kernel: Kernel,
}

impl FistaStep {
    pub fn new(gpu: &Gpu) -> anyhow::Result<FistaStep> {
        let (read, write) = (Binding::Storage { read_only: true }, Binding::Storage { read_only: false });
        Ok(FistaStep { kernel: Kernel::new(gpu, "fista_step", SOURCE, &[Binding::Uniform, read, read, write, write])? })
    }

    /// Binds a step over `nodes` (storage in the shader's order: back-projection, direction,
    /// look-ahead, σ).
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        storage: [&wgpu::Buffer; 4],
        nodes: usize,
    ) -> anyhow::Result<Bound> {
        let [back, direction, ahead, sigma] = storage;
        let resources = [whole(uniforms), whole(back), whole(direction), whole(ahead), whole(sigma)];
        let group = self.kernel.bind(gpu, &resources);
        Ok(Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
