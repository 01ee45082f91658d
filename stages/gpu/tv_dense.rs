//! Host of `shaders/tv_dense.wgsl` (+ `workgroup_sum.wgsl`): the 3-D TV of the composed field, its gradient added to
//! dF and its value (`train::regularize::tv_dense`), one invocation per lattice node.

use super::kernel::{ItemKernel, WORKGROUP, WORKGROUP_SUM};
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

/// Compiles the kernel. Storage: `F` (read), `dL/dF` (added to), [`super::l1::partials`] of the value; items: `nodes`.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "tv_dense", &[SOURCE, WORKGROUP_SUM].concat(), [true, false, false], WORKGROUP)
}
