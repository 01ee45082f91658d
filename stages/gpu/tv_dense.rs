//! Host of `shaders/tv_dense.wgsl`: the 3-D TV of the composed field, its gradient added to
//! dF and its value (`train::regularize::tv_dense`), one invocation per lattice node.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/tv_dense.wgsl");

/// `struct TvDense` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub nodes: u32,
    pub _pad0: [u32; 2],
    pub scale: f32,
    pub per_difference: f32,
    pub _pad1: [u32; 2],
}

impl Uniforms {
    pub fn new(n: usize, weight: f64) -> Uniforms {
        let differences = (n * n * n.saturating_sub(1)).max(1) as f64;
        Uniforms {
            n: n as u32,
            nodes: (n * n * n) as u32,
            _pad0: [0; 2],
            scale: (weight as f32) / differences as f32,
            per_difference: (1.0 / differences) as f32,
            _pad1: [0; 2],
        }
    }
}

pub struct TvDense(Kernel);

impl TvDense {
    pub fn new(gpu: &Gpu) -> anyhow::Result<TvDense> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(false), storage(false)];
        Ok(TvDense(Kernel::new(gpu, "tv_dense", SOURCE, &bindings)?))
    }

    /// `partials` holds `l1::partials(nodes)` floats.
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: (&wgpu::Buffer, Uniforms),
        dense: &wgpu::Buffer,
        dense_grad: &wgpu::Buffer,
        partials: &wgpu::Buffer,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(uniforms.0), whole(dense), whole(dense_grad), whole(partials)]);
        Ok(Bound { group, groups: groups(gpu, u64::from(uniforms.1.nodes), WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
