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

/// `f()` compiled a third time with AVX-512 (F + VL) as well, for the caller to pick when
/// [`has_avx512`] says so; the caller keeps a [`with_avx2`] path for other CPUs.
///
/// # Panics
/// If the CPU lacks AVX-512F, AVX-512VL, AVX2 or FMA.
#[inline(always)]
pub fn with_avx512<R>(f: impl FnOnce() -> R) -> R {
    assert!(has_avx512(), "with_avx512 on a CPU without AVX-512F/VL, AVX2 and FMA");
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
        fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: the CPU has every feature enabled (asserted above).
        unsafe { wide(f) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    f()
}

/// Whether the CPU has AVX-512F and AVX-512VL besides AVX2 and FMA (what [`with_avx512`] needs).
#[inline]
pub fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    return has_avx2_fma()
        && std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vl");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The vectors a kernel with an AVX-512 copy runs with: the widest the CPU has
/// ([`Width::widest`]), or any [`Width::available`] one (tests compare them bit for bit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Width {
    /// AVX2 + FMA: 8 f32 lanes.
    Avx2,
    /// AVX-512F + VL as well: 16 f32 lanes.
    Avx512,
}

impl Width {
    /// The widest vectors the CPU has; `None` without AVX2 + FMA.
    pub fn widest() -> Option<Width> {
        [Width::Avx512, Width::Avx2].into_iter().find(|w| w.is_available())
    }

    /// Whether the CPU runs these vectors.
    pub fn is_available(self) -> bool {
        match self {
            Width::Avx2 => has_avx2_fma(),
            Width::Avx512 => has_avx512(),
        }
    }

    /// Every width the CPU runs, narrowest first.
    pub fn available() -> Vec<Width> {
        [Width::Avx2, Width::Avx512].into_iter().filter(|w| w.is_available()).collect()
    }
}

/// Whether the CPU has AVX2 and FMA (what [`with_avx2`]'s wide copy needs).
#[inline]
pub fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// A vector of f32 lanes, for kernels written once for AVX2 (`__m256`) and AVX-512
/// (`__m512`). Every method must inline into code compiled with the vector's features
/// ([`with_avx2`], [`with_avx512`] or a `#[target_feature]` function); that is the safety
/// contract of each.
#[cfg(target_arch = "x86_64")]
pub trait F32Lanes: Copy {
    /// f32 values per vector.
    const LANES: usize;
    /// # Safety
    /// See the trait.
    unsafe fn zero() -> Self;
    /// # Safety
    /// See the trait; `p` points at `LANES` readable floats.
    unsafe fn load(p: *const f32) -> Self;
    /// # Safety
    /// See the trait; `p` points at `LANES` writable floats.
    unsafe fn store(self, p: *mut f32);
    /// Every lane `*p`.
    ///
    /// # Safety
    /// See the trait; `p` points at a readable float.
    unsafe fn splat(p: *const f32) -> Self;
    /// # Safety
    /// See the trait.
    unsafe fn add(self, other: Self) -> Self;
    /// `self · b + c`, fused (one rounding).
    ///
    /// # Safety
    /// See the trait.
    unsafe fn mul_add(self, b: Self, c: Self) -> Self;
}

#[cfg(target_arch = "x86_64")]
macro_rules! f32_lanes {
    ($vector:ident, $lanes:expr, $zero:ident, $load:ident, $store:ident, $splat:ident, $add:ident, $fma:ident) => {
        impl F32Lanes for std::arch::x86_64::$vector {
            const LANES: usize = $lanes;
            #[inline(always)]
            unsafe fn zero() -> Self {
                std::arch::x86_64::$zero()
            }
            #[inline(always)]
            unsafe fn load(p: *const f32) -> Self {
                std::arch::x86_64::$load(p)
            }
            #[inline(always)]
            unsafe fn store(self, p: *mut f32) {
                std::arch::x86_64::$store(p, self)
            }
            #[inline(always)]
            unsafe fn splat(p: *const f32) -> Self {
                std::arch::x86_64::$splat(*p)
            }
            #[inline(always)]
            unsafe fn add(self, other: Self) -> Self {
                std::arch::x86_64::$add(self, other)
            }
            #[inline(always)]
            unsafe fn mul_add(self, b: Self, c: Self) -> Self {
                std::arch::x86_64::$fma(self, b, c)
            }
        }
    };
}

#[cfg(target_arch = "x86_64")]
f32_lanes!(
    __m256,
    8,
    _mm256_setzero_ps,
    _mm256_loadu_ps,
    _mm256_storeu_ps,
    _mm256_set1_ps,
    _mm256_add_ps,
    _mm256_fmadd_ps
);
#[cfg(target_arch = "x86_64")]
f32_lanes!(
    __m512,
    16,
    _mm512_setzero_ps,
    _mm512_loadu_ps,
    _mm512_storeu_ps,
    _mm512_set1_ps,
    _mm512_add_ps,
    _mm512_fmadd_ps
);

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
