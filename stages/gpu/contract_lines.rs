//! Host of `shaders/contract_lines.wgsl`: `dL/dF` onto the line factors (the line half of
//! `train::field::VmField::contract`), one workgroup of 64 per line entry (each sums N² terms).

use super::kernel::{groups, whole, Binding, Bound, Kernel};
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

pub struct ContractLines(Kernel);

impl ContractLines {
    pub fn new(gpu: &Gpu) -> anyhow::Result<ContractLines> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(true), storage(false)];
        Ok(ContractLines(Kernel::new(gpu, "contract_lines", SOURCE, &bindings)?))
    }

    pub fn bind(
        &self,
        gpu: &Gpu,
        shape: (&wgpu::Buffer, Shape),
        factors: &wgpu::Buffer,
        dense_grad: &wgpu::Buffer,
        grad: &wgpu::Buffer,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(shape.0), whole(factors), whole(dense_grad), whole(grad)]);
        // One workgroup per entry.
        Ok(Bound { group, groups: groups(gpu, u64::from(shape.1.entries), 1)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
