// The dense fit's back-projection Aᵀr for one view along a lattice axis (mirrors
// train::projector::sheet's back_project): one invocation per lattice node, which gathers from
// the pixel rows whose cell starts at its row index (their lower weight) or the one before
// (their upper weight), and within each from the pixel columns alike: no two invocations write
// one node, so the sum does not depend on the dispatch.

struct Sheet {
    n: u32,
    width: u32,
    height: u32,
    first_ray: u32,
    plane: u32,
    row_stride: u32,
    column: u32,
    // 0 writes the view's Aᵀr, 1 adds it to what the views before wrote.
    accumulate: u32,
}

struct Cell {
    index: u32,
    lower: f32,
    upper: f32,
}

@group(0) @binding(0) var<uniform> u: Sheet;
@group(0) @binding(1) var<storage, read> rows: array<Cell>;
@group(0) @binding(2) var<storage, read> columns: array<Cell>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
// Per plane k and lattice index x (k·n + x): the pixel rows, and the pixel columns, whose cell
// starts at x, as [start, end).
@group(0) @binding(4) var<storage, read> row_runs: array<vec2<u32>>;
@group(0) @binding(5) var<storage, read> column_runs: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> residual: array<f32>;
@group(0) @binding(7) var<storage, read_write> back: array<f32>;

// Σ over the pixel row j's columns in `run` of their `upper` (or lower) weight × r·w.
fn row_sum(j: u32, k: u32, run: vec2<u32>, upper: bool) -> f32 {
    var sum = 0.0;
    for (var i = run.x; i < run.y; i++) {
        let c = columns[k * u.width + i];
        let pixel = j * u.width + i;
        sum += select(c.lower, c.upper, upper) * residual[u.first_ray + pixel] * weights[pixel];
    }
    return sum;
}

// What the pixel row j gives the node at column index x of plane k.
fn from_row(j: u32, k: u32, x: u32) -> f32 {
    var sum = row_sum(j, k, column_runs[k * u.n + x], false);
    if (x > 0u) {
        sum += row_sum(j, k, column_runs[k * u.n + x - 1u], true);
    }
    return sum;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let node = id.x + id.y * groups.x * 64u;
    let n = u.n;
    if (node >= n * n * n) {
        return;
    }
    let k = (node / u.plane) % n;
    let y = (node / u.row_stride) % n;
    let x = (node / u.column) % n;
    var value = 0.0;
    let at = row_runs[k * n + y];
    for (var j = at.x; j < at.y; j++) {
        value += rows[k * u.height + j].lower * from_row(j, k, x);
    }
    if (y > 0u) {
        let below = row_runs[k * n + y - 1u];
        for (var j = below.x; j < below.y; j++) {
            value += rows[k * u.height + j].upper * from_row(j, k, x);
        }
    }
    if (u.accumulate != 0u) {
        back[node] += value;
    } else {
        back[node] = value;
    }
}
