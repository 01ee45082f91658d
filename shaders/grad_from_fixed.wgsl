// dL/dF from the render's integer sums (fixed_point.wgsl, appended by the host) into the f32
// lattice the 3-D TV adds to and the contractions read. One invocation per lattice node.

struct Shape {
    nodes: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Shape;
// Eight words per node: four chunk sums of its positive addends, four of its negative ones.
@group(0) @binding(1) var<storage, read> dense_grad_fixed: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> dense_grad: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= u.nodes) {
        return;
    }
    dense_grad[i] = fixed_value(dense_grad_fixed[2u * i], dense_grad_fixed[2u * i + 1u]);
}
