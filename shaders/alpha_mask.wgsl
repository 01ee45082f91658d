// The alpha mask's kept nodes (mirrors train::render::Renderer::alpha_mask): a node is kept
// when the 3×3×3 max of alpha = 1 − exp(−σ·step·s) around it exceeds the threshold. Alpha is
// increasing in σ, so the host turns the threshold into one on σ, −ln(1 − threshold)/(step·s),
// in f64 — in f32, 1 − exp(−x) would lose the small alphas near the threshold to rounding.

struct Mask {
    n: u32,
    nodes: u32,
    shift: f32,
    sigma_threshold: f32,
}

@group(0) @binding(0) var<uniform> u: Mask;
@group(0) @binding(1) var<storage, read> dense: array<f32>;
@group(0) @binding(2) var<storage, read_write> mask_nodes: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= u.nodes) {
        return;
    }
    let n = u.n;
    let x = i % n;
    let y = (i / n) % n;
    let z = i / (n * n);
    var sigma = 0.0;
    for (var zz = max(z, 1u) - 1u; zz <= min(z + 1u, n - 1u); zz++) {
        for (var yy = max(y, 1u) - 1u; yy <= min(y + 1u, n - 1u); yy++) {
            for (var xx = max(x, 1u) - 1u; xx <= min(x + 1u, n - 1u); xx++) {
                sigma = max(sigma, dense[xx + n * (yy + n * zz)] + u.shift);
            }
        }
    }
    mask_nodes[i] = select(0u, 1u, sigma > u.sigma_threshold);
}
