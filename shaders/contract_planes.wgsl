// dL/dP for every plane entry from dL/dF (the plane half of train::field::VmField::contract):
// dP_p[r, u, v] = Σ_w dF[node(p, u, v, w)] · L_p[r, w], one invocation per plane entry.
// Writes (not adds) the plane part of `grad`; contract_lines.wgsl writes the line part.

struct Shape {
    n: u32,
    rank: u32,
    // 3 · rank · N²
    entries: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> shape: Shape;
@group(0) @binding(1) var<storage, read> factors: array<f32>;
@group(0) @binding(2) var<storage, read> dense_grad: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = id.x + id.y * groups.x * 64u;
    if (j >= shape.entries) {
        return;
    }
    let n = shape.n;
    let nn = n * n;
    let plane = shape.rank * nn;
    let p = j / plane;
    let r = (j % plane) / nn;
    let u = j % n;
    let v = (j / n) % n;
    // Node (u, v, w) of pair p as base + w · stride: XY⊗Z (x, y | z), XZ⊗Y (x, z | y), YZ⊗X (y, z | x).
    var base = u + n * v;
    var stride = nn;
    if (p == 1u) {
        base = u + nn * v;
        stride = n;
    } else if (p == 2u) {
        base = n * u + nn * v;
        stride = 1u;
    }
    let line = 3u * plane + p * shape.rank * n + r * n;
    var sum = 0.0;
    for (var w = 0u; w < n; w++) {
        sum += dense_grad[base + w * stride] * factors[line + w];
    }
    grad[j] = sum;
}
