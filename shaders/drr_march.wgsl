// The DRR's Beer–Lambert march through the CT (mirrors kernels::raymarch::march_ray and
// kernels::trilinear::sample): one invocation per pixel. The host clips each ray to the box
// and the CT with the CPU's own `raymarch::segment` (in f64) and uploads where its midpoint
// samples lie in voxel-index space; this kernel sums the trilinear samples and applies
// I/I0 = exp(−attenuation · Σ v · δ).

struct March {
    pixels: u32,
    attenuation: f32,
    _pad0: u32,
    _pad1: u32,
}

// Midpoint samples at `first + s · step` (voxel-index space), s < count, each weighing delta.
struct Segment {
    first: vec3<f32>,
    count: u32,
    step: vec3<f32>,
    delta: f32,
}

@group(0) @binding(0) var<uniform> march: March;
@group(0) @binding(1) var volume: texture_3d<f32>;
@group(0) @binding(2) var<storage, read> segments: array<Segment>;
@group(0) @binding(3) var<storage, read_write> pixels: array<f32>;

fn voxel(x: i32, y: i32, z: i32) -> f32 {
    return textureLoad(volume, vec3<i32>(x, y, z), 0).r;
}

// Trilinear between voxel centres, clamped to the edge voxels (kernels::trilinear::{cell, corners}).
fn trilinear(q: vec3<f32>) -> f32 {
    let dims = vec3<i32>(textureDimensions(volume));
    let x = clamp(q, vec3<f32>(0.0), vec3<f32>(dims - 1));
    let lo = min(vec3<i32>(x), max(dims - 2, vec3<i32>(0)));
    let hi = min(lo + 1, dims - 1);
    let f = x - vec3<f32>(lo);
    let g = 1.0 - f;
    return voxel(lo.x, lo.y, lo.z) * (g.x * g.y * g.z)
        + voxel(hi.x, lo.y, lo.z) * (f.x * g.y * g.z)
        + voxel(lo.x, hi.y, lo.z) * (g.x * f.y * g.z)
        + voxel(hi.x, hi.y, lo.z) * (f.x * f.y * g.z)
        + voxel(lo.x, lo.y, hi.z) * (g.x * g.y * f.z)
        + voxel(hi.x, lo.y, hi.z) * (f.x * g.y * f.z)
        + voxel(lo.x, hi.y, hi.z) * (g.x * f.y * f.z)
        + voxel(hi.x, hi.y, hi.z) * (f.x * f.y * f.z);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = id.x + id.y * groups.x * 64u;
    if (i >= march.pixels) {
        return;
    }
    let seg = segments[i];
    // Compensated (Kahan) sum: the CPU sums hundreds of samples in f64; in f32 the
    // compensation keeps the integral within a few ulps of it.
    var sum = 0.0;
    var carry = 0.0;
    for (var s = 0u; s < seg.count; s++) {
        let y = trilinear(seg.first + f32(s) * seg.step) - carry;
        let t = sum + y;
        carry = (t - sum) - y;
        sum = t;
    }
    pixels[i] = exp(-march.attenuation * (sum * seg.delta));
}
