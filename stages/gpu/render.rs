//! Host of `shaders/render.wgsl` (+ `fixed_point.wgsl`): render a ray batch through `F`, and
//! scatter `dL/dF` as fixed-point sums (`train::render::Renderer::batch` and its scatter);
//! [`super::grad_from_fixed`] turns them into f32.

use super::grad_from_fixed::FIXED_POINT;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::render::{PhotoLoss, Ray, Renderer};
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/render.wgsl");

/// `struct Render` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub rays: u32,
    pub want_grad: u32,
    pub masked: u32,
    pub shift: f32,
    /// s · step
    pub depth_scale: f32,
    /// −2 · s · step / B
    pub grad_scale: f32,
    /// 1: `PhotoLoss::Log`.
    pub log_loss: u32,
}

impl Uniforms {
    /// The constants of `renderer` for `rays` rays (`batch`: the B of the MSE when training).
    pub fn new(renderer: &Renderer, rays: usize, want_grad: bool, masked: bool) -> Uniforms {
        let depth_scale = renderer.scale * renderer.step;
        Uniforms {
            n: renderer.lattice.n as u32,
            rays: rays as u32,
            want_grad: want_grad.into(),
            masked: masked.into(),
            shift: renderer.shift as f32,
            depth_scale: depth_scale as f32,
            grad_scale: (-2.0 * depth_scale / rays.max(1) as f64) as f32,
            log_loss: (renderer.loss == PhotoLoss::Log).into(),
        }
    }
}

/// `struct RaySamples` of the shader: 32 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct RaySamples {
    pub q0: [f32; 3],
    pub count: u32,
    pub dq: [f32; 3],
    pub target: f32,
}

impl RaySamples {
    /// `ray` with jitter `offset`, as the CPU renderer walks it.
    pub fn new(renderer: &Renderer, ray: &Ray, offset: f64) -> RaySamples {
        let (q0, dq, count) = renderer.samples(ray, offset);
        RaySamples {
            q0: q0.map(|v| v as f32),
            count: count as u32,
            dq: dq.map(|v| v as f32),
            target: ray.target as f32,
        }
    }
}

pub struct Render(Kernel);

impl Render {
    pub fn new(gpu: &Gpu) -> anyhow::Result<Render> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(true), storage(true), storage(false), storage(false)];
        Ok(Render(Kernel::new(gpu, "render", &[SOURCE, FIXED_POINT].concat(), &bindings)?))
    }

    /// One invocation per ray of `rays` (`count` of them); `dense_grad_fixed` holds
    /// [`super::grad_from_fixed::fixed_bytes`] and must be cleared before each scatter.
    #[allow(clippy::too_many_arguments)]
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        dense: &wgpu::Buffer,
        mask_nodes: &wgpu::Buffer,
        rays: &wgpu::Buffer,
        predicted: &wgpu::Buffer,
        dense_grad_fixed: &wgpu::Buffer,
        count: usize,
    ) -> anyhow::Result<Bound> {
        let resources =
            [whole(uniforms), whole(dense), whole(mask_nodes), whole(rays), whole(predicted), whole(dense_grad_fixed)];
        Ok(Bound { group: self.0.bind(gpu, &resources), groups: groups(gpu, count as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
