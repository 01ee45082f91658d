//! Running a hot loop with the CPU's wide vectors: the build targets baseline x86-64 (SSE2,
//! 4 f32 lanes) so that the binary runs anywhere; [`with_avx2`] compiles a closure a second
//! time for AVX2 + FMA (8 lanes) and picks that copy at run time when the CPU has them.
//!
//! Results are identical either way: LLVM never reassociates or fuses floating-point
//! operations (no fast-math in Rust), so only the vector width changes, not the arithmetic.

/// `f()`, run by its AVX2 + FMA copy when the CPU has both. `f` and what it calls must inline
/// into it to get the wide copy (mark closures `#[inline(always)]` where needed); work that
/// stays out of line runs as built.
#[inline(always)]
pub fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        #[target_feature(enable = "avx2,fma")]
        fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: the CPU has AVX2 and FMA (checked above).
        return unsafe { wide(f) };
    }
    f()
}

/// Whether the CPU has AVX2 and FMA (what [`with_avx2`]'s wide copy needs).
#[inline]
pub fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The 8 × 8 transpose of f32 rows: `out[i]` lane `j` is `rows[j]` lane `i`.
///
/// # Safety
/// The CPU must have AVX (call it from code compiled with AVX enabled, e.g. `#[target_feature]`
/// functions or [`with_avx2`]'s copy, where it inlines).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub unsafe fn transpose_8x8(rows: [std::arch::x86_64::__m256; 8]) -> [std::arch::x86_64::__m256; 8] {
    use std::arch::x86_64::*;
    let r = rows;
    let t: [__m256; 8] = [
        _mm256_unpacklo_ps(r[0], r[1]),
        _mm256_unpackhi_ps(r[0], r[1]),
        _mm256_unpacklo_ps(r[2], r[3]),
        _mm256_unpackhi_ps(r[2], r[3]),
        _mm256_unpacklo_ps(r[4], r[5]),
        _mm256_unpackhi_ps(r[4], r[5]),
        _mm256_unpacklo_ps(r[6], r[7]),
        _mm256_unpackhi_ps(r[6], r[7]),
    ];
    let u: [__m256; 8] = [
        _mm256_shuffle_ps::<0x44>(t[0], t[2]),
        _mm256_shuffle_ps::<0xEE>(t[0], t[2]),
        _mm256_shuffle_ps::<0x44>(t[1], t[3]),
        _mm256_shuffle_ps::<0xEE>(t[1], t[3]),
        _mm256_shuffle_ps::<0x44>(t[4], t[6]),
        _mm256_shuffle_ps::<0xEE>(t[4], t[6]),
        _mm256_shuffle_ps::<0x44>(t[5], t[7]),
        _mm256_shuffle_ps::<0xEE>(t[5], t[7]),
    ];
    [
        _mm256_permute2f128_ps::<0x20>(u[0], u[4]),
        _mm256_permute2f128_ps::<0x20>(u[1], u[5]),
        _mm256_permute2f128_ps::<0x20>(u[2], u[6]),
        _mm256_permute2f128_ps::<0x20>(u[3], u[7]),
        _mm256_permute2f128_ps::<0x31>(u[0], u[4]),
        _mm256_permute2f128_ps::<0x31>(u[1], u[5]),
        _mm256_permute2f128_ps::<0x31>(u[2], u[6]),
        _mm256_permute2f128_ps::<0x31>(u[3], u[7]),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_8x8_transpose_swaps_rows_and_lanes() {
        use std::arch::x86_64::*;
        if !std::arch::is_x86_feature_detected!("avx") {
            return;
        }
        let m: [[f32; 8]; 8] = std::array::from_fn(|i| std::array::from_fn(|j| (8 * i + j) as f32));
        let mut out = [[0f32; 8]; 8];
        // SAFETY: the CPU has AVX (checked above); loads and stores address whole rows.
        unsafe {
            let t = transpose_8x8(m.map(|row| _mm256_loadu_ps(row.as_ptr())));
            for (row, v) in out.iter_mut().zip(t) {
                _mm256_storeu_ps(row.as_mut_ptr(), v);
            }
        }
        for i in 0..8 {
            for j in 0..8 {
                assert_eq!(out[i][j], m[j][i]);
            }
        }
    }

    #[test]
    fn the_wide_copy_computes_what_the_plain_one_does() {
        let x: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin()).collect();
        let body = || x.iter().map(|&v| v * 1.5 + 0.25).fold(0f32, |a, b| a + b);
        assert_eq!(with_avx2(body).to_bits(), body().to_bits());
    }
}
