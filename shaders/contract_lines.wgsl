// dL/dL for every line entry from dL/dF (the line half of train::field::VmField::contract):
// dL_p[r, w] = Σ_{u,v} P_p[r, u, v] · dF[node(p, u, v, w)] — N² terms each, so one workgroup
// per line entry: 64 strided partial sums, then a fixed-order tree (deterministic).
// Writes (not adds) the line part of `grad`.

struct Shape {
    n: u32,
    rank: u32,
    // 3 · rank · N
    entries: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> shape: Shape;
@group(0) @binding(1) var<storage, read> factors: array<f32>;
@group(0) @binding(2) var<storage, read> dense_grad: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;

var<workgroup> partial: array<f32, 64>;

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let e = group.x + group.y * groups.x;
    let n = shape.n;
    let nn = n * n;
    let line = shape.rank * n;
    // Out-of-range groups still reach every barrier (uniform control flow) and write nothing.
    let in_range = e < shape.entries;
    let p = min(e / line, 2u);
    let r = (e % line) / n;
    let w = e % n;
    let plane = shape.rank * nn;
    let factor = p * plane + r * nn;
    var sum = 0.0;
    if (in_range) {
        for (var uv = lane; uv < nn; uv += 64u) {
            let u = uv % n;
            let v = uv / n;
            var node = uv + nn * w; // XY⊗Z: (x, y) = (u, v), z = w
            if (p == 1u) {
                node = u + n * w + nn * v; // XZ⊗Y: (x, z) = (u, v), y = w
            } else if (p == 2u) {
                node = w + n * u + nn * v; // YZ⊗X: (y, z) = (u, v), x = w
            }
            sum += factors[factor + uv] * dense_grad[node];
        }
    }
    partial[lane] = sum;
    for (var half = 32u; half > 0u; half /= 2u) {
        workgroupBarrier();
        if (lane < half) {
            partial[lane] += partial[lane + half];
        }
    }
    if (in_range && lane == 0u) {
        grad[3u * plane + e] = partial[0];
    }
}
