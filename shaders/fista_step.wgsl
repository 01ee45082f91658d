// One FISTA step of the dense fit at every lattice node (mirrors the step of
// train::dense_tv::CpuFista): the gradient of E at the look-ahead point,
//   g = Aᵀ(Aσ̂ − τ)/B + λ/N³ · Σ_a (p_a(i − e_a) − p_a(i)),
// a projected step σ' = max(σ̂ − g/L, 0), and the next look-ahead σ̂ = σ' + m (σ' − σ).
// One invocation per node: it reads p at its lower neighbours but writes only its own σ and σ̂.

struct FistaStep {
    n: u32,
    // N³
    nodes: u32,
    _pad0: u32,
    _pad1: u32,
    // 1 / B, B the rays that meet the box
    per_ray: f32,
    // λ / N³
    tv_weight: f32,
    // 1 / L
    step: f32,
    // (t − 1) / t', rewritten by the host before every step
    momentum: f32,
}

@group(0) @binding(0) var<uniform> u: FistaStep;
// Aᵀ(Aσ̂ − τ), from csr_times.wgsl.
@group(0) @binding(1) var<storage, read> back: array<f32>;
// p at σ̂, from tv_direction.wgsl.
@group(0) @binding(2) var<storage, read> direction: array<f32>;
@group(0) @binding(3) var<storage, read_write> ahead: array<f32>;
@group(0) @binding(4) var<storage, read_write> sigma: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= u.nodes) {
        return;
    }
    let n = u.n;
    let coord = vec3<u32>(i % n, (i / n) % n, i / (n * n));
    let stride = vec3<u32>(1u, n, n * n);
    var tv = 0.0;
    for (var axis = 0u; axis < 3u; axis++) {
        var below = 0.0;
        if (coord[axis] > 0u) {
            below = direction[3u * (i - stride[axis]) + axis];
        }
        tv += below - direction[3u * i + axis];
    }
    let g = back[i] * u.per_ray + u.tv_weight * tv;
    let next = max(ahead[i] - u.step * g, 0.0);
    ahead[i] = next + u.momentum * (next - sigma[i]);
    sigma[i] = next;
}
