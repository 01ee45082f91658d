//! Host of `shaders/tv.wgsl`: the TV regulariser of the density planes, its gradient and value
//! (`train::regularize::tv`), one invocation per plane entry.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
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

pub struct Tv(Kernel);

impl Tv {
    pub fn new(gpu: &Gpu) -> anyhow::Result<Tv> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(false), storage(false)];
        Ok(Tv(Kernel::new(gpu, "tv", SOURCE, &bindings)?))
    }

    /// `partials` holds [`super::l1::partials`]`(entries)` floats.
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: (&wgpu::Buffer, Uniforms),
        factors: &wgpu::Buffer,
        grad: &wgpu::Buffer,
        partials: &wgpu::Buffer,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(uniforms.0), whole(factors), whole(grad), whole(partials)]);
        Ok(Bound { group, groups: groups(gpu, u64::from(uniforms.1.entries), WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
