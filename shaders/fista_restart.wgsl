// After fista_state.wgsl: where it restarted the momentum, the look-ahead point is σ itself.

struct Nodes {
    nodes: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Nodes;
@group(0) @binding(1) var<storage, read> state: State;
@group(0) @binding(2) var<storage, read> sigma: array<f32>;
@group(0) @binding(3) var<storage, read_write> ahead: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i < u.nodes && state.restarted != 0u) {
        ahead[i] = sigma[i];
    }
}
