//! Host of `shaders/l1.wgsl` (+ `workgroup_sum.wgsl`): the L1 regulariser's gradient and value
//! (`train::regularize::l1`), one invocation per parameter.

use super::kernel::{groups, ItemKernel, WORKGROUP, WORKGROUP_SUM};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/l1.wgsl");

/// `struct L1` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub entries: u32,
    pub lines: u32,
    pub plane_len: u32,
    pub line_len: u32,
    pub weight: f32,
    pub _pad: [u32; 3],
}

impl Uniforms {
    pub fn new(n: usize, rank: usize, weight: f64) -> Uniforms {
        let (plane_len, line_len) = (rank * n * n, rank * n);
        Uniforms {
            entries: (3 * (plane_len + line_len)) as u32,
            lines: (3 * plane_len) as u32,
            plane_len: plane_len as u32,
            line_len: line_len as u32,
            weight: weight as f32,
            _pad: [0; 3],
        }
    }
}

/// Value partials the kernel writes over `entries` items: one per dispatched workgroup (the
/// dispatch may round up to a rectangle of workgroups; every one of them writes its slot).
pub fn partials(gpu: &Gpu, entries: u32) -> anyhow::Result<usize> {
    let [x, y, _] = groups(gpu, u64::from(entries), WORKGROUP)?;
    Ok(x as usize * y as usize)
}

/// Compiles the kernel. Storage: factors (read), the factor gradient (added to), [`partials`] of the value; items: `entries`.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "l1", &[SOURCE, WORKGROUP_SUM].concat(), [true, false, false], WORKGROUP)
}
