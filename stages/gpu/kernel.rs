//! A compute pipeline with an explicit bind group layout, and 1-D dispatch sizes.
//!
//! Every kernel binds group 0 only, in the order its shader declares the bindings; the host
//! file of a shader lists the same bindings as [`Binding`]s, so the two read side by side.

use super::Gpu;

/// Threads per workgroup of every 1-D kernel (`@workgroup_size(64)` in the shaders).
pub const WORKGROUP: u32 = 64;

/// `shaders/workgroup_sum.wgsl`, which the regularisers' hosts append to their shader: the
/// `partials` binding and the workgroup sum that fills it.
pub const WORKGROUP_SUM: &str = include_str!("../../shaders/workgroup_sum.wgsl");

/// One binding of a kernel's group 0.
#[derive(Debug, Clone, Copy)]
pub enum Binding {
    Uniform,
    Storage {
        read_only: bool,
    },
    /// A `texture_3d<f32>` read with `textureLoad` (r32float: not filterable).
    Volume,
}

pub struct Kernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    name: &'static str,
}

impl Kernel {
    /// Compiles `source` (entry point `main`) with `bindings` at 0, 1, … of group 0.
    pub fn new(gpu: &Gpu, name: &'static str, source: &str, bindings: &[Binding]) -> anyhow::Result<Kernel> {
        let entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: match *b {
                    Binding::Uniform => wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    Binding::Storage { read_only } => wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    Binding::Volume => wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D3,
                        multisampled: false,
                    },
                },
                count: None,
            })
            .collect();
        let device = &gpu.device;
        let layout =
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(name), entries: &entries });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(name),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(name),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        gpu.wait().map_err(|e| e.context(format!("compiling shaders/{name}.wgsl")))?;
        Ok(Kernel { pipeline, layout, name })
    }

    /// A bind group of `resources` in binding order.
    pub fn bind(&self, gpu: &Gpu, resources: &[wgpu::BindingResource]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .iter()
            .enumerate()
            .map(|(i, r)| wgpu::BindGroupEntry { binding: i as u32, resource: r.clone() })
            .collect();
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.name),
            layout: &self.layout,
            entries: &entries,
        })
    }

    /// Records one dispatch of `bound`, in a pass of its own (passes order each kernel's reads
    /// after the previous kernel's writes).
    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        let mut pass =
            encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(self.name), timestamp_writes: None });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bound.group, &[]);
        pass.dispatch_workgroups(bound.groups[0], bound.groups[1], bound.groups[2]);
    }
}

/// A kernel's resources and its dispatch size, ready to record.
pub struct Bound {
    pub group: wgpu::BindGroup,
    pub groups: [u32; 3],
}

/// A whole buffer as a binding.
pub fn whole(buffer: &wgpu::Buffer) -> wgpu::BindingResource<'_> {
    buffer.as_entire_binding()
}

/// Workgroups for `items` work items, `per_group` each: `[x, y, 1]` with x within the
/// per-dimension limit. Shaders linearise the group as `group.x + group.y · num_workgroups.x`.
pub fn groups(gpu: &Gpu, items: u64, per_group: u32) -> anyhow::Result<[u32; 3]> {
    let needed = items.div_ceil(u64::from(per_group)).max(1);
    let max = u64::from(gpu.limits.max_compute_workgroups_per_dimension);
    let y = needed.div_ceil(max);
    if y > max {
        anyhow::bail!("{items} work items exceed the GPU's dispatch limit ({max}² workgroups)");
    }
    Ok([needed.div_ceil(y) as u32, y as u32, 1])
}

/// The shape five kernels share (contract planes and lines, L1, TV, 3-D TV): a uniform block,
/// then three storage buffers, and a dispatch of `items_per_group` work items per workgroup
/// (`WORKGROUP` for one invocation per item, 1 for one workgroup per item). Their host files
/// keep what differs: the uniform struct and which buffers the shader only reads.
pub struct ItemKernel {
    kernel: Kernel,
    items_per_group: u32,
}

impl ItemKernel {
    /// Compiles `source` with bindings `[uniform, storage × 3]`, the storage buffers read only
    /// where `read_only` says so.
    pub fn new(
        gpu: &Gpu,
        name: &'static str,
        source: &str,
        read_only: [bool; 3],
        items_per_group: u32,
    ) -> anyhow::Result<ItemKernel> {
        let [a, b, c] = read_only.map(|read_only| Binding::Storage { read_only });
        Ok(ItemKernel { kernel: Kernel::new(gpu, name, source, &[Binding::Uniform, a, b, c])?, items_per_group })
    }

    /// Binds `uniforms` and `storage` (in the shader's order) for a dispatch over `items`.
    pub fn bind(
        &self,
        gpu: &Gpu,
        uniforms: &wgpu::Buffer,
        storage: [&wgpu::Buffer; 3],
        items: u32,
    ) -> anyhow::Result<Bound> {
        let [a, b, c] = storage;
        let group = self.kernel.bind(gpu, &[whole(uniforms), whole(a), whole(b), whole(c)]);
        Ok(Bound { group, groups: groups(gpu, u64::from(items), self.items_per_group)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
