//! Host of `shaders/drr_march.wgsl`: the DRR stage's radiographs on the GPU
//! (`kernels::raymarch::render`). The CT goes up once as a 3-D r32float texture; each pixel's
//! ray is clipped on the host by `raymarch::segment` (f64, the CPU's own code: both backends
//! take the same samples), and the kernel sums the samples and applies Beer–Lambert.

use super::buffers;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::geometry::{Aabb, Camera};
use crate::kernels::raymarch::{segment, Field, Segment, VolumeField};
use bytemuck::{Pod, Zeroable};
use glam::DVec3;

const SOURCE: &str = include_str!("../../shaders/drr_march.wgsl");

/// `struct March` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub pixels: u32,
    pub attenuation: f32,
    pub _pad: [u32; 2],
}

/// `struct Segment` of the shader: midpoint samples at `voxel + fraction + s·(step_hi + step_lo)`
/// in voxel-index space (see the shader for why positions are split so).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct PixelSegment {
    pub voxel: [i32; 3],
    pub count: u32,
    pub fraction: [f32; 3],
    pub delta: f32,
    pub step_hi: [f32; 3],
    pub _pad0: u32,
    pub step_lo: [f32; 3],
    pub _pad1: u32,
}

impl PixelSegment {
    /// The segment's first sample at `first` and the increment `step` (f64, voxel index).
    fn new(first: DVec3, step: DVec3, count: usize, delta: f64) -> PixelSegment {
        let voxel = first.floor();
        let step_hi = step.as_vec3();
        PixelSegment {
            voxel: voxel.as_ivec3().to_array(),
            count: count as u32,
            fraction: (first - voxel).as_vec3().to_array(),
            delta: delta as f32,
            step_hi: step_hi.to_array(),
            _pad0: 0,
            step_lo: (step - step_hi.as_dvec3()).as_vec3().to_array(),
            _pad1: 0,
        }
    }
}

pub struct DrrMarch(Kernel);

impl DrrMarch {
    pub fn new(gpu: &Gpu) -> anyhow::Result<DrrMarch> {
        let storage = |read_only| Binding::Storage { read_only };
        let bindings = [Binding::Uniform, Binding::Volume, storage(true), storage(false)];
        Ok(DrrMarch(Kernel::new(gpu, "drr_march", SOURCE, &bindings)?))
    }

    fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        volume: &wgpu::TextureView,
        segments: &wgpu::Buffer,
        pixels: &wgpu::Buffer,
        count: usize,
    ) -> anyhow::Result<Bound> {
        let resources = [whole(uniforms), wgpu::BindingResource::TextureView(volume), whole(segments), whole(pixels)];
        Ok(Bound { group: self.0.bind(gpu, &resources), groups: groups(gpu, count as u64, WORKGROUP)? })
    }
}

/// `I/I0 = exp(−attenuation · ∫ v ds)` of every pixel of every camera (row-major from the top
/// row, one image per camera), `field` marched inside `aabb` — as `raymarch::render` with no
/// step limit beyond the field's half voxel.
pub fn render(
    gpu: &Gpu,
    field: &VolumeField,
    aabb: &Aabb,
    cameras: &[Camera],
    attenuation: f64,
) -> anyhow::Result<Vec<Vec<f32>>> {
    let march = gpu.compiled(DrrMarch::new)?;
    let volume = upload_volume(gpu, field)?;
    let view = volume.create_view(&Default::default());
    let mut segments = Vec::new();
    for cam in cameras {
        let eye = cam.eye();
        for j in 0..cam.height {
            for i in 0..cam.width {
                let dir = cam.ray_dir(i, j);
                let ray = field.prepare(eye, dir);
                segments.push(match segment(field, aabb, &ray, eye, dir, f64::INFINITY) {
                    Some(Segment { t0, delta, count }) => {
                        let (o, d) = ray;
                        PixelSegment::new(o + d * (t0 + 0.5 * delta), d * delta, count, delta)
                    }
                    None => PixelSegment::zeroed(),
                });
            }
        }
    }
    let count = segments.len();
    let uniforms = Uniforms { pixels: count as u32, attenuation: attenuation as f32, _pad: [0; 2] };
    let uniforms = buffers::uniform(gpu, "drr uniforms", &uniforms);
    let segments = buffers::storage(gpu, "drr segments", &segments)?;
    let pixels = buffers::zeroed(gpu, "drr pixels", 4 * count as u64)?;
    let bound = march.bind(gpu, &uniforms, &view, &segments, &pixels, count)?;
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    march.0.record(&mut encoder, &bound);
    gpu.queue.submit([encoder.finish()]);
    let all = buffers::read::<f32>(gpu, &[(&pixels, count)])?.remove(0);
    let mut out = Vec::with_capacity(cameras.len());
    let mut at = 0;
    for cam in cameras {
        out.push(all[at..at + cam.width * cam.height].to_vec());
        at += cam.width * cam.height;
    }
    Ok(out)
}

/// The CT as a 3-D r32float texture (x fastest, as `Volume` stores it), written in slabs of
/// slices so the staging copy stays small.
fn upload_volume(gpu: &Gpu, field: &VolumeField) -> anyhow::Result<wgpu::Texture> {
    let [nx, ny, nz] = field.dims();
    let max = gpu.limits.max_texture_dimension_3d as usize;
    if nx.max(ny).max(nz) > max {
        anyhow::bail!(
            "the CT ({nx}×{ny}×{nz} voxels) exceeds {}'s largest 3-D texture ({max} per axis): \
             use [drr] backend = \"cpu\" for it",
            gpu.info.name
        );
    }
    let size =
        |depth: usize| wgpu::Extent3d { width: nx as u32, height: ny as u32, depth_or_array_layers: depth as u32 };
    let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("ct volume"),
        size: size(nz),
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format: wgpu::TextureFormat::R32Float,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    let slice = nx * ny;
    let per_slab = (16 << 20) / (4 * slice).max(1);
    for (k, slab) in field.data().chunks(slice * per_slab.max(1)).enumerate() {
        gpu.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &texture,
                mip_level: 0,
                origin: wgpu::Origin3d { x: 0, y: 0, z: (k * per_slab.max(1)) as u32 },
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(slab),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * nx as u32),
                rows_per_image: Some(ny as u32),
            },
            size(slab.len() / slice),
        );
    }
    gpu.check()?;
    Ok(texture)
}
