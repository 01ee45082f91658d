//! Host of `shaders/contract_planes.wgsl`: `dL/dF` onto the plane factors (the plane half of
//! `train::field::VmField::contract`), one invocation per plane entry.

use super::kernel::{ItemKernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/contract_planes.wgsl");

/// `struct Shape` of the shader (and of `contract_lines.wgsl`); `entries` = 3 · rank · N² here.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Shape {
    pub n: u32,
    pub rank: u32,
    pub entries: u32,
    pub _pad: u32,
}

/// Compiles the kernel. Storage: factors, `dL/dF` (read), the factor gradient (written); items: plane entries.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "contract_planes", SOURCE, [true, true, false], WORKGROUP)
}
