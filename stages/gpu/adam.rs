//! Host of `shaders/adam.wgsl`: one Adam update of every parameter (`train::adam::Adam::update`).

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::adam::{AdamParams, AdamStep};
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/adam.wgsl");

/// `struct Adam` of the shader: rewritten before every update.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub entries: u32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    pub lr_t: f32,
    pub sqrt_bias2: f32,
    pub _pad: [u32; 2],
}

impl Uniforms {
    /// The update of `step` (the scalars `AdamParams::step` gives the CPU, rounded as it rounds them).
    pub fn new(entries: usize, params: &AdamParams, step: &AdamStep) -> Uniforms {
        Uniforms {
            entries: entries as u32,
            beta1: params.beta1 as f32,
            beta2: params.beta2 as f32,
            eps: params.eps as f32,
            lr_t: step.lr_t as f32,
            sqrt_bias2: step.sqrt_bias2 as f32,
            _pad: [0; 2],
        }
    }
}

pub struct Adam(Kernel);

impl Adam {
    pub fn new(gpu: &Gpu) -> anyhow::Result<Adam> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(false), storage(false), storage(false)];
        Ok(Adam(Kernel::new(gpu, "adam", SOURCE, &bindings)?))
    }

    /// `m` and `v` are the optimiser's moments, as long as `factors`.
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        grad: &wgpu::Buffer,
        factors: &wgpu::Buffer,
        moments: [&wgpu::Buffer; 2],
        entries: usize,
    ) -> anyhow::Result<Bound> {
        let group =
            self.0.bind(gpu, &[whole(uniforms), whole(grad), whole(factors), whole(moments[0]), whole(moments[1])]);
        Ok(Bound { group, groups: groups(gpu, entries as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
