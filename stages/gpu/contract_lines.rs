//! Host of `shaders/contract_lines.wgsl`: `dL/dF` onto the line factors (the line half of
//! `train::field::VmField::contract`), one workgroup of 64 per line entry (each sums N² terms).

use super::kernel::ItemKernel;
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/contract_lines.wgsl");

/// `struct Shape` of the shader; `entries` = 3 · rank · N.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Shape {
    pub n: u32,
    pub rank: u32,
    pub entries: u32,
    pub _pad: u32,
}

/// Compiles the kernel. Storage: factors, `dL/dF` (read), the factor gradient (written); one workgroup per line entry.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "contract_lines", SOURCE, [true, true, false], 1)
}
