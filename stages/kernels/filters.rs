//! 3-D image filters on x-fastest volumes (`x + nx·(y + ny·z)`, dims `[nx, ny, nz]`, spacing
//! `[sx, sy, sz]` mm), each equal to its scipy / scikit-image counterpart on the `(nz, ny, nx)`
//! array (`docs/kernels.md`, checked by `tests/py/test_filters_scipy.py`):
//!
//! - [`gaussian_mm`]: `scipy.ndimage.gaussian_filter(x, sigma_mm / spacing, mode="nearest")`;
//! - [`blob_response`]: the scale-normalised negative Laplacian of Gaussian, from scipy's
//!   second-derivative Gaussian filters;
//! - [`hessian_blob_response`]: the scale-normalised Hessian of Gaussian's least-negative
//!   eigenvalue (numpy's `eigvalsh` of scipy's Gaussian derivative filters), which answers
//!   blobs and not lines or sheets;
//! - [`distance_inside_mm`]: `scipy.ndimage.distance_transform_edt(mask, sampling=spacing)`;
//! - [`otsu_threshold`]: `skimage.filters.threshold_otsu(values, nbins=256)`, float32
//!   arithmetic and all, so the threshold is the same float;
//! - [`fill_holes_per_slice`]: `scipy.ndimage.binary_fill_holes` on every 2-D slice.
//!
//! The Gaussian filters are separable and computed in f64, one axis at a time in scipy's order
//! (z, then y, then x), rounded to f32 once at the end. Every 1-D pass runs over whole z-planes
//! with rayon; each output voxel's sum has a fixed order, so the result does not depend on the
//! number of threads.

use super::eigen3::largest_eigenvalue;
use super::wide::with_avx2;
use rayon::prelude::*;

/// scipy's default `truncate`: kernels reach `int(4·σ + 0.5)` voxels each side.
pub const TRUNCATE: f64 = 4.0;

/// `scipy.ndimage.gaussian_filter(x, sigma=[sigma_mm / s for s in spacing_zyx], order=0,
/// mode="nearest", truncate=4.0)` on the `(nz, ny, nx)` array, computed in f64 (equal to scipy
/// on the float64 array to about 1e-15 of the value range) and rounded to f32.
///
/// `sigma_mm = 0` returns the values unchanged (scipy skips an axis whose σ is below 1e-15).
///
/// # Panics
/// If `values` does not hold `dims` voxels, a spacing is not positive and finite, or
/// `sigma_mm` is negative or not finite.
pub fn gaussian_mm(values: &[f32], dims: [usize; 3], spacing_mm: [f64; 3], sigma_mm: f64) -> Vec<f32> {
    check(values.len(), dims, spacing_mm, sigma_mm);
    let mut field: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    for axis in [2, 1, 0] {
        let sigma = sigma_mm / spacing_mm[axis];
        if sigma > 1e-15 {
            field = along(&field, dims, axis, &gaussian_kernel(sigma, Order::Smooth));
        }
    }
    field.iter().map(|&v| v as f32).collect()
}

/// The scale-normalised bright-blob response at scale `s_mm`:
/// `−s² · (∂²/∂x² + ∂²/∂y² + ∂²/∂z²)(G_s ∗ values)`, second derivatives in mm⁻² — the negative
/// Laplacian of Gaussian, positive at bright blobs and largest at their centre for a ball of
/// radius ≈ √3·s. Term by term it is scipy's
/// `gaussian_filter(x, sv, order=o, mode="nearest") / spacing_a²` with `o` 2 on axis `a` and 0
/// on the others (sv = s_mm / spacing), summed over the three axes and multiplied by −s².
/// Computed in f64, rounded to f32 once.
///
/// `s_mm = 0` gives zeros (the factor s² is 0).
///
/// # Panics
/// As [`gaussian_mm`].
pub fn blob_response(values: &[f32], dims: [usize; 3], spacing_mm: [f64; 3], s_mm: f64) -> Vec<f32> {
    check(values.len(), dims, spacing_mm, s_mm);
    if s_mm == 0.0 {
        return vec![0.0; values.len()];
    }
    let v: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    let sigma = [0, 1, 2].map(|a| s_mm / spacing_mm[a]);
    let smooth = sigma.map(|s| gaussian_kernel(s, Order::Smooth));
    let second = sigma.map(|s| gaussian_kernel(s, Order::Second));
    let inv_sq = spacing_mm.map(|s| 1.0 / (s * s));
    // Each term in scipy's axis order (z, y, x), sharing the passes the terms have in common:
    // x term = K2x K0y K0z v, y term = K0x K2y K0z v, z term = K0x K0y K2z v.
    let z_smoothed = along(&v, dims, 2, &smooth[2]);
    let x_term = along(&along(&z_smoothed, dims, 1, &smooth[1]), dims, 0, &second[0]);
    let y_part = along(&z_smoothed, dims, 1, &second[1]);
    drop(z_smoothed);
    let z_part = along(&along(&v, dims, 2, &second[2]), dims, 1, &smooth[1]);
    let yz: Vec<f64> = y_part.iter().zip(&z_part).map(|(&y, &z)| y * inv_sq[1] + z * inv_sq[2]).collect();
    let yz_term = along(&yz, dims, 0, &smooth[0]);
    let scale = -s_mm * s_mm;
    x_term.iter().zip(&yz_term).map(|(&x, &yz)| (scale * (x * inv_sq[0] + yz)) as f32).collect()
}

/// The scale-normalised Hessian blob response at scale `s_mm`: `s² · max(0, −λ₁)`, where λ₁ is
/// the largest (least negative) eigenvalue of the Hessian of `G_s ∗ values` in mm⁻². It is
/// positive only where all three curvatures are negative, so it answers bright blobs and not
/// bright lines (one curvature ≈ 0: vessels, the field's axis-aligned streaks) or sheets and
/// edges; at a ball's centre the three are equal and it is a third of [`blob_response`], with
/// the same best scale (radius ≈ √3·s). The Hessian's terms are scipy's
/// `gaussian_filter(x, sv, order=o, mode="nearest") / (spacing_a · spacing_b)` with `o` the
/// derivative orders on axes a and b; λ₁ is numpy's `eigvalsh(H)[..., -1]` (closed form here).
/// Computed in f64, rounded to f32 once.
///
/// # Panics
/// As [`gaussian_mm`].
pub fn hessian_blob_response(values: &[f32], dims: [usize; 3], spacing_mm: [f64; 3], s_mm: f64) -> Vec<f32> {
    check(values.len(), dims, spacing_mm, s_mm);
    if s_mm == 0.0 {
        return vec![0.0; values.len()];
    }
    let v: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    let sigma = [0, 1, 2].map(|a| s_mm / spacing_mm[a]);
    let k = |a: usize, order: Order| gaussian_kernel(sigma[a], order);
    // pass(order, axis) on f; odd kernels take the antisymmetric path.
    let pass = |f: &[f64], axis: usize, order: Order| match order {
        Order::First => along_odd(f, dims, axis, &k(axis, order)),
        _ => along(f, dims, axis, &k(axis, order)),
    };
    use Order::{First as D1, Second as D2, Smooth as D0};
    // In scipy's axis order (z, y, x), sharing the z and y passes the six terms have in common.
    let z = [D0, D1, D2].map(|o| pass(&v, 2, o));
    let y_of = |zi: usize, o: Order| pass(&z[zi], 1, o);
    let (y0z0, y1z0, y2z0, y0z1, y1z1, y0z2) =
        (y_of(0, D0), y_of(0, D1), y_of(0, D2), y_of(1, D0), y_of(1, D1), y_of(2, D0));
    let [sx, sy, sz] = spacing_mm;
    let term = |f: &[f64], o: Order, per_mm2: f64| -> Vec<f64> { pass(f, 0, o).iter().map(|&h| h * per_mm2).collect() };
    let hxx = term(&y0z0, D2, 1.0 / (sx * sx));
    let hxy = term(&y1z0, D1, 1.0 / (sx * sy));
    let hyy = term(&y2z0, D0, 1.0 / (sy * sy));
    let hxz = term(&y0z1, D1, 1.0 / (sx * sz));
    let hyz = term(&y1z1, D0, 1.0 / (sy * sz));
    let hzz = term(&y0z2, D0, 1.0 / (sz * sz));
    let s2 = s_mm * s_mm;
    (0..v.len())
        .into_par_iter()
        .map(|i| {
            let largest = largest_eigenvalue([hxx[i], hyy[i], hzz[i]], [hxy[i], hxz[i], hyz[i]]);
            (s2 * (-largest).max(0.0)) as f32
        })
        .collect()
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Order {
    /// The Gaussian itself.
    Smooth,
    /// Its first derivative (an odd kernel).
    First,
    /// Its second derivative.
    Second,
}

/// scipy's `_gaussian_kernel1d(sigma, order, radius)` with `radius = int(truncate·σ + 0.5)`:
/// weights at `x = −radius..=radius` of `φ(x) = exp(−x²/(2σ²))` normalised to sum 1, and for
/// the second derivative `φ(x)·(x² − σ²)/σ⁴`, formed as scipy forms it (the polynomial
/// `q = [−1/σ², 0, 1/σ⁴]` evaluated at x). Both are symmetric, so correlating (scipy) and
/// convolving are the same.
fn gaussian_kernel(sigma: f64, order: Order) -> Vec<f64> {
    let radius = (TRUNCATE * sigma + 0.5) as i64;
    let sigma2 = sigma * sigma;
    let factor = -0.5 / sigma2;
    let phi: Vec<f64> = (-radius..=radius).map(|x| (factor * (x * x) as f64).exp()).collect();
    let sum: f64 = phi.iter().sum();
    let phi = phi.into_iter().map(|p| p / sum);
    match order {
        Order::Smooth => phi.collect(),
        // scipy's q = [0, −1/σ²]: φ(x)·(−x/σ²). scipy convolves (it reverses the weights), so
        // the pass correlates with the reversed kernel: weight x/σ²·φ(x) at offset +x.
        Order::First => (-radius..=radius).zip(phi).map(|(x, phi)| x as f64 / sigma2 * phi).collect(),
        Order::Second => {
            let p = 1.0 / -sigma2;
            let (q0, q2) = (p, p * p);
            (-radius..=radius).zip(phi).map(|(x, phi)| (q0 + ((x * x) as f64) * q2) * phi).collect()
        }
    }
}

/// One 1-D pass of the symmetric `kernel` (odd length, centre in the middle) along `axis`,
/// edges replicated (scipy's mode "nearest", however far the kernel reaches past the edge).
/// Each output is `w₀·v₀ + Σ_{j=1..r} w_j·(v₋ⱼ + v₊ⱼ)`, j ascending, as scipy's symmetric path
/// sums it.
fn along(src: &[f64], dims: [usize; 3], axis: usize, kernel: &[f64]) -> Vec<f64> {
    along_with(src, dims, axis, kernel, Parity::Even)
}

/// [`along`] for an odd `kernel` (`w₋ⱼ = −w_j`, `w₀ = 0`, `w_j` the weight at offset +j):
/// `Σ_{j=1..r} w_j·(v₊ⱼ − v₋ⱼ)`, scipy's antisymmetric path.
fn along_odd(src: &[f64], dims: [usize; 3], axis: usize, kernel: &[f64]) -> Vec<f64> {
    along_with(src, dims, axis, kernel, Parity::Odd)
}

#[derive(Clone, Copy)]
enum Parity {
    Even,
    Odd,
}

fn along_with(src: &[f64], dims: [usize; 3], axis: usize, kernel: &[f64], parity: Parity) -> Vec<f64> {
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    let mut out = vec![0.0; src.len()];
    if src.is_empty() {
        return out;
    }
    let r = kernel.len() / 2;
    let (w0, wings) = (kernel[r], &kernel[r + 1..]);
    match axis {
        0 => out.par_chunks_mut(plane).zip(src.par_chunks(plane)).for_each(|(dst, src)| {
            let mut padded = vec![0.0; nx + 2 * r];
            for (dst, row) in dst.chunks_exact_mut(nx).zip(src.chunks_exact(nx)) {
                padded[..r].fill(row[0]);
                padded[r..r + nx].copy_from_slice(row);
                padded[r + nx..].fill(row[nx - 1]);
                let padded = &padded;
                accumulate(dst, w0, wings, parity, |k| {
                    let start = (r as i64 + k) as usize;
                    &padded[start..start + nx]
                });
            }
        }),
        1 => out.par_chunks_mut(plane).zip(src.par_chunks(plane)).for_each(|(dst, src)| {
            let row = |y: i64| {
                let y = y.clamp(0, ny as i64 - 1) as usize;
                &src[y * nx..(y + 1) * nx]
            };
            for (y, dst) in dst.chunks_exact_mut(nx).enumerate() {
                accumulate(dst, w0, wings, parity, |k| row(y as i64 + k));
            }
        }),
        2 => out.par_chunks_mut(plane).enumerate().for_each(|(z, dst)| {
            let slab = |k: i64| {
                let z = k.clamp(0, nz as i64 - 1) as usize;
                &src[z * plane..(z + 1) * plane]
            };
            accumulate(dst, w0, wings, parity, |k| slab(z as i64 + k));
        }),
        _ => panic!("axis {axis} is not 0, 1 or 2"),
    }
    out
}

/// `dst = w0·line(0) + Σ_j w_j·(line(−j) + line(+j))` (even kernels) or
/// `Σ_j w_j·(line(+j) − line(−j))` (odd kernels, whose `w0` is 0), elementwise over whole rows
/// or planes, j ascending, in its AVX2 copy where the CPU has it. (Keeping blocks of sums in
/// registers across the kernel instead was measured slower.)
fn accumulate<'a>(dst: &mut [f64], w0: f64, wings: &[f64], parity: Parity, line: impl Fn(i64) -> &'a [f64]) {
    with_avx2(
        #[inline(always)]
        || {
            for (d, &c) in dst.iter_mut().zip(line(0)) {
                *d = w0 * c;
            }
            for (j, &w) in wings.iter().enumerate() {
                let k = j as i64 + 1;
                let pairs = dst.iter_mut().zip(line(-k)).zip(line(k));
                match parity {
                    Parity::Even => pairs.for_each(|((d, &a), &b)| *d += w * (a + b)),
                    Parity::Odd => pairs.for_each(|((d, &a), &b)| *d += w * (b - a)),
                }
            }
        },
    )
}

fn check(len: usize, dims: [usize; 3], spacing_mm: [f64; 3], sigma_mm: f64) {
    let n: usize = dims.iter().product();
    assert_eq!(len, n, "{len} values for dims {dims:?} ({n} voxels)");
    assert!(
        spacing_mm.iter().all(|s| s.is_finite() && *s > 0.0),
        "spacing must be positive and finite, got {spacing_mm:?}"
    );
    assert!(sigma_mm.is_finite() && sigma_mm >= 0.0, "the scale must be finite and ≥ 0 mm, got {sigma_mm}");
}

/// The Euclidean distance in mm (per-axis spacing) from every voxel of `mask` to the nearest
/// voxel of the volume that is not in `mask`; 0 outside the mask. Equals
/// `scipy.ndimage.distance_transform_edt(mask, sampling=spacing_zyx)` on the `(nz, ny, nx)`
/// array (to rounding, about 1e-15 relative): the array's border is not background, only unset
/// voxels inside the array are.
///
/// **If every voxel is set, every distance is `f64::INFINITY`** (there is no background to be
/// near; scipy answers arbitrary finite numbers then).
///
/// Exact and separable (Felzenszwalb & Huttenlocher's lower envelope of parabolas): squared
/// distances along x first, then the envelope along y and along z with that axis's spacing.
///
/// # Panics
/// If `mask` does not hold `dims` voxels or a spacing is not positive and finite.
pub fn distance_inside_mm(mask: &[bool], dims: [usize; 3], spacing_mm: [f64; 3]) -> Vec<f64> {
    check(mask.len(), dims, spacing_mm, 0.0);
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    let mut d2 = vec![0.0; mask.len()];
    if mask.is_empty() {
        return d2;
    }
    let [sx, sy, sz] = spacing_mm;
    // x: squared distance to the nearest unset voxel of the row, by two sweeps.
    d2.par_chunks_mut(nx).zip(mask.par_chunks(nx)).for_each(|(dst, row)| {
        let mut last: Option<usize> = None;
        for (x, (d, &set)) in dst.iter_mut().zip(row).enumerate() {
            if !set {
                last = Some(x);
            }
            *d = last.map_or(f64::INFINITY, |l| (x - l) as f64);
        }
        let mut next: Option<usize> = None;
        for (x, (d, &set)) in dst.iter_mut().zip(row).enumerate().rev() {
            if !set {
                next = Some(x);
            }
            if let Some(n) = next {
                *d = d.min((n - x) as f64);
            }
            *d = (*d * sx) * (*d * sx);
        }
    });
    // y: the envelope along every column of each z-plane.
    d2.par_chunks_mut(plane).for_each(|slab| {
        let mut envelope = Envelope::new(ny);
        let mut line = vec![0.0; ny];
        for x in 0..nx {
            for (y, v) in line.iter_mut().enumerate() {
                *v = slab[x + nx * y];
            }
            envelope.transform(&mut line, sy);
            for (y, &v) in line.iter().enumerate() {
                slab[x + nx * y] = v;
            }
        }
    });
    // z: lines cross every plane, so each y gathers its nx lines (row by row, into a local
    // x-major buffer), and they are written back, row by row, after.
    let columns: Vec<Vec<f64>> = (0..ny)
        .into_par_iter()
        .map(|y| {
            let mut envelope = Envelope::new(nz);
            let mut lines = vec![0.0; nx * nz];
            for z in 0..nz {
                let row = &d2[nx * (y + ny * z)..][..nx];
                for (x, &v) in row.iter().enumerate() {
                    lines[x * nz + z] = v;
                }
            }
            for line in lines.chunks_exact_mut(nz) {
                envelope.transform(line, sz);
            }
            lines
        })
        .collect();
    for (y, lines) in columns.iter().enumerate() {
        for z in 0..nz {
            let row = &mut d2[nx * (y + ny * z)..][..nx];
            for (x, v) in row.iter_mut().enumerate() {
                *v = lines[x * nz + z];
            }
        }
    }
    d2.par_iter_mut().for_each(|d| *d = d.sqrt());
    d2
}

/// Felzenszwalb & Huttenlocher's 1-D squared distance transform with spacing `s`:
/// `out[q] = min_p (s·(q − p))² + f[p]` over the sites `p` with finite `f[p]` (infinite where
/// there are none), in linear time. Buffers are kept between lines.
struct Envelope {
    /// Sites of the parabolas on the lower envelope.
    sites: Vec<usize>,
    /// `bounds[k]`: where parabola `k` starts being the lowest (index units).
    bounds: Vec<f64>,
    values: Vec<f64>,
}

impl Envelope {
    fn new(n: usize) -> Self {
        Self { sites: Vec::with_capacity(n), bounds: Vec::with_capacity(n + 1), values: vec![0.0; n] }
    }

    fn transform(&mut self, f: &mut [f64], s: f64) {
        let s2 = s * s;
        self.sites.clear();
        self.bounds.clear();
        self.values.copy_from_slice(f);
        // Where the parabolas of sites p < q meet, in index units.
        let meet = |f: &[f64], p: usize, q: usize| {
            let (pf, qf) = (p as f64, q as f64);
            ((f[q] + s2 * qf * qf) - (f[p] + s2 * pf * pf)) / (2.0 * s2 * (qf - pf))
        };
        for q in 0..f.len() {
            if !self.values[q].is_finite() {
                continue;
            }
            while let Some(&p) = self.sites.last() {
                let x = meet(&self.values, p, q);
                if x <= *self.bounds.last().expect("a bound per site") {
                    self.sites.pop();
                    self.bounds.pop();
                } else {
                    self.sites.push(q);
                    self.bounds.push(x);
                    break;
                }
            }
            if self.sites.is_empty() {
                self.sites.push(q);
                self.bounds.push(f64::NEG_INFINITY);
            }
        }
        if self.sites.is_empty() {
            return; // no finite site: f stays infinite
        }
        let mut k = 0;
        for (q, out) in f.iter_mut().enumerate() {
            while k + 1 < self.sites.len() && self.bounds[k + 1] < q as f64 {
                k += 1;
            }
            let p = self.sites[k];
            let d = (q as f64 - p as f64) * s;
            *out = d * d + self.values[p];
        }
    }
}

/// Otsu's threshold as `skimage.filters.threshold_otsu(values, nbins=256)` computes it for a
/// float32 array, operation by operation in f32, so the threshold is the same float:
///
/// - `np.histogram(values, 256)`: edges `linspace(min, max, 257)` in float32
///   (`i·((max − min)/256) + min`, the last edge `max`); a value's bin is
///   `⌊(v − min)/(max − min)·256⌋` in float32 (256 → 255), corrected by one where that
///   disagrees with the edges (`v < edge[i]` → i − 1; `v ≥ edge[i + 1]` → i + 1, except in
///   the last bin, which holds its right edge);
/// - bin centres `(edge[i] + edge[i + 1])/2`, counts as float32;
/// - `weight1`, `weight2`, `mean1`, `mean2` as cumulative sums from either end, and
///   `variance12[i] = weight1[i]·weight2[i + 1]·(mean1[i] − mean2[i + 1])²` for i < 255;
/// - the threshold is the centre of the first bin where `variance12` is largest (`np.argmax`).
///
/// `None` for an empty slice, a non-finite value (skimage raises), fewer than two distinct
/// values (skimage returns that value itself), a range `max − min` beyond f32, or a range too
/// narrow for 256 distinct float32 bin edges (numpy raises "Too many bins for data range").
pub fn otsu_threshold(values: &[f32]) -> Option<f32> {
    const NBINS: usize = 256;
    let first = *values.first()?;
    let (mut lo, mut hi) = (first, first);
    for &v in values {
        if !v.is_finite() {
            return None;
        }
        lo = lo.min(v);
        hi = hi.max(v);
    }
    let denom = hi - lo;
    if lo == hi || !denom.is_finite() {
        return None;
    }
    // np.linspace(lo, hi, 257, dtype=float32): y = arange·step, then + lo, the last set to hi
    // (a step that underflows to 0 is applied as arange/256·(hi − lo), as numpy does).
    let step = denom / NBINS as f32;
    let mut edges: Vec<f32> = (0..=NBINS)
        .map(|i| if step == 0.0 { i as f32 / NBINS as f32 * denom + lo } else { i as f32 * step + lo })
        .collect();
    edges[NBINS] = hi;
    if edges.windows(2).any(|e| e[0] >= e[1]) {
        return None; // numpy: "Too many bins for data range"
    }
    let mut counts = [0u64; NBINS];
    for &v in values {
        let mut i = (((v - lo) / denom) * NBINS as f32) as usize;
        if i == NBINS {
            i -= 1;
        }
        if v < edges[i] {
            i -= 1;
        }
        if v >= edges[i + 1] && i != NBINS - 1 {
            i += 1;
        }
        counts[i] += 1;
    }
    let counts = counts.map(|c| c as f32);
    let centers: Vec<f32> = edges.windows(2).map(|e| (e[0] + e[1]) / 2.0).collect();
    let weighted: Vec<f32> = counts.iter().zip(&centers).map(|(&c, &x)| c * x).collect();
    let cumsum = |v: &mut dyn Iterator<Item = f32>| {
        let mut acc = 0.0f32;
        v.map(|x| {
            acc += x;
            acc
        })
        .collect::<Vec<f32>>()
    };
    let weight1 = cumsum(&mut counts.iter().copied());
    let mut weight2 = cumsum(&mut counts.iter().rev().copied());
    let mean1: Vec<f32> = cumsum(&mut weighted.iter().copied()).iter().zip(&weight1).map(|(&s, &w)| s / w).collect();
    let mut mean2: Vec<f32> =
        cumsum(&mut weighted.iter().rev().copied()).iter().zip(&weight2).map(|(&s, &w)| s / w).collect();
    weight2.reverse();
    mean2.reverse();
    let mut best = (0, f32::NEG_INFINITY);
    for i in 0..NBINS - 1 {
        let d = mean1[i] - mean2[i + 1];
        let variance = weight1[i] * weight2[i + 1] * (d * d);
        if variance > best.1 {
            best = (i, variance);
        }
    }
    Some(centers[best.0])
}

/// `scipy.ndimage.binary_fill_holes` (default structure: 4-connectivity in the plane) on every
/// 2-D slice perpendicular to `axis` (0 = x, 1 = y, 2 = z): a hole is an unset pixel not
/// connected to the slice's border through unset pixels; holes are set, the rest is the mask.
///
/// # Panics
/// If `mask` does not hold `dims` voxels or `axis > 2`.
pub fn fill_holes_per_slice(mask: &[bool], dims: [usize; 3], axis: usize) -> Vec<bool> {
    let n: usize = dims.iter().product();
    assert_eq!(mask.len(), n, "{} voxels for dims {dims:?} ({n} voxels)", mask.len());
    assert!(axis < 3, "axis {axis} is not 0, 1 or 2");
    if n == 0 {
        return Vec::new();
    }
    let strides = [1, dims[0], dims[0] * dims[1]];
    let (u, v) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let (nu, nv) = (dims[u], dims[v]);
    let index = move |k: usize, i: usize, j: usize| k * strides[axis] + i * strides[u] + j * strides[v];
    // Per slice, u fastest: 0 unset and not (yet) reached from the border, 1 set, 2 unset and
    // reached from the border through unset pixels (4-connected).
    const OPEN: u8 = 0;
    const OUTSIDE: u8 = 2;
    let slices: Vec<Vec<u8>> = (0..dims[axis])
        .into_par_iter()
        .map(|k| {
            let mut state = Vec::with_capacity(nu * nv);
            for j in 0..nv {
                state.extend((0..nu).map(|i| u8::from(mask[index(k, i, j)])));
            }
            let mut stack = Vec::new();
            let visit = |p: usize, state: &mut [u8], stack: &mut Vec<usize>| {
                if state[p] == OPEN {
                    state[p] = OUTSIDE;
                    stack.push(p);
                }
            };
            for i in 0..nu {
                visit(i, &mut state, &mut stack);
                visit(i + nu * (nv - 1), &mut state, &mut stack);
            }
            for j in 0..nv {
                visit(nu * j, &mut state, &mut stack);
                visit(nu - 1 + nu * j, &mut state, &mut stack);
            }
            while let Some(p) = stack.pop() {
                let (i, j) = (p % nu, p / nu);
                if i > 0 {
                    visit(p - 1, &mut state, &mut stack);
                }
                if i + 1 < nu {
                    visit(p + 1, &mut state, &mut stack);
                }
                if j > 0 {
                    visit(p - nu, &mut state, &mut stack);
                }
                if j + 1 < nv {
                    visit(p + nu, &mut state, &mut stack);
                }
            }
            state
        })
        .collect();
    let mut out = vec![true; n];
    for (k, state) in slices.iter().enumerate() {
        for j in 0..nv {
            for (i, &s) in state[nu * j..nu * (j + 1)].iter().enumerate() {
                if s == OUTSIDE {
                    out[index(k, i, j)] = false;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn at(dims: [usize; 3], x: usize, y: usize, z: usize) -> usize {
        x + dims[0] * (y + dims[1] * z)
    }

    #[test]
    fn kernels_are_scipys() {
        // σ = 1.5: radius int(6.5) = 6, weights ∝ exp(−x²/4.5), summing to 1.
        let k = gaussian_kernel(1.5, Order::Smooth);
        assert_eq!(k.len(), 13);
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for (i, &w) in k.iter().enumerate() {
            let x = i as f64 - 6.0;
            assert!((w / k[6] - (-x * x / 4.5).exp()).abs() < 1e-15);
        }
        // The second derivative: φ(x)(x² − σ²)/σ⁴; on x²/2 it gives ≈ 1 (0.995: the tails
        // beyond 4σ are cut).
        let k2 = gaussian_kernel(3.0, Order::Second);
        let k0 = gaussian_kernel(3.0, Order::Smooth);
        assert_eq!(k2.len(), 25);
        for (i, (&w2, &w0)) in k2.iter().zip(&k0).enumerate() {
            let x = i as f64 - 12.0;
            assert!((w2 - w0 * (x * x - 9.0) / 81.0).abs() < 1e-17);
        }
        let on_half_square: f64 = k2.iter().enumerate().map(|(i, w)| w * (i as f64 - 12.0).powi(2) / 2.0).sum();
        assert!((on_half_square - 1.0).abs() < 1e-2, "{on_half_square}");
        // A tiny σ still has scipy's radius-0 kernel.
        assert_eq!(gaussian_kernel(0.1, Order::Smooth), vec![1.0]);
    }

    #[test]
    fn gaussian_of_a_delta_is_the_kernel() {
        // σ = 1.5 mm at spacing [1, 1.5, 0.75]: σ = 1.5, 1, 2 voxels, radii 6, 4, 8 — all inside.
        let dims = [17, 11, 21];
        let spacing = [1.0, 1.5, 0.75];
        let mut v = vec![0.0f32; dims.iter().product()];
        v[at(dims, 8, 5, 10)] = 1.0;
        let g = gaussian_mm(&v, dims, spacing, 1.5);
        let [kx, ky, kz] = [1.5, 1.0, 2.0].map(|s| gaussian_kernel(s, Order::Smooth));
        let mut total = 0.0;
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let w = |k: &[f64], i: usize, c: usize| {
                        let r = k.len() / 2;
                        let d = i as i64 - c as i64 + r as i64;
                        if (0..k.len() as i64).contains(&d) {
                            k[d as usize]
                        } else {
                            0.0
                        }
                    };
                    let expected = w(&kx, x, 8) * w(&ky, y, 5) * w(&kz, z, 10);
                    let got = f64::from(g[at(dims, x, y, z)]);
                    assert!((got - expected).abs() < 1e-8, "({x}, {y}, {z}): {got} vs {expected}");
                    total += got;
                }
            }
        }
        assert!((total - 1.0).abs() < 1e-6);
        // σ = 0 is the identity, as scipy (which skips the axes).
        assert_eq!(gaussian_mm(&v, dims, spacing, 0.0), v);
    }

    #[test]
    fn nearest_mode_keeps_constants_and_replicates_edges() {
        let dims = [5, 4, 3];
        let v = vec![2.5f32; 60];
        for g in gaussian_mm(&v, dims, [1.0, 2.0, 3.0], 4.0) {
            assert!((g - 2.5).abs() < 1e-6);
        }
        // A step along x on a 3-voxel line with a kernel far wider than it: every output is the
        // kernel's mass on each side of the step, the edges extended forever.
        let dims = [3, 1, 1];
        let g = gaussian_mm(&[0.0, 0.0, 1.0], dims, [1.0, 1.0, 1.0], 2.0);
        let k = gaussian_kernel(2.0, Order::Smooth);
        let r = k.len() / 2;
        for (x, &got) in g.iter().enumerate() {
            // Output x sees input x + d for d in −r..=r; clamped index 2 (the 1) for d ≥ 2 − x.
            let expected: f64 = (0..k.len()).filter(|&i| x as i64 + i as i64 - r as i64 >= 2).map(|i| k[i]).sum();
            assert!((f64::from(got) - expected).abs() < 1e-7, "{x}: {got} vs {expected}");
        }
    }

    fn ball(dims: [usize; 3], spacing: [f64; 3], centre: [f64; 3], radius_mm: f64) -> Vec<f32> {
        let mut v = vec![0.0f32; dims.iter().product()];
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let d2: f64 =
                        [x, y, z].iter().enumerate().map(|(a, &i)| ((i as f64 - centre[a]) * spacing[a]).powi(2)).sum();
                    if d2 <= radius_mm * radius_mm {
                        v[at(dims, x, y, z)] = 1.0;
                    }
                }
            }
        }
        v
    }

    #[test]
    fn blob_response_peaks_at_the_centre_of_a_ball() {
        let dims = [40, 32, 36];
        let spacing = [1.0, 1.25, 1.1];
        let centre = [20.0, 16.0, 18.0];
        let radius = 6.0;
        let v = ball(dims, spacing, centre, radius);
        let s = radius / 3f64.sqrt();
        let r = blob_response(&v, dims, spacing, s);
        let c = r[at(dims, 20, 16, 18)];
        assert!(c > 0.3, "centre response {c}");
        let (argmax, max) = r.iter().enumerate().fold((0, f32::MIN), |b, (i, &x)| if x > b.1 { (i, x) } else { b });
        assert_eq!(argmax, at(dims, 20, 16, 18), "max {max} elsewhere");
        // Beyond the ball, a ring of negative response (0.7 of the radius out, at about −8 % of
        // the centre's).
        assert!(r[at(dims, 20 + 10, 16, 18)] < -0.05 * c);
        // Far away (flat zero) it vanishes.
        assert!(r[at(dims, 1, 1, 1)].abs() < 1e-6);
        // The scale: among s = r/√3 · {0.5, 1, 2} the centre responds most at r/√3.
        let small = blob_response(&v, dims, spacing, s / 2.0)[at(dims, 20, 16, 18)];
        let large = blob_response(&v, dims, spacing, s * 2.0)[at(dims, 20, 16, 18)];
        assert!(c > small && c > large, "{small} {c} {large}");
    }

    #[test]
    fn hessian_response_is_a_third_of_the_laplacian_at_a_ball_centre_and_zero_on_a_rod() {
        // The rod runs from x = 26 to the edge (replicated: it goes on for ever), its middle 18
        // voxels, six of the scale's σ, from its one end.
        let dims = [56, 36, 36];
        let spacing = [1.0, 1.2, 1.1];
        let radius = 5.0;
        let mut v = ball(dims, spacing, [12.0, 18.0, 18.0], radius);
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 26..dims[0] {
                    let d2 = ((y as f64 - 18.0) * spacing[1]).powi(2) + ((z as f64 - 18.0) * spacing[2]).powi(2);
                    if d2 <= radius * radius {
                        v[at(dims, x, y, z)] = 1.0;
                    }
                }
            }
        }
        let s = radius / 3f64.sqrt();
        let (log, hessian) = (blob_response(&v, dims, spacing, s), hessian_blob_response(&v, dims, spacing, s));
        let (ball_centre, rod_middle) = (at(dims, 12, 18, 18), at(dims, 44, 18, 18));
        // At the ball's centre the three curvatures are about equal (the lattice is anisotropic).
        let third = log[ball_centre] / 3.0;
        assert!((hessian[ball_centre] - third).abs() < 0.2 * third, "{} vs {third}", hessian[ball_centre]);
        assert!(log[rod_middle] > 0.5 * log[ball_centre], "the Laplacian answers the rod");
        assert!(hessian[rod_middle] < 1e-3 * hessian[ball_centre], "the Hessian does not: {}", hessian[rod_middle]);
        assert!(hessian.iter().all(|&h| h >= 0.0));
    }

    #[test]
    fn blob_response_is_in_mm() {
        // X² + Y² + Z² in mm² has Laplacian 6 mm⁻²·mm² = 6: the response at the centre is −6s²,
        // to the Gaussian's discretisation (about 0.4 % at σ = 1.5–3 voxels).
        let dims = [41, 41, 41];
        let spacing = [1.0, 1.5, 2.0];
        let mut v = vec![0.0f32; dims.iter().product()];
        for z in 0..41 {
            for y in 0..41 {
                for x in 0..41 {
                    v[at(dims, x, y, z)] =
                        [x, y, z].iter().zip(spacing).map(|(&i, s)| ((i as f64 - 20.0) * s).powi(2)).sum::<f64>()
                            as f32;
                }
            }
        }
        let s = 3.0;
        let got = f64::from(blob_response(&v, dims, spacing, s)[at(dims, 20, 20, 20)]);
        assert!((got / (-6.0 * s * s) - 1.0).abs() < 0.01, "{got}");
        assert!(blob_response(&v, dims, spacing, 0.0).iter().all(|&x| x == 0.0));
    }

    /// The distance from the definition: to every unset voxel.
    fn brute_edt(mask: &[bool], dims: [usize; 3], spacing: [f64; 3]) -> Vec<f64> {
        let unset: Vec<[usize; 3]> = (0..mask.len())
            .filter(|&i| !mask[i])
            .map(|i| [i % dims[0], (i / dims[0]) % dims[1], i / (dims[0] * dims[1])])
            .collect();
        (0..mask.len())
            .map(|i| {
                let p = [i % dims[0], (i / dims[0]) % dims[1], i / (dims[0] * dims[1])];
                unset
                    .iter()
                    .map(|u| (0..3).map(|a| ((p[a] as f64 - u[a] as f64) * spacing[a]).powi(2)).sum::<f64>())
                    .fold(f64::INFINITY, f64::min)
                    .sqrt()
            })
            .collect()
    }

    #[test]
    fn distance_to_a_single_hole() {
        let dims = [5, 6, 7];
        let spacing = [0.7, 1.3, 2.5];
        let mut mask = vec![true; 210];
        mask[at(dims, 2, 3, 4)] = false;
        let d = distance_inside_mm(&mask, dims, spacing);
        for z in 0..7 {
            for y in 0..6 {
                for x in 0..5 {
                    let expected = ((x as f64 - 2.0) * 0.7).hypot((y as f64 - 3.0) * 1.3).hypot((z as f64 - 4.0) * 2.5);
                    let got = d[at(dims, x, y, z)];
                    assert!((got - expected).abs() < 1e-12, "({x}, {y}, {z}): {got} vs {expected}");
                }
            }
        }
        assert_eq!(d[at(dims, 2, 3, 4)], 0.0);
        // No background at all: infinite everywhere; nothing set: zero everywhere.
        assert!(distance_inside_mm(&[true; 210], dims, spacing).iter().all(|d| *d == f64::INFINITY));
        assert!(distance_inside_mm(&[false; 210], dims, spacing).iter().all(|d| *d == 0.0));
    }

    #[test]
    fn distance_equals_the_definition_on_random_masks() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for (dims, density) in [([9, 8, 7], 0.9), ([13, 5, 11], 0.97), ([1, 12, 10], 0.8), ([6, 6, 1], 0.6)] {
            let spacing = [0.5 + rng.gen::<f64>() * 3.0, 0.5 + rng.gen::<f64>() * 3.0, 0.5 + rng.gen::<f64>() * 3.0];
            let n: usize = dims.iter().product();
            let mask: Vec<bool> = (0..n).map(|_| rng.gen::<f64>() < density).collect();
            let got = distance_inside_mm(&mask, dims, spacing);
            for (i, (g, e)) in got.iter().zip(brute_edt(&mask, dims, spacing)).enumerate() {
                assert!((g - e).abs() <= 1e-12 * e.max(1.0), "{dims:?} voxel {i}: {g} vs {e}");
            }
        }
    }

    #[test]
    fn otsu_between_the_modes_and_skimages_ties() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut values: Vec<f32> = (0..3000).map(|_| rng.gen::<f32>()).collect();
        values.extend((0..1000).map(|_| 10.0 + rng.gen::<f32>()));
        let t = otsu_threshold(&values).expect("two modes");
        assert!(t > 1.0 && t < 10.0, "{t}");
        // Two values: every split between the two occupied bins has the same variance, and
        // skimage takes the first — the centre of bin 0, 1/512 for {0, 1}.
        assert_eq!(otsu_threshold(&[0.0, 1.0, 1.0, 0.0, 1.0]), Some(1.0 / 512.0));
        assert_eq!(otsu_threshold(&[]), None);
        assert_eq!(otsu_threshold(&[4.0, 4.0]), None);
        assert_eq!(otsu_threshold(&[0.0, f32::NAN, 1.0]), None);
        assert_eq!(otsu_threshold(&[-f32::MAX, f32::MAX]), None);
        assert_eq!(otsu_threshold(&[1.0, 1.0 + f32::EPSILON]), None);
    }

    #[test]
    fn fill_holes_of_a_ring() {
        // A diamond ring |dx| + |dy| = 2 around (3, 3) in the z = 2 plane: closed for
        // 4-connectivity although its pixels touch only diagonally.
        let dims = [7, 7, 5];
        let mut mask = vec![false; 245];
        for y in 0..7i64 {
            for x in 0..7i64 {
                if (x - 3).abs() + (y - 3).abs() == 2 {
                    mask[at(dims, x as usize, y as usize, 2)] = true;
                }
            }
        }
        let filled = fill_holes_per_slice(&mask, dims, 2);
        for (i, (&m, &f)) in mask.iter().zip(&filled).enumerate() {
            let (x, y, z) = ((i % 7) as i64, ((i / 7) % 7) as i64, i / 49);
            let inside = z == 2 && (x - 3).abs() + (y - 3).abs() <= 1;
            assert_eq!(f, m || inside, "({x}, {y}, {z})");
        }
        // Across the ring (slices along x or y) there is no hole.
        assert_eq!(fill_holes_per_slice(&mask, dims, 0), mask);
        assert_eq!(fill_holes_per_slice(&mask, dims, 1), mask);
        // An open ring leaks: a gap to the border through the ring keeps the inside empty.
        let mut open = mask.clone();
        open[at(dims, 3, 1, 2)] = false;
        assert_eq!(fill_holes_per_slice(&open, dims, 2), open);
        // A ring around the border itself leaves its centre a hole in every orientation.
        let dims = [3, 3, 3];
        let mut shell = vec![true; 27];
        shell[at(dims, 1, 1, 1)] = false;
        for axis in 0..3 {
            assert!(fill_holes_per_slice(&shell, dims, axis).iter().all(|&v| v));
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let dims = [23, 17, 19];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let v: Vec<f32> = (0..dims.iter().product::<usize>()).map(|_| rng.gen()).collect();
        let spacing = [1.1, 0.9, 2.3];
        let run = || (gaussian_mm(&v, dims, spacing, 2.0), blob_response(&v, dims, spacing, 2.0));
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(run);
        let three = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap().install(run);
        assert_eq!(one, three);
    }
}
