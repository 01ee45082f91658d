// One Adam update of every parameter (mirrors train::adam::Adam::update): the host passes the
// step's bias-corrected rate lr/(1 − β1^t) and √(1 − β2^t) (train::adam::AdamParams::step).

struct Adam {
    entries: u32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    lr_t: f32,
    sqrt_bias2: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> u: Adam;
@group(0) @binding(1) var<storage, read> grad: array<f32>;
@group(0) @binding(2) var<storage, read_write> factors: array<f32>;
@group(0) @binding(3) var<storage, read_write> m: array<f32>;
@group(0) @binding(4) var<storage, read_write> v: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = id.x + id.y * groups.x * 64u;
    if (j >= u.entries) {
        return;
    }
    let g = grad[j];
    let mj = u.beta1 * m[j] + (1.0 - u.beta1) * g;
    let vj = u.beta2 * v[j] + (1.0 - u.beta2) * g * g;
    m[j] = mj;
    v[j] = vj;
    factors[j] = factors[j] - u.lr_t * mj / (sqrt(vj) / u.sqrt_bias2 + u.eps);
}
