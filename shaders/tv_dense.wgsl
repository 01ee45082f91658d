// 3-D TV of the composed field F (mirrors train::regularize::tv_dense): the mean absolute
// forward difference along x, y and z, over N² · (N − 1) differences each. One invocation per
// lattice node (index x + N·(y + N·z)): it adds the derivative of the (up to) six differences
// it belongs to, scaled, to dF — after the render's scatter, before the contraction — and
// writes the penalties of the three it starts (+x, +y, +z) to its workgroup's share.

struct TvDense {
    n: u32,
    // N³
    nodes: u32,
    _pad0: u32,
    _pad1: u32,
    // weight / (N² · (N − 1))
    scale: f32,
    // 1 / (N² · (N − 1))
    per_difference: f32,
    _pad2: u32,
    _pad3: u32,
}

@group(0) @binding(0) var<uniform> u: TvDense;
@group(0) @binding(1) var<storage, read> dense: array<f32>;
@group(0) @binding(2) var<storage, read_write> dense_grad: array<f32>;
// binding 3: partials, with write_workgroup_sum, in the appended workgroup_sum.wgsl.

@compute @workgroup_size(64)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let j = id.x + id.y * groups.x * 64u;
    var share = 0.0;
    if (j < u.nodes) {
        let n = u.n;
        let coord = vec3<u32>(j % n, (j / n) % n, j / (n * n));
        let stride = vec3<u32>(1u, n, n * n);
        let here = dense[j];
        var g = 0.0;
        for (var axis = 0u; axis < 3u; axis++) {
            if (coord[axis] + 1u < n) {
                let d = dense[j + stride[axis]] - here;
                g -= u.scale * sign_of(d);
                share += abs(d);
            }
            if (coord[axis] > 0u) {
                g += u.scale * sign_of(here - dense[j - stride[axis]]);
            }
        }
        dense_grad[j] += g;
        share *= u.per_difference;
    }
    write_workgroup_sum(share, lane, group, groups);
}
