//! Host of `shaders/sheet_back.wgsl`: the dense fit's back-projection for one view along a
//! lattice axis (`train::projector::sheet::Sheet::back_project`), one invocation per node,
//! gathering through the view's row and column runs.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::sheet_project::DeviceSheet;
use super::Gpu;

const SOURCE: &str = include_str!("../../shaders/sheet_back.wgsl");

pub struct SheetBack {
    kernel: Kernel,
}

impl SheetBack {
    pub fn new(gpu: &Gpu) -> anyhow::Result<SheetBack> {
        let read = Binding::Storage { read_only: true };
        let bindings = [Binding::Uniform, read, read, read, read, read, read, Binding::Storage { read_only: false }];
        Ok(SheetBack { kernel: Kernel::new(gpu, "sheet_back", SOURCE, &bindings)? })
    }

    /// Binds `back` = (or +=, unless `sheet` is the first view) `sheet`'s Aᵀ `residual` over
    /// the `nodes` of the lattice.
    pub fn bind(
        &self,
        gpu: &Gpu,
        sheet: &DeviceSheet,
        residual: &wgpu::Buffer,
        back: &wgpu::Buffer,
        nodes: usize,
    ) -> anyhow::Result<Bound> {
        let resources = [
            whole(&sheet.uniforms),
            whole(&sheet.rows),
            whole(&sheet.columns),
            whole(&sheet.weights),
            whole(&sheet.row_runs),
            whole(&sheet.column_runs),
            whole(residual),
            whole(back),
        ];
        let group = self.kernel.bind(gpu, &resources);
        Ok(Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
