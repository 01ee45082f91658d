//! Host of `shaders/contract_planes.wgsl`: `dL/dF` onto the plane factors (the plane half of
//! `train::field::VmField::contract`), one invocation per plane entry.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/contract_planes.wgsl");

/// `struct Shape` of the shader; `entries` = 3 · rank · N².
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Shape {
    pub n: u32,
    pub rank: u32,
    pub entries: u32,
    pub _pad: u32,
}

pub struct ContractPlanes(Kernel);

impl ContractPlanes {
    pub fn new(gpu: &Gpu) -> anyhow::Result<ContractPlanes> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(true), storage(false)];
        Ok(ContractPlanes(Kernel::new(gpu, "contract_planes", SOURCE, &bindings)?))
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
        Ok(Bound { group, groups: groups(gpu, u64::from(shape.1.entries), WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
