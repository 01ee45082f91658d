// One ray per invocation through the composed field F (mirrors train::render::Renderer::batch
// and its scatter): σ = ReLU(F + Δ) trilinear between nodes, Î = exp(−s·step·Σσ); then, when
// training, dL/dσ = 2(Î − I)/B · (−s·step·Î) for each active sample (σ > 0, in a kept cell of
// the alpha mask), scattered onto its cell's 8 nodes with its trilinear weights. With the log
// loss (PhotoLoss::Log) dL/dσ = 2(τ̂ − τ)/B · s·step, τ̂ = s·step·Σσ and τ = −ln max(I, 1e-6).
//
// The host uploads each ray's first sample and per-sample increment in continuous lattice
// index (Renderer::samples, in f64, rounded to f32 as the CPU renderer rounds them), so both
// backends walk the same samples. `add_grad` comes from grad_add_f32.wgsl (native float
// atomics) or grad_add_cas.wgsl (compare-exchange), appended by the host.

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
// binding 5: dense_grad, declared with add_grad in the appended file.

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

// Adds g times the trilinear weights of `s` to its cell's 8 nodes (the CPU scatter's order:
// lower face by g·(1 − fz), upper face by g·fz).
fn scatter(s: Sample, g: f32) {
    let c = s.cell;
    let sy = u.n;
    let sz = u.n * u.n;
    let f = s.frac;
    let gx = 1.0 - f.x;
    let gy = 1.0 - f.y;
    let lower = g * (1.0 - f.z);
    let upper = g * f.z;
    add_grad(c, lower * (gx * gy));
    add_grad(c + 1u, lower * (f.x * gy));
    add_grad(c + sy, lower * (gx * f.y));
    add_grad(c + sy + 1u, lower * (f.x * f.y));
    add_grad(c + sz, upper * (gx * gy));
    add_grad(c + sz + 1u, upper * (f.x * gy));
    add_grad(c + sz + sy, upper * (gx * f.y));
    add_grad(c + sz + sy + 1u, upper * (f.x * f.y));
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
    // Second walk: the same samples, scattering where σ > 0 (dσ/dF = 1 there, 0 elsewhere).
    for (var k = 0u; k < ray.count; k++) {
        let s = locate(ray, k);
        if (kept(s.cell) && pre_activation(s) > 0.0) {
            scatter(s, g);
        }
    }
}
