// dL/dF as exact integer sums: not a kernel, appended by the hosts of render.wgsl (which adds
// into it) and grad_from_fixed.wgsl (which turns it into f32). Integer addition is
// associative, so the scatter's sum is the same whatever order the device runs the rays in;
// f32 atomics were not (on an H100 they left most factors different from one run to the next).
//
// An addend v becomes the integer round(|v| · 2^48), cut into four 16-bit chunks. A node owns
// eight u32 words: the chunks of its positive addends are summed into words 0–3, of its
// negative ones into words 4–7. Each word takes atomic adds whose results nobody reads, and
// holds 65,536 chunks before it could wrap: the host keeps a batch's addends per node under
// that (gpu::grad_from_fixed::max_batch_rays). Resolution 2^-48 ≈ 3.6e-15, far below the terms
// that move Adam (its ε is 1e-8); an addend of 2^16 or more (or ∞, NaN) saturates.

const FIXED_ONE: f32 = 281474976710656.0;

// The four 16-bit chunks of round(|v| · 2^48), lowest first, by integer shifts of v's
// mantissa: exact, halves round up, subnormal v give 0. (Integer shifts, not f32 division and
// floor: on an H100 that made the render + scatter 1.2 → 0.74 ms a batch.)
fn fixed_chunks(v: f32) -> vec4<u32> {
    let bits = bitcast<u32>(v) & 0x7fffffffu;
    let exponent = i32(bits >> 23u);
    if (exponent == 0) {
        return vec4<u32>(0u);
    }
    let mantissa = (bits & 0x7fffffu) | 0x800000u;
    // |v| · 2^48 = mantissa · 2^shift
    let shift = exponent - 102;
    var lo: u32;
    var hi: u32;
    if (shift < 0) {
        let right = u32(-shift);
        if (right > 24u) {
            return vec4<u32>(0u);
        }
        lo = (mantissa + (1u << (right - 1u))) >> right;
        hi = 0u;
    } else if (shift > 40) {
        lo = 0xffffffffu;
        hi = 0xffffffffu;
    } else if (shift < 32) {
        let left = u32(shift);
        lo = mantissa << left;
        hi = select(mantissa >> (32u - left), 0u, left == 0u);
    } else {
        lo = 0u;
        hi = mantissa << u32(shift - 32);
    }
    return vec4<u32>(lo & 0xffffu, lo >> 16u, hi & 0xffffu, hi >> 16u);
}

// Σ_k w_k · 2^(16k) as a 64-bit (lo, hi) pair (mod 2^64).
fn chunk_total(w: vec4<u32>) -> vec2<u32> {
    let lo = w.x + (w.y << 16u);
    let carry = select(0u, 1u, lo < w.x);
    return vec2<u32>(lo, (w.y >> 16u) + w.z + (w.w << 16u) + carry);
}

// A node's value in f32: the exact 64-bit difference of its positive and negative sums, then
// its magnitude converted word by word (never a difference of two large, nearly equal floats).
fn fixed_value(positive: vec4<u32>, negative: vec4<u32>) -> f32 {
    let p = chunk_total(positive);
    let n = chunk_total(negative);
    let negative_result = p.y < n.y || (p.y == n.y && p.x < n.x);
    var big = p;
    var small = n;
    if (negative_result) {
        big = n;
        small = p;
    }
    let lo = big.x - small.x;
    let hi = big.y - small.y - select(0u, 1u, big.x < small.x);
    let magnitude = f32(hi) * (4294967296.0 / FIXED_ONE) + f32(lo) * (1.0 / FIXED_ONE);
    return select(magnitude, -magnitude, negative_result);
}
