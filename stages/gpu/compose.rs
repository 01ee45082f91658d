//! Host of `shaders/compose.wgsl`: the dense field `F = Σ P⊗L` on the lattice
//! (`train::field::VmField::compose`), one invocation per node.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/compose.wgsl");

/// `struct Shape` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Shape {
    pub n: u32,
    pub rank: u32,
    pub nodes: u32,
    pub _pad: u32,
}

pub struct Compose(Kernel);

impl Compose {
    pub fn new(gpu: &Gpu) -> anyhow::Result<Compose> {
        let storage = |read_only| Binding::Storage { read_only };
        Ok(Compose(Kernel::new(gpu, "compose", SOURCE, &[Binding::Uniform, storage(true), storage(false)])?))
    }

    /// `shape` holds a [`Shape`]; `dense` receives `F` (N³ floats).
    pub fn bind(
        &self,
        gpu: &Gpu,
        shape: &wgpu::Buffer,
        factors: &wgpu::Buffer,
        dense: &wgpu::Buffer,
        nodes: u32,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(shape), whole(factors), whole(dense)]);
        Ok(Bound { group, groups: groups(gpu, u64::from(nodes), WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
