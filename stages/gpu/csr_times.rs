//! Host of `shaders/csr_times.wgsl`: a sparse matrix in compressed rows times a vector
//! (`train::dense_tv::Csr::times`), one invocation per row. The dense fit runs it as its
//! projection `Aσ̂ − τ` and its back-projection `Aᵀr`.

use super::buffers;
use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::dense_tv::Csr;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/csr_times.wgsl");

/// `struct CsrTimes` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Uniforms {
    pub rows: u32,
    pub subtract: u32,
    pub _pad: [u32; 2],
}

/// A [`Csr`] on the device: u32 offsets and indices, f32 weights.
pub struct DeviceCsr {
    offsets: wgpu::Buffer,
    index: wgpu::Buffer,
    weight: wgpu::Buffer,
    rows: usize,
}

impl DeviceCsr {
    /// Uploads `matrix` (`what` names it in errors: its entries must fit u32 offsets and one buffer each).
    pub fn upload(gpu: &Gpu, what: &str, matrix: &Csr) -> anyhow::Result<DeviceCsr> {
        let entries = matrix.index.len();
        if u32::try_from(entries).is_err() {
            anyhow::bail!(
                "{what} has {entries} entries, more than the GPU kernel's u32 offsets hold: use backend = \"cpu\""
            );
        }
        let offsets: Vec<u32> = matrix.offsets.iter().map(|&o| o as u32).collect();
        let weight: Vec<f32> = matrix.weight.iter().map(|&w| w as f32).collect();
        Ok(DeviceCsr {
            offsets: buffers::storage(gpu, &format!("{what} offsets"), &offsets)?,
            index: buffers::storage(gpu, &format!("{what} indices"), &matrix.index)?,
            weight: buffers::storage(gpu, &format!("{what} weights"), &weight)?,
            rows: matrix.offsets.len() - 1,
        })
    }
}

pub struct CsrTimes {
    kernel: Kernel,
}

impl CsrTimes {
    pub fn new(gpu: &Gpu) -> anyhow::Result<CsrTimes> {
        let read = Binding::Storage { read_only: true };
        let bindings = [Binding::Uniform, read, read, read, read, read, Binding::Storage { read_only: false }];
        Ok(CsrTimes { kernel: Kernel::new(gpu, "csr_times", SOURCE, &bindings)? })
    }

    /// Binds `y = M x`, or with `target` `y = M x − target` on the rows that have entries and 0
    /// on the others. The returned uniform buffer must live as long as the binding.
    pub fn bind(
        &self,
        gpu: &Gpu,
        matrix: &DeviceCsr,
        x: &wgpu::Buffer,
        target: Option<&wgpu::Buffer>,
        y: &wgpu::Buffer,
    ) -> anyhow::Result<(Bound, wgpu::Buffer)> {
        let values = Uniforms { rows: matrix.rows as u32, subtract: u32::from(target.is_some()), _pad: [0; 2] };
        let uniforms = buffers::uniform(gpu, "csr_times", &values);
        let resources = [
            whole(&uniforms),
            whole(&matrix.offsets),
            whole(&matrix.index),
            whole(&matrix.weight),
            whole(x),
            whole(target.unwrap_or(x)),
            whole(y),
        ];
        let group = self.kernel.bind(gpu, &resources);
        Ok((Bound { group, groups: groups(gpu, matrix.rows as u64, WORKGROUP)? }, uniforms))
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.kernel.record(encoder, bound);
    }
}
