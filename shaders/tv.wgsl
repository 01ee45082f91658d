// TV of the three density planes (mirrors train::regularize::tv): per component, the mean
// horizontal plus the mean vertical difference penalty, |d| ("l1") or d² ("l2"), over
// rank · N · (N − 1) differences each. One invocation per plane entry: it gathers the
// derivative of the (up to) four differences it belongs to, in the CPU's order, and writes
// the penalties of the two it starts (right, down) to its workgroup's share of the value.

struct Tv {
    n: u32,
    // 3 · rank · N²
    entries: u32,
    // 1: squared differences ("l2"); 0: absolute ("l1")
    squared: u32,
    _pad0: u32,
    // weight / (rank · N · (N − 1))
    scale: f32,
    // 1 / (rank · N · (N − 1))
    per_difference: f32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Tv;
@group(0) @binding(1) var<storage, read> factors: array<f32>;
@group(0) @binding(2) var<storage, read_write> grad: array<f32>;
// binding 3: partials, with write_workgroup_sum, in the appended workgroup_sum.wgsl.

fn penalty(d: f32) -> f32 {
    return select(abs(d), d * d, u.squared == 1u);
}

// d penalty / d d, scaled by the weight per difference.
fn slope(d: f32) -> f32 {
    return u.scale * select(sign_of(d), d + d, u.squared == 1u);
}

@compute @workgroup_size(64)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let j = id.x + id.y * groups.x * 64u;
    var share = 0.0;
    if (j < u.entries) {
        let n = u.n;
        let col = j % n;
        let row = (j / n) % n;
        let x = factors[j];
        var g = grad[j];
        var value = 0.0;
        // Each difference d = b − a adds −slope to a and +slope to b.
        if (col + 1u < n) {
            let d = factors[j + 1u] - x;
            g -= slope(d);
            value += penalty(d);
        }
        if (col > 0u) {
            g += slope(x - factors[j - 1u]);
        }
        if (row + 1u < n) {
            let d = factors[j + n] - x;
            g -= slope(d);
            value += penalty(d);
        }
        if (row > 0u) {
            g += slope(x - factors[j - n]);
        }
        grad[j] = g;
        share = value * u.per_difference;
    }
    write_workgroup_sum(share, lane, group, groups);
}
