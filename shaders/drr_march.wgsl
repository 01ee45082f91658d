// The DRR's Beer–Lambert march through the CT (mirrors kernels::raymarch::march_ray and
// kernels::trilinear::sample): one invocation per pixel. The host clips each ray to the box
// and the CT with the CPU's own `raymarch::segment` (in f64) and uploads where its midpoint
// samples lie in voxel-index space; this kernel sums the trilinear samples and applies
// I/I0 = exp(−attenuation · Σ v · δ).
//
// Precision: an f32 position near voxel 500 is only good to 3e-5 voxel, and a step rounded to
// f32 drifts by hundreds of ulps over a ray — enough to move dark pixels by 2e-5 relative.
// So a sample's position is kept as an integer voxel plus a fraction in [0, 1), and the step
// as two f32s (hi + lo): positions stay within ~1e-6 voxel of the CPU's f64 ones.

struct March {
    pixels: u32,
    attenuation: f32,
    _pad0: u32,
    _pad1: u32,
}

// Midpoint samples at `voxel + fraction + s · (step_hi + step_lo)` (voxel-index space),
// s < count, each weighing delta.
struct Segment {
    voxel: vec3<i32>,
    count: u32,
    fraction: vec3<f32>,
    delta: f32,
    step_hi: vec3<f32>,
    _pad0: u32,
    step_lo: vec3<f32>,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> march: March;
@group(0) @binding(1) var volume: texture_3d<f32>;
@group(0) @binding(2) var<storage, read> segments: array<Segment>;
@group(0) @binding(3) var<storage, read_write> pixels: array<f32>;

fn voxel_value(x: i32, y: i32, z: i32) -> f32 {
    return textureLoad(volume, vec3<i32>(x, y, z), 0).r;
}

// Trilinear between voxel centres at `voxel + fraction`, clamped to the edge voxels
// (kernels::trilinear::{cell, corners}: beyond the last centre the cell is the last one, at
// fraction 1; an axis of one voxel repeats it).
fn trilinear(voxel: vec3<i32>, fraction: vec3<f32>) -> f32 {
    let dims = vec3<i32>(textureDimensions(volume));
    let last_cell = max(dims - 2, vec3<i32>(0));
    let below = voxel < vec3<i32>(0);
    let beyond = voxel >= dims - 1;
    let lo = select(select(voxel, last_cell, beyond), vec3<i32>(0), below);
    let at_end = select(vec3<f32>(0.0), vec3<f32>(1.0), dims > vec3<i32>(1));
    let f = select(select(fraction, at_end, beyond), vec3<f32>(0.0), below);
    let hi = min(lo + 1, dims - 1);
    let g = 1.0 - f;
    return voxel_value(lo.x, lo.y, lo.z) * (g.x * g.y * g.z)
        + voxel_value(hi.x, lo.y, lo.z) * (f.x * g.y * g.z)
        + voxel_value(lo.x, hi.y, lo.z) * (g.x * f.y * g.z)
        + voxel_value(hi.x, hi.y, lo.z) * (f.x * f.y * g.z)
        + voxel_value(lo.x, lo.y, hi.z) * (g.x * g.y * f.z)
        + voxel_value(hi.x, lo.y, hi.z) * (f.x * g.y * f.z)
        + voxel_value(lo.x, hi.y, hi.z) * (g.x * f.y * f.z)
        + voxel_value(hi.x, hi.y, hi.z) * (f.x * f.y * f.z);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= march.pixels) {
        return;
    }
    let seg = segments[i];
    var voxel = seg.voxel;
    var fraction = seg.fraction;
    // Compensated (Kahan) sum: the CPU sums hundreds of samples in f64.
    var sum = 0.0;
    var carry = 0.0;
    for (var s = 0u; s < seg.count; s++) {
        let y = trilinear(voxel, fraction) - carry;
        let t = sum + y;
        carry = (t - sum) - y;
        sum = t;
        // Next sample: the fraction moves by the step and hands whole voxels to `voxel`.
        fraction = (fraction + seg.step_hi) + seg.step_lo;
        let whole = floor(fraction);
        fraction -= whole;
        voxel += vec3<i32>(whole);
    }
    pixels[i] = exp(-march.attenuation * (sum * seg.delta));
}
