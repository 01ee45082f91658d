//! Buffers: uploads, zeroed storage, uniforms, and reading results back to the host.

use super::Gpu;
use bytemuck::Pod;
use wgpu::util::DeviceExt;

/// Storage usages: kernels read and write it, the host writes it and copies out of it.
const STORAGE: wgpu::BufferUsages =
    wgpu::BufferUsages::STORAGE.union(wgpu::BufferUsages::COPY_DST).union(wgpu::BufferUsages::COPY_SRC);

/// Fails unless one binding of `bytes` fits the device (the error names `what`).
pub fn check_size(gpu: &Gpu, what: &str, bytes: u64) -> anyhow::Result<()> {
    let max = gpu.limits.max_storage_buffer_binding_size.min(gpu.limits.max_buffer_size);
    if bytes > max {
        anyhow::bail!(
            "{what} needs {:.1} MiB in one GPU buffer; {} allows {:.1} MiB: use backend = \"cpu\" for this size",
            bytes as f64 / 1048576.0,
            gpu.info.name,
            max as f64 / 1048576.0
        );
    }
    Ok(())
}

/// A storage buffer holding `data` (at least 4 bytes: empty bindings are invalid).
pub fn storage<T: Pod>(gpu: &Gpu, label: &str, data: &[T]) -> anyhow::Result<wgpu::Buffer> {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    check_size(gpu, label, bytes.len() as u64)?;
    if bytes.is_empty() {
        return zeroed(gpu, label, 4);
    }
    Ok(gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytes,
        usage: STORAGE,
    }))
}

/// A zero-filled storage buffer of `bytes` (at least 4).
pub fn zeroed(gpu: &Gpu, label: &str, bytes: u64) -> anyhow::Result<wgpu::Buffer> {
    check_size(gpu, label, bytes)?;
    Ok(gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(4).next_multiple_of(4),
        usage: STORAGE,
        mapped_at_creation: false,
    }))
}

/// A uniform buffer holding `value` (the host rewrites it with `queue.write_buffer`).
pub fn uniform<T: Pod>(gpu: &Gpu, label: &str, value: &T) -> wgpu::Buffer {
    gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::bytes_of(value),
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}

/// Copies the first `counts[i]` elements of each of `sources` to the host, after everything
/// submitted so far: the one place results come back (log rows, the end of a fit, tests).
pub fn read<T: Pod>(gpu: &Gpu, sources: &[(&wgpu::Buffer, usize)]) -> anyhow::Result<Vec<Vec<T>>> {
    let size = std::mem::size_of::<T>() as u64;
    let total: u64 = sources.iter().map(|&(_, n)| n as u64 * size).sum();
    let staging = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read-back"),
        size: total.max(4),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    let mut at = 0;
    for &(buffer, n) in sources {
        let bytes = n as u64 * size;
        if bytes > 0 {
            encoder.copy_buffer_to_buffer(buffer, 0, &staging, at, bytes);
        }
        at += bytes;
    }
    gpu.queue.submit([encoder.finish()]);
    let (sender, receiver) = std::sync::mpsc::channel();
    staging.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = sender.send(r);
    });
    gpu.wait()?;
    receiver
        .recv()
        .map_err(|_| anyhow::anyhow!("GPU read-back was never answered"))?
        .map_err(|e| anyhow::anyhow!("GPU read-back failed: {e}"))?;
    let view = staging.get_mapped_range(..).map_err(|e| anyhow::anyhow!("GPU read-back: {e}"))?;
    let all: &[T] = bytemuck::cast_slice(&view[..total as usize]);
    let mut out = Vec::with_capacity(sources.len());
    let mut from = 0;
    for &(_, n) in sources {
        out.push(all[from..from + n].to_vec());
        from += n;
    }
    drop(view);
    staging.unmap();
    Ok(out)
}
