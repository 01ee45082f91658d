// Appended by the hosts of the regularisers (l1, tv, tv_dense): binding 3, the per-workgroup
// partial sums of the value, which the host adds in f64 when a row is logged; and the
// subgradient sign they share.

@group(0) @binding(3) var<storage, read_write> partials: array<f32>;

var<workgroup> lanes: array<f32, 64>;

// −1, 0 or 1 (0 at the kink, as the CPU's subgradient).
fn sign_of(x: f32) -> f32 {
    return select(0.0, 1.0, x > 0.0) - select(0.0, 1.0, x < 0.0);
}

// Sums every invocation's `share` over its workgroup (a fixed tree of 64 lanes) into the
// workgroup's slot of `partials`. Every invocation of the workgroup must call it: it holds
// barriers.
fn write_workgroup_sum(share: f32, lane: u32, group: vec3<u32>, groups: vec3<u32>) {
    lanes[lane] = share;
    for (var half = 32u; half > 0u; half /= 2u) {
        workgroupBarrier();
        if (lane < half) {
            lanes[lane] += lanes[lane + half];
        }
    }
    if (lane == 0u) {
        partials[group.x + group.y * groups.x] = lanes[0];
    }
}
