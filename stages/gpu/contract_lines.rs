//! Host of `shaders/contract_lines.wgsl`: `dL/dF` onto the line factors (the line half of
//! `train::field::VmField::contract`), one workgroup of 64 per line entry (each sums N² terms).

use super::kernel::ItemKernel;
use super::Gpu;

const SOURCE: &str = include_str!("../../shaders/contract_lines.wgsl");

/// `struct Shape` of the shader, the planes' own layout; here `entries` = 3 · rank · N.
pub use super::contract_planes::Shape;

/// Compiles the kernel. Storage: factors, `dL/dF` (read), the factor gradient (written); one workgroup per line entry.
pub fn kernel(gpu: &Gpu) -> anyhow::Result<ItemKernel> {
    ItemKernel::new(gpu, "contract_lines", SOURCE, [true, true, false], 1)
}
