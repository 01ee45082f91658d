// F = Σ_r P0_r ⊗ L0_r + P1_r ⊗ L1_r + P2_r ⊗ L2_r on the node lattice (mirrors
// train::field::VmField::compose): one invocation per node, index x + N·(y + N·z).
//
// `factors` is every factor back to back, as VmField::params() lists them: planes 0, 1, 2
// (rank × N × N, index r·N² + u + N·v) then lines 0, 1, 2 (rank × N, index r·N + w), for the
// pairs XY⊗Z, XZ⊗Y, YZ⊗X.

struct Shape {
    n: u32,
    rank: u32,
    nodes: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> shape: Shape;
@group(0) @binding(1) var<storage, read> factors: array<f32>;
@group(0) @binding(2) var<storage, read_write> dense: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= shape.nodes) {
        return;
    }
    let n = shape.n;
    let nn = n * n;
    let x = i % n;
    let y = (i / n) % n;
    let z = i / nn;
    let plane = shape.rank * nn;
    let line = shape.rank * n;
    let lines = 3u * plane;
    var f = 0.0;
    for (var r = 0u; r < shape.rank; r++) {
        f += factors[r * nn + x + n * y] * factors[lines + r * n + z];
        f += factors[plane + r * nn + x + n * z] * factors[lines + line + r * n + y];
        f += factors[2u * plane + r * nn + y + n * z] * factors[lines + 2u * line + r * n + x];
    }
    dense[i] = f;
}
