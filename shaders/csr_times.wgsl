// y = M x for a sparse matrix M in compressed rows (mirrors train::dense_tv's Csr::times), one
// invocation per row, each row summed in column order (so the result does not depend on the
// dispatch). The dense fit's projection sets `subtract`: a row with entries (a ray that meets
// the box) gives its sum less target[row], an empty row 0 — the residual τ̂ − τ. Its
// back-projection Aᵀr leaves it unset (and binds x again as the unread target).

struct CsrTimes {
    rows: u32,
    // 1: y = M x − target on rows with entries, 0 on empty rows; 0: y = M x.
    subtract: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> u: CsrTimes;
// rows + 1 offsets into index/weight.
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> index: array<u32>;
@group(0) @binding(3) var<storage, read> weight: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read> target_depth: array<f32>;
@group(0) @binding(6) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let row = id.x + id.y * groups.x * 64u;
    if (row >= u.rows) {
        return;
    }
    let start = offsets[row];
    let end = offsets[row + 1u];
    var sum = 0.0;
    for (var k = start; k < end; k++) {
        sum += weight[k] * x[index[k]];
    }
    if (u.subtract != 0u) {
        sum = select(0.0, sum - target_depth[row], end > start);
    }
    y[row] = sum;
}
