//! Host of `shaders/sheet_project.wgsl`: the dense fit's projection and residual for one view
//! along a lattice axis (`train::projector::sheet::Sheet::project`), one invocation per pixel;
//! and [`DeviceSheet`], a view's tables on the device, which `sheet_back` reads too.

use super::buffers;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::projector::sheet::Sheet;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/sheet_project.wgsl");

/// `struct Sheet` of the shaders.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub n: u32,
    pub width: u32,
    pub height: u32,
    pub first_ray: u32,
    pub plane: u32,
    pub row_stride: u32,
    pub column: u32,
    pub accumulate: u32,
}

/// A view's tables on the device, and its uniforms (`accumulate` set unless it is the first).
pub struct DeviceSheet {
    pub rows: wgpu::Buffer,
    pub columns: wgpu::Buffer,
    pub weights: wgpu::Buffer,
    pub row_runs: wgpu::Buffer,
    pub column_runs: wgpu::Buffer,
    pub uniforms: wgpu::Buffer,
    pub pixels: usize,
}

impl DeviceSheet {
    pub fn upload(gpu: &Gpu, sheet: &Sheet, n: usize, first: bool) -> anyhow::Result<DeviceSheet> {
        let stride = |axis: usize| n.pow(axis as u32) as u32;
        let values = Uniforms {
            n: n as u32,
            width: sheet.width as u32,
            height: sheet.height as u32,
            first_ray: sheet.first_ray as u32,
            plane: stride(sheet.axis),
            row_stride: stride(sheet.row_axis),
            column: stride(sheet.column_axis),
            accumulate: u32::from(!first),
        };
        Ok(DeviceSheet {
            rows: buffers::storage(gpu, "a view's row cells", &sheet.rows)?,
            columns: buffers::storage(gpu, "a view's column cells", &sheet.columns)?,
            weights: buffers::storage(gpu, "a view's ray weights", &sheet.weights)?,
            row_runs: buffers::storage(gpu, "a view's row runs", &sheet.row_runs)?,
            column_runs: buffers::storage(gpu, "a view's column runs", &sheet.column_runs)?,
            uniforms: buffers::uniform(gpu, "sheet", &values),
            pixels: sheet.width * sheet.height,
        })
    }
}

pub struct SheetProject {
    kernel: Kernel,
}

impl SheetProject {
    pub fn new(gpu: &Gpu) -> anyhow::Result<SheetProject> {
        let read = Binding::Storage { read_only: true };
        let bindings = [Binding::Uniform, read, read, read, read, read, Binding::Storage { read_only: false }];
        Ok(SheetProject { kernel: Kernel::new(gpu, "sheet_project", SOURCE, &bindings)? })
    }

    /// Binds `residual` = A σ − τ over `sheet`'s pixels (0 where a ray misses the box).
    pub fn bind(
        &self,
        gpu: &Gpu,
        sheet: &DeviceSheet,
        sigma: &wgpu::Buffer,
        target: &wgpu::Buffer,
        residual: &wgpu::Buffer,
    ) -> anyhow::Result<Bound> {
        let resources = [
            whole(&sheet.uniforms),
            whole(&sheet.rows),
            whole(&sheet.columns),
            whole(&sheet.weights),
            whole(sigma),
            whole(target),
            whole(residual),
        ];
        let group = self.kernel.bind(gpu, &resources);
        Ok(Bound { group, groups: groups(gpu, sheet.pixels as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
