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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wide_copy_computes_what_the_plain_one_does() {
        let x: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin()).collect();
        let body = || x.iter().map(|&v| v * 1.5 + 0.25).fold(0f32, |a, b| a + b);
        assert_eq!(with_avx2(body).to_bits(), body().to_bits());
    }
}
