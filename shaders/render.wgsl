// One ray per invocation through the composed field F (mirrors train::render::Renderer::batch
// and its scatter): σ = ReLU(F + Δ) trilinear between nodes, Î = exp(−s·step·Σσ); then, when
// training, dL/dσ = 2(Î − I)/B · (−s·step·Î) for each active sample (σ > 0, in a kept cell of
// the alpha mask), scattered onto its cell's 8 nodes with its trilinear weights. With the log
// loss (PhotoLoss::Log) dL/dσ = 2(τ̂ − τ)/B · s·step, τ̂ = s·step·Σσ and τ = −ln max(I, 1e-6).
//
// The host uploads each ray's first sample and per-sample increment in continuous lattice
// index (Renderer::samples, in f64, rounded to f32 as the CPU renderer rounds them), so both
// backends walk the same samples. dL/dF is summed as integers (fixed_point.wgsl, appended by
// the host), so the sum does not depend on the order the rays run in.

struct Render {
    n: u32,
    rays: u32,
    // 1: scatter dL/dF into dense_grad; 0: predictions only (the log's full-view evaluation).
    want_grad: u32,
    // 1: the alpha mask is on (a sample counts only if one of its 8 nodes is kept).
    masked: u32,
    shift: f32,
    // s · step
    depth_scale: f32,
    // −2 · s · step / B
    grad_scale: f32,
    // 1: the loss compares optical depths (PhotoLoss::Log); 0: intensities.
    log_loss: u32,
}

// The smallest measured intensity the log loss takes the logarithm of (render.rs MIN_INTENSITY).
const MIN_INTENSITY: f32 = 1e-6;

struct RaySamples {
    q0: vec3<f32>,
    count: u32,
    dq: vec3<f32>,
    target_value: f32,
}

@group(0) @binding(0) var<uniform> u: Render;
@group(0) @binding(1) var<storage, read> dense: array<f32>;
@group(0) @binding(2) var<storage, read> mask_nodes: array<u32>;
@group(0) @binding(3) var<storage, read> rays: array<RaySamples>;
@group(0) @binding(4) var<storage, read_write> predicted: array<f32>;
// dL/dF as integer chunk sums, eight words per node (fixed_point.wgsl).
@group(0) @binding(5) var<storage, read_write> dense_grad_fixed: array<atomic<u32>>;

struct Sample {
    cell: u32,
    frac: vec3<f32>,
}

// Sample k of `ray`: its cell's lower node and the position in the cell, clamped to the
// outermost nodes (the CPU renderer's rule, in f32).
fn locate(ray: RaySamples, k: u32) -> Sample {
    let q = clamp(ray.q0 + f32(k) * ray.dq, vec3<f32>(0.0), vec3<f32>(f32(u.n - 1u)));
    let base = min(vec3<u32>(q), vec3<u32>(u.n - 2u));
    return Sample(base.x + u.n * (base.y + u.n * base.z), q - vec3<f32>(base));
}

fn kept(cell: u32) -> bool {
    if (u.masked == 0u) {
        return true;
    }
    let sy = u.n;
    let sz = u.n * u.n;
    return (mask_nodes[cell] | mask_nodes[cell + 1u] | mask_nodes[cell + sy] | mask_nodes[cell + sy + 1u]
        | mask_nodes[cell + sz] | mask_nodes[cell + sz + 1u] | mask_nodes[cell + sz + sy]
        | mask_nodes[cell + sz + sy + 1u]) != 0u;
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    return a + (b - a) * t;
}

// σ before the ReLU: F trilinear in the cell, plus Δ (the CPU's lerp order).
fn pre_activation(s: Sample) -> f32 {
    let c = s.cell;
    let sy = u.n;
    let sz = u.n * u.n;
    let f = s.frac;
    let lower = lerp(lerp(dense[c], dense[c + 1u], f.x), lerp(dense[c + sy], dense[c + sy + 1u], f.x), f.y);
    let upper = lerp(lerp(dense[c + sz], dense[c + sz + 1u], f.x), lerp(dense[c + sz + sy], dense[c + sz + sy + 1u], f.x), f.y);
    return lerp(lower, upper, f.z) + u.shift;
}

// Adds v to node i's integer sums: each non-zero chunk to its word, positive and negative
// addends apart (fixed_point.wgsl).
fn add_grad(i: u32, v: f32) {
    let chunks = fixed_chunks(v);
    let base = 8u * i + select(0u, 4u, v < 0.0);
    if (chunks.x != 0u) {
        atomicAdd(&dense_grad_fixed[base], chunks.x);
    }
    if (chunks.y != 0u) {
        atomicAdd(&dense_grad_fixed[base + 1u], chunks.y);
    }
    if (chunks.z != 0u) {
        atomicAdd(&dense_grad_fixed[base + 2u], chunks.z);
    }
    if (chunks.w != 0u) {
        atomicAdd(&dense_grad_fixed[base + 3u], chunks.w);
    }
}

// A value no cell index takes: no cell is open yet.
const NO_CELL: u32 = 0xffffffffu;

// Adds a cell's held addends to its 8 nodes: `lower` to the nodes at z, `upper` at z + 1,
// each in the order (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1).
fn flush(c: u32, lower: vec4<f32>, upper: vec4<f32>) {
    let sy = u.n;
    let sz = u.n * u.n;
    add_grad(c, lower.x);
    add_grad(c + 1u, lower.y);
    add_grad(c + sy, lower.z);
    add_grad(c + sy + 1u, lower.w);
    add_grad(c + sz, upper.x);
    add_grad(c + sz + 1u, upper.y);
    add_grad(c + sz + sy, upper.z);
    add_grad(c + sz + sy + 1u, upper.w);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= u.rays) {
        return;
    }
    let ray = rays[i];
    var depth = 0.0;
    for (var k = 0u; k < ray.count; k++) {
        let s = locate(ray, k);
        if (kept(s.cell)) {
            depth += max(pre_activation(s), 0.0);
        }
    }
    let p = exp(-u.depth_scale * depth);
    predicted[i] = p;
    if (u.want_grad == 0u) {
        return;
    }
    var g = u.grad_scale * (p - ray.target_value) * p;
    if (u.log_loss == 1u) {
        g = -u.grad_scale * (u.depth_scale * depth + log(max(ray.target_value, MIN_INTENSITY)));
    }
    if (g == 0.0) {
        return;
    }
    // Second walk: the same samples, scattering g times the trilinear weights where σ > 0
    // (dσ/dF = 1 there, 0 elsewhere). A ray leaves about two samples in each cell it crosses:
    // their weights are summed here, in walk order, and the cell's 8 nodes take one addend
    // each when the walk leaves it, half the atomics of one per sample.
    var open = NO_CELL;
    var lower = vec4<f32>(0.0);
    var upper = vec4<f32>(0.0);
    for (var k = 0u; k < ray.count; k++) {
        let s = locate(ray, k);
        if (kept(s.cell) && pre_activation(s) > 0.0) {
            if (s.cell != open) {
                if (open != NO_CELL) {
                    flush(open, lower, upper);
                }
                open = s.cell;
                lower = vec4<f32>(0.0);
                upper = vec4<f32>(0.0);
            }
            let f = s.frac;
            let face = vec4<f32>((1.0 - f.x) * (1.0 - f.y), f.x * (1.0 - f.y), (1.0 - f.x) * f.y, f.x * f.y);
            lower += (g * (1.0 - f.z)) * face;
            upper += (g * f.z) * face;
        }
    }
    if (open != NO_CELL) {
        flush(open, lower, upper);
    }
}
