//! Host of `shaders/render.wgsl` (+ `grad_add_f32.wgsl` or `grad_add_cas.wgsl`): render a ray
//! batch through `F`, and scatter `dL/dF` (`train::render::Renderer::batch` and its scatter).

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::render::{PhotoLoss, Ray, Renderer};
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/render.wgsl");
const ADD_NATIVE: &str = include_str!("../../shaders/grad_add_f32.wgsl");
const ADD_CAS: &str = include_str!("../../shaders/grad_add_cas.wgsl");

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
    /// Native float atomics when the device has them, else the compare-exchange loop.
    pub fn new(gpu: &Gpu) -> anyhow::Result<Render> {
        let add = if gpu.float_atomics { ADD_NATIVE } else { ADD_CAS };
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, storage(true), storage(true), storage(true), storage(false), storage(false)];
        Ok(Render(Kernel::new(gpu, "render", &format!("{SOURCE}\n{add}"), &bindings)?))
    }

    /// One invocation per ray of `rays` (`count` of them).
    #[allow(clippy::too_many_arguments)]
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        dense: &wgpu::Buffer,
        mask_nodes: &wgpu::Buffer,
        rays: &wgpu::Buffer,
        predicted: &wgpu::Buffer,
        dense_grad: &wgpu::Buffer,
        count: usize,
    ) -> anyhow::Result<Bound> {
        let resources =
            [whole(uniforms), whole(dense), whole(mask_nodes), whole(rays), whole(predicted), whole(dense_grad)];
        Ok(Bound { group: self.0.bind(gpu, &resources), groups: groups(gpu, count as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}
