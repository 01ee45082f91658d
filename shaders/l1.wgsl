// L1 = Σ over the 3 planes and 3 lines of mean |value| (mirrors train::regularize::l1): adds
// weight/len · sign(x) to each parameter's gradient, and writes each workgroup's share of the
// value, Σ |x| / len, to `partials` (summed on the host, in f64, when a row is logged).

struct L1 {
    // 3 · rank · N² + 3 · rank · N
    entries: u32,
    // where the lines start: 3 · rank · N²
    lines: u32,
    plane_len: u32,
    line_len: u32,
    weight: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: L1;
@group(0) @binding(1) var<storage, read> factors: array<f32>;
@group(0) @binding(2) var<storage, read_write> grad: array<f32>;
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
    if (j < u.entries) {
        let len = f32(select(u.plane_len, u.line_len, j >= u.lines));
        let x = factors[j];
        grad[j] += u.weight / len * sign_of(x);
        share = abs(x) / len;
    }
    write_workgroup_sum(share, lane, group, groups);
}
