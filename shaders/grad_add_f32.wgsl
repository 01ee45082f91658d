// dL/dF for render.wgsl, with native float atomics (wgpu's SHADER_FLOAT32_ATOMIC).
@group(0) @binding(5) var<storage, read_write> dense_grad: array<atomic<f32>>;

fn add_grad(i: u32, v: f32) {
    atomicAdd(&dense_grad[i], v);
}
