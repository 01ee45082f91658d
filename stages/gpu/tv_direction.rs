//! Host of `shaders/tv_direction.wgsl`: the smoothed TV's normalised differences `∇σ / m` and
//! `1/m` (`train::dense_tv::tv::PlaneDirections`), one invocation per lattice node.

use super::buffers;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/tv_direction.wgsl");

/// `struct TvDirection` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub nodes: u32,
    pub epsilon: f32,
    pub _pad: u32,
}

pub struct TvDirection {
    kernel: Kernel,
}

impl TvDirection {
    pub fn new(gpu: &Gpu) -> anyhow::Result<TvDirection> {
        let bindings = [Binding::Uniform, Binding::Storage { read_only: true }, Binding::Storage { read_only: false }];
        Ok(TvDirection { kernel: Kernel::new(gpu, "tv_direction", SOURCE, &bindings)? })
    }

    /// Binds `direction` (4 floats a node) = p and 1/m of `sigma` on an `n³` lattice. The returned
    /// uniform buffer must live as long as the binding.
    pub fn bind(
        &self,
        gpu: &Gpu,
        n: usize,
        epsilon: f64,
        sigma: &wgpu::Buffer,
        direction: &wgpu::Buffer,
    ) -> anyhow::Result<(Bound, wgpu::Buffer)> {
        let nodes = n * n * n;
        let values = Uniforms { n: n as u32, nodes: nodes as u32, epsilon: epsilon as f32, _pad: 0 };
        let uniforms = buffers::uniform(gpu, "tv_direction", &values);
        let group = self.kernel.bind(gpu, &[whole(&uniforms), whole(sigma), whole(direction)]);
        Ok((Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? }, uniforms))
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
