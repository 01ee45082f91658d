//! Host of `shaders/tv.wgsl` (+ `workgroup_sum.wgsl`): the TV regulariser of the density planes, its gradient and value
//! (`train::regularize::tv`), one invocation per plane entry.

use super::kernel::{ItemKernel, WORKGROUP, WORKGROUP_SUM};
use super::Gpu;
use crate::train::regularize::TvNorm;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/tv.wgsl");

/// `struct Tv` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub entries: u32,
    pub squared: u32,
    pub _pad0: u32,
    pub scale: f32,
    pub per_difference: f32,
    pub _pad1: [u32; 2],
}

impl Uniforms {
    pub fn new(n: usize, rank: usize, norm: TvNorm, weight: f64) -> Uniforms {
        // As the CPU: the weight per difference is weight / count, divided in f32.
        let count = (rank * n * n.saturating_sub(1)) as f32;
        Uniforms {
            n: n as u32,
            entries: (3 * rank * n * n) as u32,
            squared: (norm == TvNorm::L2).into(),
            _pad0: 0,
            scale: weight as f32 / count,
            per_difference: 1.0 / count,
            _pad1: [0; 2],
        }
    }
}

/// Compiles the kernel. Storage: factors (read), the factor gradient (added to), [`super::l1::partials`] of the value; items: `entries`.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "tv", &[SOURCE, WORKGROUP_SUM].concat(), [true, false, false], WORKGROUP)
}
