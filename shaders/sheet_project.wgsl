// The dense fit's projection for one view along a lattice axis (mirrors train::projector::sheet's
// project): one invocation per pixel, summing over the planes the bilinear read of its crossing,
// from the tables of each plane's row and column cells; then the residual w·Σ − τ on a pixel
// whose ray meets the box (w > 0), 0 on the others.

struct Sheet {
    n: u32,
    width: u32,
    height: u32,
    // The row of A of the view's first pixel.
    first_ray: u32,
    // Node-index strides of the plane axis, the row axis and the column axis.
    plane: u32,
    row_stride: u32,
    column: u32,
    // sheet_back: 0 writes the view's Aᵀr, 1 adds it.
    accumulate: u32,
}

struct Cell {
    index: u32,
    lower: f32,
    upper: f32,
}

@group(0) @binding(0) var<uniform> u: Sheet;
// Per plane k and pixel row j (k·height + j), and per plane and pixel column (k·width + i).
@group(0) @binding(1) var<storage, read> rows: array<Cell>;
@group(0) @binding(2) var<storage, read> columns: array<Cell>;
// Per pixel: s × the ray's length between planes, 0 where the ray misses the box.
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read> sigma: array<f32>;
@group(0) @binding(5) var<storage, read> target_depth: array<f32>;
@group(0) @binding(6) var<storage, read_write> residual: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let pixel = id.x + id.y * groups.x * 64u;
    if (pixel >= u.width * u.height) {
        return;
    }
    let ray = u.first_ray + pixel;
    let w = weights[pixel];
    if (w == 0.0) {
        residual[ray] = 0.0;
        return;
    }
    let i = pixel % u.width;
    let j = pixel / u.width;
    var sum = 0.0;
    for (var k = 0u; k < u.n; k++) {
        let r = rows[k * u.height + j];
        if (r.lower == 0.0 && r.upper == 0.0) {
            continue;
        }
        let c = columns[k * u.width + i];
        let base = k * u.plane + r.index * u.row_stride + c.index * u.column;
        let low = r.lower * sigma[base] + r.upper * sigma[base + u.row_stride];
        let high = r.lower * sigma[base + u.column] + r.upper * sigma[base + u.row_stride + u.column];
        sum += c.lower * low + c.upper * high;
    }
    residual[ray] = w * sum - target_depth[ray];
}
