// The smoothed TV's normalised differences p = ∇σ / m and 1/m, m = √(|∇σ|² + ε²), at every
// lattice node (mirrors train::dense_tv::tv's PlaneDirections): forward differences in lattice
// steps, none across the far faces. One invocation per node (index x + N·(y + N·z)), four
// floats a node (p, then 1/m). fista_step.wgsl takes p's backward divergence and the
// majoriser's curvature from 1/m.

struct TvDirection {
    n: u32,
    // N³
    nodes: u32,
    epsilon: f32,
    _pad0: u32,
}

@group(0) @binding(0) var<uniform> u: TvDirection;
@group(0) @binding(1) var<storage, read> sigma: array<f32>;
@group(0) @binding(2) var<storage, read_write> direction: array<vec4<f32>>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= u.nodes) {
        return;
    }
    let n = u.n;
    let coord = vec3<u32>(i % n, (i / n) % n, i / (n * n));
    let stride = vec3<u32>(1u, n, n * n);
    var d = vec3<f32>(0.0);
    for (var axis = 0u; axis < 3u; axis++) {
        if (coord[axis] + 1u < n) {
            d[axis] = sigma[i + stride[axis]] - sigma[i];
        }
    }
    let inverse = 1.0 / sqrt(dot(d, d) + u.epsilon * u.epsilon);
    direction[i] = vec4<f32>(d * inverse, inverse);
}
