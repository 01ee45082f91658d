// One FISTA step of the dense fit at every lattice node (mirrors the pass of
// train::dense_tv::cpu::CpuFista): the gradient of E at the look-ahead point,
//   g = Aᵀ(Aσ̂ − τ)/B + λ/N³ · Σ_a (p_a(i − e_a) − p_a(i)),
// a projected step σ' = max(σ̂ − g·step, 0) with the node's step from the majoriser's
// curvature, 1/((AᵀA·1)/B + λ/N³ (6/m_i + 2 Σ_a 1/m_{i−e_a})), and the next look-ahead
// σ̂ = σ' + momentum (σ' − σ). Each workgroup also writes its sums of (σ' − σ)², σ'² and the
// restart test (σ̂ − σ')(σ' − σ)/step for fista_state.wgsl. Once the solve has settled the
// step changes nothing.

struct FistaStep {
    n: u32,
    nodes: u32,
    _pad0: u32,
    _pad1: u32,
    // 1 / B, B the rays that meet the box
    per_ray: f32,
    // λ / N³
    tv_weight: f32,
    _pad2: u32,
    _pad3: u32,
}

@group(0) @binding(0) var<uniform> u: FistaStep;
// Aᵀ(Aσ̂ − τ), from sheet_back.wgsl.
@group(0) @binding(1) var<storage, read> back: array<f32>;
// p and 1/m at σ̂, from tv_direction.wgsl.
@group(0) @binding(2) var<storage, read> direction: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> data_curvature: array<f32>;
@group(0) @binding(4) var<storage, read> state: State;
@group(0) @binding(5) var<storage, read_write> ahead: array<f32>;
@group(0) @binding(6) var<storage, read_write> sigma: array<f32>;
// Three sums per workgroup.
@group(0) @binding(7) var<storage, read_write> partials: array<f32>;

var<workgroup> lanes: array<vec3<f32>, 64>;

@compute @workgroup_size(64)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = id.x + id.y * groups.x * 64u;
    var share = vec3<f32>(0.0);
    if (i < u.nodes && state.settled == 0u) {
        let n = u.n;
        let coord = vec3<u32>(i % n, (i / n) % n, i / (n * n));
        let stride = vec3<u32>(1u, n, n * n);
        let own = direction[i];
        var tv = 0.0;
        var curvature = 6.0 * own.w;
        for (var axis = 0u; axis < 3u; axis++) {
            var below = vec4<f32>(0.0);
            if (coord[axis] > 0u) {
                below = direction[i - stride[axis]];
            }
            tv += below[axis] - own[axis];
            curvature += 2.0 * below.w;
        }
        let g = back[i] * u.per_ray + u.tv_weight * tv;
        let step = 1.0 / (data_curvature[i] + u.tv_weight * curvature);
        let look = ahead[i];
        let next = max(look - step * g, 0.0);
        let change = next - sigma[i];
        share = vec3<f32>(change * change, next * next, (look - next) * change / step);
        ahead[i] = next + state.momentum * change;
        sigma[i] = next;
    }
    lanes[lane] = share;
    for (var half = 32u; half > 0u; half /= 2u) {
        workgroupBarrier();
        if (lane < half) {
            lanes[lane] += lanes[lane + half];
        }
    }
    if (lane == 0u) {
        let slot = 3u * (group.x + group.y * groups.x);
        partials[slot] = lanes[0].x;
        partials[slot + 1u] = lanes[0].y;
        partials[slot + 2u] = lanes[0].z;
    }
}
