//! Host of `shaders/alpha_mask.wgsl`: the alpha mask's kept nodes
//! (`train::render::Renderer::alpha_mask`), one invocation per node.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::render::Renderer;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/alpha_mask.wgsl");

/// `struct Mask` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub nodes: u32,
    pub shift: f32,
    pub sigma_threshold: f32,
}

impl Uniforms {
    /// `alpha = 1 − exp(−σ·step·s) > threshold` is `σ > −ln(1 − threshold)/(step·s)`:
    /// the threshold on σ, in f64 (nothing is kept at a threshold of 1 or more).
    pub fn new(renderer: &Renderer, threshold: f64) -> Uniforms {
        let n = renderer.lattice.n;
        let sigma = if threshold < 1.0 { -(-threshold).ln_1p() / (renderer.step * renderer.scale) } else { f64::MAX };
        Uniforms {
            n: n as u32,
            nodes: (n * n * n) as u32,
            shift: renderer.shift as f32,
            sigma_threshold: sigma.min(f64::from(f32::MAX)) as f32,
        }
    }
}

pub struct AlphaMask(Kernel);

impl AlphaMask {
    pub fn new(gpu: &Gpu) -> anyhow::Result<AlphaMask> {
        let storage = |read_only| Binding::Storage { read_only };
        Ok(AlphaMask(Kernel::new(gpu, "alpha_mask", SOURCE, &[Binding::Uniform, storage(true), storage(false)])?))
    }

    /// `mask_nodes` receives one u32 per node (1: kept).
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: (&wgpu::Buffer, Uniforms),
        dense: &wgpu::Buffer,
        mask_nodes: &wgpu::Buffer,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(uniforms.0), whole(dense), whole(mask_nodes)]);
        Ok(Bound { group, groups: groups(gpu, u64::from(uniforms.1.nodes), WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
